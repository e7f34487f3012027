"""The camera's white balance: the BlueROV2 camera's own, a fixed temperature, grey world.

The camera a BlueROV2 has carried since mid-2017 is Blue Robotics' Low-Light HD USB
Camera: a Sony IMX322 sensor, which gives raw Bayer colour and balances nothing itself,
behind a USB bridge that develops the image and codes it as H.264. It lists as "H264 USB
Camera" (bluerobotics/ardusub-gitbook, ``developers/cameras.md``), USB id 05a3:9422, by
which the Companion software found it (ArduPilot/companion,
``RPI2/Raspbian/start_video.sh``). Its white balance is a UVC camera's: two V4L2
controls, ``white_balance_automatic`` (on by default) and ``white_balance_temperature``,
the white point as a colour temperature, used when the automatic one is off: 2,800 to
6,500 K, 4,600 K by default, as a control panel written for this camera sets them
(Sayantani-Bhattacharya/Universal_Camera_Control_Pannel, ``pannel.py``, "tested on: Blue
ROV low-light monocular HD") and as USB cameras with the same kind of bridge list them;
the least V4L2 asks of a driver, 2,800 (incandescent) to 6,500 (daylight) (the Linux
kernel's V4L2 documentation, "User Controls"). How the bridge's automatic mode picks its
temperature is not published.

So we model it as a UVC camera's auto white balance works: it estimates the light from
the frame's mean colour (grey world: the scene averages to grey), takes the colour
temperature of the black body whose colour lies nearest (in log chromaticity, the locus
of `lamp_colour`), holds it within the control's range, and applies that temperature's
gains. A temperature moves colour along the locus only, red against blue. Water's cast
lies off it (water takes red and leaves green and blue, a colour no black body has) and
past its 6,500 K end; so the camera leaves clear water's blue-green, which grey world,
free to scale each channel, would take out. Lamps warmer than daylight it corrects, down
to 2,800 K.

The estimate reads the mean colour the rig already meters for its exposure
(`rig.grid_mean`, over the coarse shading grid): a few microseconds a frame, no pass
over the pixels. Every frame is balanced on its own, as it is exposed: a real camera
settles over a few frames, which a render of one pose cannot show.
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

from cavenav.sensors.optics import KELVIN_LIMITS, Optics, lamp_colour
from cavenav.world.procedural import cpu_independent

__all__ = ["camera_kelvin", "kelvin_gains", "locus_kelvin", "white_balance_gains"]

# The locus is tabulated in mireds (10^6 / K), along which colour shifts about evenly
# (equal steps in 1 / T move log(R/G) and log(B/G) by about equal amounts, by Wien's law):
# every 2.5 mireds within `KELVIN_LIMITS` (1,001-37,956 K; beyond, its ends hold), 390
# points between which it is nearly straight, one of them at 6,500 K, the sensor's white,
# so that daylight's gains are 1 exactly.
_STEP = 2.5
_WHITE = 1e6 / 6500.0
_MIREDS = _WHITE + _STEP * np.arange(
    math.ceil((1e6 / KELVIN_LIMITS[1] - _WHITE) / _STEP),
    math.floor((1e6 / KELVIN_LIMITS[0] - _WHITE) / _STEP) + 1,
)


@lru_cache(maxsize=1)
def _locus() -> np.ndarray:
    """(n, 2) float64 log(R / G), log(B / G) of a black body at each of `_MIREDS`, in
    the camera's bands (`lamp_colour`: 6,500 K is white, (0, 0)). Built once (30 ms),
    with the C library's log, so the same on every CPU (`cpu_independent`)."""
    colours = np.array([lamp_colour(1e6 / mired) for mired in _MIREDS], np.float64)
    return cpu_independent(math.log, colours[:, [0, 2]])


def locus_kelvin(mean: np.ndarray) -> float:
    """The colour temperature, in kelvin, of the point of the black-body locus nearest
    the colour ``mean`` (3,), in log chromaticity (log(R / G), log(B / G)), within
    `KELVIN_LIMITS`: what a camera's auto white balance takes the light to be when it
    assumes that the scene averages to grey. A few microseconds: one pass over the
    table for its nearest point, then the segments on either side of it in scalars.
    """
    m = np.maximum(np.asarray(mean, np.float64), 1e-9)
    x, y = math.log(m[0] / m[1]), math.log(m[2] / m[1])
    locus = _locus()
    i = int(np.argmin((locus[:, 0] - x) ** 2 + (locus[:, 1] - y) ** 2))
    best = (math.inf, 0.0)  # (squared distance, mireds) of the nearest point so far
    for j in (i - 1, i):
        if 0 <= j < len(locus) - 1:
            (x0, y0), (x1, y1) = locus[j].tolist(), locus[j + 1].tolist()
            dx, dy = x1 - x0, y1 - y0
            along = min(max(((x - x0) * dx + (y - y0) * dy) / (dx * dx + dy * dy), 0.0), 1.0)
            gap = (x0 + along * dx - x) ** 2 + (y0 + along * dy - y) ** 2
            best = min(best, (gap, float(_MIREDS[j]) + along * _STEP))
    return 1e6 / best[1]


def kelvin_gains(kelvin: float) -> np.ndarray:
    """(3,) float64 white-balance gains for a white point of ``kelvin``: those that make
    a black body of that temperature white, 1 / `lamp_colour` with green 1 (interpolated
    along the tabulated locus; 1, 1, 1 at 6,500 K). Lower temperatures lift blue and
    lower red."""
    locus = _locus()
    position = (1e6 / kelvin - float(_MIREDS[0])) / _STEP
    j = min(max(int(position), 0), len(locus) - 2)
    along = min(max(position - j, 0.0), 1.0)
    (red0, blue0), (red1, blue1) = locus[j].tolist(), locus[j + 1].tolist()
    red, blue = red0 + along * (red1 - red0), blue0 + along * (blue1 - blue0)
    return np.array([math.exp(-red), 1.0, math.exp(-blue)])


def camera_kelvin(mean: np.ndarray, optics: Optics) -> float:
    """The white point, in kelvin, that the camera of ``optics`` uses for a frame whose
    mean colour is ``mean`` (3,): the fixed `Optics.white_balance_kelvin` when set, else
    its auto white balance's `locus_kelvin`, held within `Optics.white_balance_range`."""
    if optics.white_balance_kelvin is not None:
        return optics.white_balance_kelvin
    low, high = optics.white_balance_range
    return min(max(locus_kelvin(mean), low), high)


def white_balance_gains(mean: np.ndarray, optics: Optics) -> np.ndarray:
    """(3,) float64 gains of the white balance of ``optics`` for a frame whose mean colour
    is ``mean`` (3,) float64, each channel at least 1e-9 (`Optics.white_balance_mode`).

    Grey world (`Optics.white_balance` set; the camera's white balance before it was the
    BlueROV2 camera's own): every channel scaled toward the mean's luminance by that
    strength, as log-distance, within 0.25-4.
    Otherwise the gains of `camera_kelvin`'s white point.
    """
    if optics.white_balance is not None:
        luminance = float(mean @ (0.25, 0.5, 0.25))
        return np.clip((luminance / mean) ** optics.white_balance, 0.25, 4.0)
    return kelvin_gains(camera_kelvin(mean, optics))
