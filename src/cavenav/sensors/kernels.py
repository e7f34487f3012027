"""Per-pixel kernels compiled with numba: everything after the ray cast, in one pass.

The sensor step must cost little more than its ray cast (target: 1.5x). In numpy each
formula is a separate pass over 307,200 pixels with its temporaries; here one parallel
loop reads each hit once and writes the colour and the depth PNG directly.
"""

from __future__ import annotations

import math

import numba
import numpy as np

# OpenMP, else numba's own work queue; never TBB, whose old system builds only warn.
numba.config.THREADING_LAYER_PRIORITY = ["omp", "workqueue", "tbb"]  # type: ignore[attr-defined]

__all__ = ["fill_rays", "shade_frame"]

_NO_HIT = np.uint32(0xFFFFFFFF)


@numba.njit(parallel=True, fastmath=True, cache=True)
def shade_frame(
    t: np.ndarray,  # (n,) float32 ray parameter = planar depth, inf where no hit
    triangle: np.ndarray,  # (n,) uint32 hit triangle, 0xFFFFFFFF where no hit
    normals: np.ndarray,  # (n, 3) float32 triangle normals (either orientation)
    directions: np.ndarray,  # (n, 3) float32 world ray directions, unit optical component
    ray_length: np.ndarray,  # (n,) float32 length of each direction
    face_albedo: np.ndarray,  # (m, 3) float32 rock reflectance per triangle
    sediment: np.ndarray,  # (3,) float32 reflectance of up-facing floors
    attenuation: np.ndarray,  # (3,) float32 per-channel attenuation, 1/m
    light_power: float,
    ambient: np.ndarray,  # (3,) float32
    veil: np.ndarray,  # (3,) float32
    open_water: np.ndarray,  # (3,) float32 radiance of rays leaving the cave
    gains: np.ndarray,  # (3,) float32 camera white-balance gains
    lut: np.ndarray,  # (k,) uint8 tone map from linear radiance * lut_scale
    lut_scale: float,
    d_min: float,
    d_max: float,
    rgb: np.ndarray,  # (n, 3) uint8 out
    depth_png: np.ndarray,  # (n,) uint8 out
) -> None:
    """Shade every pixel and normalise its depth (see `cavenav.sensors.optics`)."""
    last = lut.shape[0] - 1
    for i in numba.prange(t.shape[0]):
        depth = t[i]
        norm = (min(depth, d_max) - d_min) / (d_max - d_min)
        depth_png[i] = np.uint8(min(max(norm, 0.0), 1.0) * 255.0 + 0.5)
        tri = triangle[i]
        if tri == _NO_HIT:
            for c in range(3):
                rgb[i, c] = lut[min(int(gains[c] * open_water[c] * lut_scale), last)]
            continue
        nx, ny, nz = normals[i, 0], normals[i, 1], normals[i, 2]
        n_dot_d = nx * directions[i, 0] + ny * directions[i, 1] + nz * directions[i, 2]
        r = depth * ray_length[i]
        cos = abs(n_dot_d) / ray_length[i]
        # Sediment settles on up-facing surfaces: blend toward it as the normal turns up.
        up_facing = -nz if n_dot_d > 0 else nz
        floor = min(max((up_facing - 0.55) * 3.0, 0.0), 1.0)
        light = light_power * cos / max(r, 0.3) ** 2
        for c in range(3):
            albedo = face_albedo[tri, c] + floor * (sediment[c] - face_albedo[tri, c])
            trans = math.exp(-attenuation[c] * r)
            radiance = albedo * trans * (light * trans + ambient[c]) + veil[c] * (1.0 - trans)
            rgb[i, c] = lut[min(int(gains[c] * radiance * lut_scale), last)]


@numba.njit(parallel=True, fastmath=True, cache=True)
def fill_rays(
    pixel_dirs: np.ndarray, rotation: np.ndarray, origin: np.ndarray, rays: np.ndarray
) -> None:
    """rays[i] = (origin, rotation @ pixel_dirs[i]) for (n, 3) camera-frame directions."""
    for i in numba.prange(pixel_dirs.shape[0]):
        for k in range(3):
            rays[i, k] = origin[k]
            rays[i, 3 + k] = (
                rotation[k, 0] * pixel_dirs[i, 0]
                + rotation[k, 1] * pixel_dirs[i, 1]
                + rotation[k, 2] * pixel_dirs[i, 2]
            )
