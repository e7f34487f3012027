"""The sensor rig: renders one Observation for a pose from a single main ray cast.

Forward colour and depth share one 640x480 cast (depth is the ray parameter, colour is
shaded from the same hits); the two echo sounders are tiny extra casts.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from cavenav.sensors.camera import CameraIntrinsics, camera_to_world, look_frame
from cavenav.sensors.kernels import fill_rays, shade_frame
from cavenav.sensors.optics import LUT_SCALE, Optics, rock_albedo, tone_lut
from cavenav.types import Observation, Pose
from cavenav.world.raycast import RayCaster

__all__ = ["SensorConfig", "SensorRig"]

_UP = np.array([0.0, 0.0, 1.0])
_SEDIMENT = np.array([0.46, 0.40, 0.30], np.float32)


@dataclass(frozen=True)
class SensorConfig:
    """Sensor set-up of SPEC section 2.

    Attributes:
        camera: forward RGB and depth intrinsics (co-located, identical).
        depth_min_m, depth_max_m: range mapped to black and white in the depth PNG.
        camera_offset_m: the camera sits this far ahead of the vehicle's centre (the
            BlueROV2's front dome), so depth is measured from the nose.
        sounder: "camera" emulates each echo sounder as the reference set-up does, with an
            upward or downward depth camera whose minimum planar depth is taken; "beam"
            takes the minimum range over a cone of rays, like a single-beam sounder.
        sounder_fov_deg: full field of view of either model. 25 degrees is the beam width
            of a Ping2-class sounder; with the forward camera's 53 degrees, a round 5 m
            passage reads about 1.7 m to the ceiling from its centre (the side walls).
        sounder_pixels: resolution of the emulating depth cameras; the minimum of a
            32x24 image is as good as a full frame's for a smooth ceiling and costs nothing.
        sounder_max_range_m: reading when nothing is in range.
        optics: water and light parameters of the colour image.
        albedo_seed: seeds the rock colour field.
    """

    camera: CameraIntrinsics = field(default_factory=CameraIntrinsics)
    depth_min_m: float = 0.0
    depth_max_m: float = 20.0
    camera_offset_m: float = 0.2
    sounder: Literal["camera", "beam"] = "camera"
    sounder_fov_deg: float = 25.0
    sounder_pixels: tuple[int, int] = (32, 24)
    sounder_max_range_m: float = 50.0
    optics: Optics = field(default_factory=Optics)
    albedo_seed: int = 0


def _beam_directions(cone_deg: float, rings: int = 3, per_ring: int = 8) -> np.ndarray:
    """(n, 3) unit directions filling a cone around +z, for the narrow-beam sounder."""
    dirs = [np.array([0.0, 0.0, 1.0])]
    half = np.radians(cone_deg) / 2.0
    for k in range(1, rings + 1):
        theta = half * k / rings
        for j in range(per_ring):
            phi = 2 * np.pi * j / per_ring
            dirs.append(
                np.array([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)])
            )
    return np.array(dirs)


class SensorRig:
    """Renders observations of one cave; holds the precomputed rays and rock colours."""

    def __init__(self, caster: RayCaster, config: SensorConfig | None = None):
        self.caster = caster
        self.config = config or SensorConfig()
        cfg = self.config
        self._pixel_dirs = cfg.camera.directions.reshape(-1, 3)
        self._ray_length = np.linalg.norm(self._pixel_dirs, axis=1)  # rotation-invariant
        self._rays = np.empty((len(self._pixel_dirs), 6), np.float32)
        if cfg.sounder == "camera":
            w, h = cfg.sounder_pixels
            focal_mm = (
                0.5 * cfg.camera.sensor_width_mm / math.tan(math.radians(cfg.sounder_fov_deg) / 2)
            )
            sounder = CameraIntrinsics(w, h, focal_mm, cfg.camera.sensor_width_mm)
            self._sounder_dirs = sounder.directions.reshape(-1, 3)
            self._sounder_planar = True
        else:
            self._sounder_dirs = _beam_directions(cfg.sounder_fov_deg)
            self._sounder_planar = False
        albedo = rock_albedo(caster.mesh, cfg.albedo_seed)
        # One colour per triangle (mean of its corners): one gather per pixel when shading.
        self._face_albedo = albedo[caster.mesh.faces].mean(axis=1).astype(np.float32)

    def camera_position(self, pose: Pose) -> np.ndarray:
        return pose.position + self.config.camera_offset_m * pose.forward

    def forward_frame(self, pose: Pose) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Planar depth (H, W) float32 metres, its PNG (H, W) uint8 and colour (H, W, 3) uint8."""
        cfg = self.config
        optics = cfg.optics
        rot = camera_to_world(pose).astype(np.float32)
        # Write origins and directions straight into the (n, 6) ray buffer Open3D reads.
        rays = self._rays
        fill_rays(self._pixel_dirs, rot, self.camera_position(pose).astype(np.float32), rays)
        dirs = rays[:, 3:]
        raw = self.caster.cast_raw_rays(rays)
        n = len(rays)
        rgb = np.empty((n, 3), np.uint8)
        depth_png = np.empty(n, np.uint8)
        shade_frame(
            raw["t_hit"],
            raw["primitive_ids"],
            raw["primitive_normals"],
            dirs,
            self._ray_length,
            self._face_albedo,
            _SEDIMENT,
            np.asarray(optics.attenuation, np.float32),
            optics.light_power,
            np.asarray(optics.ambient, np.float32),
            np.asarray(optics.veil, np.float32),
            np.asarray(optics.open_water, np.float32),
            optics.gains,
            tone_lut(optics.exposure),
            LUT_SCALE,
            cfg.depth_min_m,
            cfg.depth_max_m,
            rgb,
            depth_png,
        )
        shape = (cfg.camera.height, cfg.camera.width)
        return raw["t_hit"].reshape(shape), depth_png.reshape(shape), rgb.reshape(*shape, 3)

    def echo_sounders(self, pose: Pose) -> tuple[float, float]:
        """(d_top, d_bottom) in metres from the vehicle's centre."""
        readings = []
        for sign in (1.0, -1.0):
            # An up- (down-) looking camera: optical axis +-z, image x along the vehicle's right.
            rot = look_frame(sign * _UP, pose.right if sign > 0 else -pose.right)
            dirs = self._sounder_dirs @ rot.T
            t = self.caster.first_hit(pose.position, dirs)
            if not self._sounder_planar:
                t = t * np.linalg.norm(dirs, axis=1)
            readings.append(float(min(np.min(t), self.config.sounder_max_range_m)))
        return readings[0], readings[1]

    def observe(self, pose: Pose, step: int = 0) -> Observation:
        """Render everything a pilot sees at ``pose``."""
        cfg = self.config
        depth, depth_png, rgb = self.forward_frame(pose)
        d_top, d_bottom = self.echo_sounders(pose)
        return Observation(
            rgb=rgb,
            depth_m=depth,
            depth_png=depth_png,
            d_top=d_top,
            d_bottom=d_bottom,
            depth_range=(cfg.depth_min_m, cfg.depth_max_m),
            step=step,
        )
