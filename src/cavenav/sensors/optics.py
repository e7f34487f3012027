"""Colour image formation from one ray cast: vehicle lights, water, rock albedo.

A deliberately simple model, evaluated per pixel in linear light then tone-mapped:

    L = albedo * P * cos(theta) / r^2 * exp(-2 c r)      (lights beside the camera)
      + albedo * A * exp(-c r)                           (faint ambient light)
      + B * (1 - exp(-c r))                              (veiling light of the water)

with per-channel attenuation ``c`` (red lost first). Rays that leave the cave see open
water. The per-pixel evaluation lives in `cavenav.sensors.kernels` (one compiled pass).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from cavenav.world.mesh import CaveMesh

__all__ = ["LUT_SCALE", "Optics", "rock_albedo", "tone_lut"]


@dataclass(frozen=True)
class Optics:
    """Water and lighting parameters (linear RGB, per metre).

    Attributes:
        attenuation: per-channel beam attenuation c in 1/m; coastal water loses red first.
        light_power: strength of the vehicle's lights (radiance at 1 m on a white wall).
        ambient: faint diffuse light inside the cave.
        veil: colour of light scattered by the water toward the camera.
        open_water: radiance seen along rays that leave the cave.
        exposure: scales linear light before tone mapping.
        white_balance_m: the camera's white balance cancels the water's colour for a
            surface this far away (lit and seen through 2x this much water), as an ROV
            camera's does; nearer rock looks warmer, farther rock fades to blue-green.
    """

    attenuation: tuple[float, float, float] = (0.22, 0.07, 0.06)
    light_power: float = 20.0
    ambient: tuple[float, float, float] = (0.006, 0.010, 0.012)
    veil: tuple[float, float, float] = (0.002, 0.010, 0.014)
    open_water: tuple[float, float, float] = (0.05, 0.35, 0.40)
    exposure: float = 1.6
    white_balance_m: float = 2.0

    @property
    def gains(self) -> np.ndarray:
        """(3,) float32 per-channel camera gains, green = 1."""
        c = np.asarray(self.attenuation, np.float64)
        gains = np.exp(2.0 * self.white_balance_m * (c - c[1]))
        return gains.astype(np.float32)


def rock_albedo(mesh: CaveMesh, seed: int = 0) -> np.ndarray:
    """(n_vertices, 3) float32 rock colour from seeded 3-D noise at each vertex.

    Random phases of a few sinusoids per octave give a smooth, band-limited field that is
    cheap to evaluate once per vertex; pixels interpolate it with barycentric weights.
    """
    rng = np.random.default_rng(seed)
    p = mesh.vertices.astype(np.float32)
    field = np.zeros(len(p), np.float32)
    for wavelength, weight in ((3.0, 0.5), (1.1, 0.3), (0.45, 0.2)):
        for _ in range(3):
            k = rng.normal(size=3).astype(np.float32)
            k *= 2 * np.pi / wavelength / np.linalg.norm(k)
            field += weight * np.sin(p @ k + rng.uniform(0, 2 * np.pi)) / 1.7
    grey = 0.36 + 0.22 * field  # rock reflectance around 0.15-0.6
    tint = np.array([1.0, 0.93, 0.82], np.float32)  # warm limestone
    return np.clip(grey[:, None] * tint, 0.05, 0.9).astype(np.float32)


LUT_SIZE = 65536
LUT_SCALE = LUT_SIZE / 16.0


@lru_cache(maxsize=8)
def tone_lut(exposure: float) -> np.ndarray:
    """(65536,) uint8 map from linear radiance in [0, 16) to tone-mapped sRGB.

    One table lookup replaces an exp, a power and a branch per channel and pixel; 65536
    steps keep the darkest tones within about one 8-bit level. Index: radiance * LUT_SCALE.
    """
    radiance = np.arange(LUT_SIZE, dtype=np.float64) / LUT_SCALE
    mapped = 1.0 - np.exp(-exposure * radiance)  # soft shoulder instead of clipping
    srgb = np.where(mapped <= 0.0031308, 12.92 * mapped, 1.055 * mapped ** (1 / 2.4) - 0.055)
    return (np.clip(srgb, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
