"""The depth a reader may rely on: the depth image, with the imaging sonar's ranges where
the depth camera found nothing.

A stereo camera leaves pixels unmatched (`cavenav.sensors.stereo`): beyond the visibility,
in silt, on bare rock. Those pixels are unknown, never free space. The geometric pilot, the
safety shield and the cave map all read depth through `readable_depth`, which gives
each unknown pixel:

- where the sonar's fan covers its bearing (a beam pinged in the last `MAX_AGE_S`):
  the planar depth of the nearest echo along that beam (`echo_ranges`), because sound is
  not blinded by what blinds light; above or below the beam's vertical aperture, nearer
  still where the pixel's ray meets the ceiling or the floor the echo sounders range
  (assumed to go on level: the one inference made, and never farther than the sonar);
- elsewhere: `UNKNOWN_AS_M`, an obstacle near enough that no forward move is allowed
  toward it (inside the rules' 1.5 m no-forward distance) yet farther than the body's
  keep-clear margin, so that the vehicle turns to look rather than backing away from
  nothing.

Small holes (within `HOLE_PX` of a match: an edge's occlusion, a dropped speck) take the
nearest matched depth around them first, as a stereo camera's hole filling does.

The exact depth image, and a stereo one without unknown pixels, pass unchanged.
"""

from __future__ import annotations

import functools
import math

import numpy as np

from cavenav.core.types import Observation, SonarImage
from cavenav.sensors.depth import normalise_depth, pixel_slopes
from cavenav.world.procedural import cpu_independent

__all__ = ["ECHO_THRESHOLD", "UNKNOWN_AS_M", "echo_ranges", "readable_depth"]

UNKNOWN_AS_M = 1.0
MAX_AGE_S = 10.0  # older echoes say too little of where the vehicle is now
HOLE_PX = 6  # holes this many pixels from a match are filled from it
# The 8-bit echo strength that counts as rock: 15 dB below a wall met square on (the
# display spans 45 dB): a wall or a boulder ahead, met at less than about 80 degrees of
# incidence, is above it; a dense silt cloud's haze (about -28 dB) and the receiver's
# noise within 20 m are below it. Measured on the crawl in a silt-out (seeds 1000-1004,
# stereo depth, multibeam): at -22 dB floor and ceiling met at grazing incidence a few
# metres ahead read as rock, and the geometric pilot got 1 of 5 through, at -15 dB 4 of
# 5, with no collision either way.
ECHO_THRESHOLD = 170  # (-15 + 45) / 45 * 255


def echo_ranges(sonar: SonarImage, threshold: int = ECHO_THRESHOLD) -> np.ndarray:
    """(beams,) the slant range of each beam's first echo at or above ``threshold``
    (``range_m`` where it found none), shortened by how far the vehicle has moved since it
    was pinged (a scanning head's angles swept steps ago: the echo may be that much nearer
    now); NaN for a beam never pinged or older than `MAX_AGE_S`."""
    strong = sonar.echoes >= threshold
    first = np.argmax(strong, axis=1)
    ranges = np.where(strong.any(axis=1), (first + 0.5) * sonar.bin_m, sonar.range_m)
    if sonar.moved_m is not None:
        ranges = np.maximum(ranges - sonar.moved_m, 0.0)
    return np.where(sonar.age_s <= MAX_AGE_S, ranges, np.nan)


def readable_depth(observation: Observation) -> tuple[np.ndarray, np.ndarray | None]:
    """(H, W) uint8 the observation's depth PNG with its unknown pixels filled (module
    docstring), and (H, W) bool the pixels filled by a guess rather than a range (neither
    a match, a filled hole nor the sonar's echo): what a reader may use to stop short, never
    to remember as rock. The PNG itself, and None, when no pixel is unknown."""
    png = observation.depth_png
    if observation.depth_source != "stereo" or not observation.has_depth:
        return png, None
    if _last is not None and _last[0] is observation:  # the shield, the pilot, the map
        return _last[1]
    unknown = np.isnan(observation.depth_m)
    if not unknown.any():
        return png, None
    fill = np.full(png.shape, UNKNOWN_AS_M, np.float32)
    ranged = np.zeros(png.shape, bool)
    if observation.sonar is not None:
        ranged = _sonar_depth(observation, fill)
    hole = _hole_depth(observation.depth_m)
    ranged |= np.isfinite(hole)
    fill = np.where(np.isfinite(hole), hole, fill)
    filled = png.copy()
    filled[unknown] = normalise_depth(fill[unknown], *observation.depth_range)
    read = (filled, unknown & ~ranged)
    _remember(observation, read)
    return read


# The last observation read, and what it read: three readers read each observation.
_last: tuple[Observation, tuple[np.ndarray, np.ndarray | None]] | None = None


def _remember(observation: Observation, read: tuple[np.ndarray, np.ndarray | None]) -> None:
    global _last
    _last = (observation, read)


def _hole_depth(depth_m: np.ndarray) -> np.ndarray:
    """(H, W) the nearest matched depth within `HOLE_PX` of each pixel (``inf`` where none):
    a small hole (an edge's occlusion, a speck) takes the nearest side, as a stereo
    camera's hole filling fills it."""
    from scipy import ndimage

    known = np.where(np.isnan(depth_m), np.inf, depth_m)
    return ndimage.grey_erosion(known, size=(2 * HOLE_PX + 1, 2 * HOLE_PX + 1))


@functools.lru_cache(maxsize=4)
def _pixel_angles(shape: tuple[int, int], hfov_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """(H, W) each pixel's bearing (right of ahead) and elevation, degrees, with the C
    library's arctangent (`cpu_independent`: the same on every CPU), once per camera."""
    leftward, upward = pixel_slopes(shape, hfov_deg, 1, dtype=np.float64)
    bearing = np.degrees(cpu_independent(math.atan, -leftward))
    elevation = np.degrees(cpu_independent(math.atan, upward / np.sqrt(1.0 + leftward**2)))
    return bearing, elevation


def _sonar_depth(observation: Observation, fill: np.ndarray) -> np.ndarray:
    """Write into ``fill`` the planar depth, from the camera, of the sonar's nearest echo
    at every pixel inside a fresh beam and the vertical aperture; (H, W) bool those."""
    sonar = observation.sonar
    assert sonar is not None
    leftward, upward = pixel_slopes(fill.shape, observation.hfov_deg, 1)
    bearing, elevation = _pixel_angles(fill.shape, observation.hfov_deg)
    ranges = echo_ranges(sonar)
    now = sonar.bearings_deg + (0.0 if sonar.turned_deg is None else sonar.turned_deg)
    now = (now + 180.0) % 360.0 - 180.0  # where each beam lies now, right of ahead
    order = np.argsort(now)
    beams, sorted_bearings = order, now[order]
    at = np.clip(np.searchsorted(sorted_bearings, bearing), 1, len(order) - 1)
    nearer = np.abs(sorted_bearings[at - 1] - bearing) < np.abs(sorted_bearings[at] - bearing)
    beam = beams[np.where(nearer, at - 1, at)]
    pitch = np.median(np.diff(sorted_bearings)) if len(order) > 1 else 360.0
    inside = np.abs(now[beam] - bearing) <= max(pitch, sonar.beam_width_deg) / 2
    slant = ranges[beam]
    inside &= np.isfinite(slant)
    planar = slant / np.sqrt(1.0 + leftward**2 + upward**2) - observation.camera_offset_m
    # Above and below the aperture the sonar says nothing: there the ray stops where it
    # meets the ceiling or the floor as the sounders put them, if nearer.
    beyond = np.abs(elevation) > sonar.aperture_deg / 2
    height = np.where(upward > 0, observation.d_top, observation.d_bottom)
    with np.errstate(divide="ignore", invalid="ignore"):
        meets = np.where(np.isfinite(height), height / np.abs(upward), 0.0)
    planar = np.where(beyond, np.minimum(planar, meets), planar)
    fill[inside] = np.maximum(planar[inside], 0.0)
    return inside
