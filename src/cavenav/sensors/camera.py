"""Pinhole camera geometry: intrinsics and the rays of every pixel.

Camera frame: x right, y down, z along the optical axis. Each pixel's ray direction is
scaled so its z component is 1, so the ray parameter of a hit *is* the planar depth
(what a depth camera reports), with no division per pixel.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from cavenav.types import Pose

__all__ = ["CameraIntrinsics", "camera_to_world", "look_frame"]


@dataclass(frozen=True)
class CameraIntrinsics:
    """A pinhole camera; the defaults are SPEC section 2's forward camera.

    36 mm focal length on a 36 mm wide sensor gives f = 640 px over 640 px, a horizontal
    field of view of 2 * atan(0.5) = 53.13 degrees (and 41.1 degrees vertically at 4:3).
    """

    width: int = 640
    height: int = 480
    focal_mm: float = 36.0
    sensor_width_mm: float = 36.0

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
