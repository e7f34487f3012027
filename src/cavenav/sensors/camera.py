"""Pinhole camera geometry: intrinsics and the rays of every pixel.

Camera frame: x right, y down, z along the optical axis. Each pixel's ray direction is
scaled so its z component is 1, so the ray parameter of a hit *is* the planar depth
(what a depth camera reports), with no division per pixel.
"""

from __future__ import annotations

import math
import numbers
import re
from dataclasses import dataclass, replace
from functools import cached_property

import numpy as np

from cavenav.core.errors import ConfigError
from cavenav.core.types import Pose

__all__ = [
    "CameraIntrinsics",
    "camera_to_world",
    "look_frame",
    "parse_resolution",
    "pixel_size",
]


@dataclass(frozen=True)
class CameraIntrinsics:
    """A pinhole camera; the defaults are SPEC section 2's forward camera.

    36 mm focal length on a 36 mm wide sensor gives f = 640 px over 640 px, a horizontal
    field of view of 2 * atan(0.5) = 53.13 degrees (and 41.1 degrees vertically at 4:3).

    Pixels are square and the focal length in pixels scales with the width, so the
    horizontal field of view is the same at every resolution (`with_resolution`); the
    vertical one follows the aspect ratio: 160x120 sees 53.1 x 41.1 degrees as 640x480
    does, 84x84 sees 53.1 x 53.1.
    """

    width: int = 640
    height: int = 480
    focal_mm: float = 36.0
    sensor_width_mm: float = 36.0

    def __post_init__(self) -> None:
        # A zero, negative or fractional size fails deep inside the ray buffer's reshape;
        # refuse it where it is set. numpy integers are welcome, stored as int (for JSON).
        width, height = pixel_size((self.width, self.height), "camera resolution")
        object.__setattr__(self, "width", width)
        object.__setattr__(self, "height", height)

    def with_resolution(self, width: int, height: int) -> CameraIntrinsics:
        """The same lens and sensor at ``width`` x ``height`` pixels: the horizontal field
        of view is kept, the vertical one follows the aspect ratio (see above).

        Raises:
            ConfigError: a size that is not a positive whole number.
        """
        return replace(self, width=width, height=height)

    @property
    def focal_px(self) -> float:
        return self.focal_mm / self.sensor_width_mm * self.width

    @property
    def hfov_deg(self) -> float:
        return math.degrees(2.0 * math.atan(0.5 * self.width / self.focal_px))

    @property
    def vfov_deg(self) -> float:
        return math.degrees(2.0 * math.atan(0.5 * self.height / self.focal_px))

    @cached_property
    def directions(self) -> np.ndarray:
        """(H, W, 3) float32 camera-frame ray directions with unit z, through pixel centres."""
        u = (np.arange(self.width, dtype=np.float32) + 0.5 - 0.5 * self.width) / self.focal_px
        v = (np.arange(self.height, dtype=np.float32) + 0.5 - 0.5 * self.height) / self.focal_px
        uu, vv = np.meshgrid(u, v)
        return np.stack([uu, vv, np.ones_like(uu)], axis=-1)


def look_frame(forward: np.ndarray, right: np.ndarray) -> np.ndarray:
    """(3, 3) rotation whose columns are the camera's x (right), y (down), z (forward)."""
    f = np.asarray(forward, np.float64) / np.linalg.norm(forward)
    r = np.asarray(right, np.float64) / np.linalg.norm(right)
    # z x x = y in a right-handed camera frame (written out: np.cross costs 20x on 3-vectors)
    down = np.array(
        [f[1] * r[2] - f[2] * r[1], f[2] * r[0] - f[0] * r[2], f[0] * r[1] - f[1] * r[0]]
    )
    return np.stack([r, down, f], axis=1)


def camera_to_world(pose: Pose) -> np.ndarray:
    """(3, 3) rotation of the forward camera of a vehicle at ``pose`` (no pitch or roll)."""
    return look_frame(pose.forward, pose.right)


# The largest side of an image, as a scenario file's [sensors] bounds it: beyond 8K video
# (7680 x 4320); 100000x1 crashed the JPEG encoder and 30000x30000 ran out of memory.
MAX_SIDE_PX = 8192


def pixel_size(value: object, what: str = "resolution") -> tuple[int, int]:
    """``value`` as (width, height) in pixels: two whole numbers above 0, in any sequence.

    Raises:
        ConfigError: naming ``what`` and the value, with an example.
    """
    pair = tuple(value) if isinstance(value, list | tuple | np.ndarray) else (value,)
    whole = all(isinstance(v, numbers.Integral) and not isinstance(v, bool) for v in pair)
    if len(pair) != 2 or not whole or not _within(*pair):
        raise ConfigError(
            f"{what} {value!r}: give [width, height] as two whole numbers of pixels from 1 "
            f"to {MAX_SIDE_PX}, e.g. [160, 120]"
        )
    return int(pair[0]), int(pair[1])


def _within(*sides: int) -> bool:
    return all(0 < side <= MAX_SIDE_PX for side in sides)


def parse_resolution(text: str, what: str = "--resolution") -> tuple[int, int]:
    """ "160x120" -> (160, 120): width x height in pixels, as the command line writes it.

    Raises:
        ConfigError: naming ``what`` and the text that is not WxH with positive sizes.
    """
    match = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", text)
    if not match or not _within(int(match[1]), int(match[2])):
        raise ConfigError(
            f"{what}: '{text}' is not a resolution; write WIDTHxHEIGHT in pixels from 1 to "
            f"{MAX_SIDE_PX}, e.g. 160x120 or 84x84"
        )
    return int(match[1]), int(match[2])
