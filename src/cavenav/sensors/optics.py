"""Underwater image formation: the parameters, the water presets and the tone curve.

Per pixel, in linear light, for a ray from the camera that hits rock at path length r:

    L = rho * ( sum_k I_k spot_k(x) cos_k / d_k^2 * exp(-c d_k)     vehicle lamps
                + D(face) )                                          daylight from exits
          * exp(-c r)                                                 back to the camera
        + B(pixel, r)                                                 backscatter veil

with per-channel attenuation c = a + b (absorption + scattering; red is lost first),
lamp k at distance d_k from the surface point, spot_k its cone fall-off and cos_k the
incidence on the wall. D is the daylight a wall receives through the cave's openings
(`cavenav.sensors.lighting` precomputes it per triangle, with one bounce), rho the rock
albedo (seeded noise, sediment on floors, darker in crevices). B integrates the lamps'
light scattered back toward the camera along the ray (a Henyey-Greenstein phase
function); it depends only on the pixel and r, so it is tabulated once per camera.
A ray that leaves the cave sees open water: daylight, brighter toward the surface, dimmed
by the water between the camera and the cave's bounds. Marine snow adds lamp-lit specks,
defocused near the lens. The camera then applies white balance, vignetting, sensor noise
and a tone curve. Everything is seeded: the same seed and pose give the same image.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, replace
from functools import lru_cache
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from cavenav.errors import ConfigError

__all__ = [
    "BLUEROV2_LAMPS",
    "TONE_FLOOR",
    "TONE_SHIFT",
    "WATER_TYPES",
    "Lamp",
    "Optics",
    "Water",
    "optics_from_table",
    "tone_lut",
]

RGB = tuple[float, float, float]


@dataclass(frozen=True)
class Water:
    """Inherent optical properties of the water, per colour channel (R, G, B), in 1/m.

    Attributes:
        absorption: a; pure water absorbs red strongly (about 0.3/m), blue hardly at all;
            dissolved organic matter adds absorption in the blue.
        scattering: b; particles scatter all colours about alike. It lights the veil
            of backscatter in front of the camera.
        phase_g: asymmetry of the Henyey-Greenstein phase function; natural waters
            scatter mostly forward (0.8-0.95), so little light comes straight back.
    """

    absorption: RGB
    scattering: RGB
    phase_g: float = 0.92

    @property
    def attenuation(self) -> np.ndarray:
        """(3,) float32 beam attenuation c = a + b."""
        return (np.asarray(self.absorption) + np.asarray(self.scattering)).astype(np.float32)


# Broad-band camera channels (R ~ 600-650 nm, G ~ 520-570 nm, B ~ 450-490 nm), after
# pure-water absorption (Pope and Fry 1997) plus typical particle and organic loads.
WATER_TYPES: dict[str, Water] = {
    # Spring-fed karst (cenotes, Florida springs): visibility of tens of metres.
    "clear": Water(absorption=(0.29, 0.060, 0.020), scattering=(0.010, 0.012, 0.015)),
    # Open ocean, Jerlov type I-II.
    "ocean": Water(absorption=(0.31, 0.065, 0.030), scattering=(0.040, 0.050, 0.060)),
    # Coastal water: greener, walls beyond five metres fade into the lamps' haze.
    "coastal": Water(absorption=(0.34, 0.085, 0.11), scattering=(0.065, 0.07, 0.075)),
    # Silty water after rain or a careless fin kick: rock beyond 3 m is lost in the veil.
    "turbid": Water(absorption=(0.40, 0.14, 0.22), scattering=(0.19, 0.20, 0.21)),
}


@dataclass(frozen=True)
class Lamp:
    """A spot lamp on the vehicle, in the camera frame (x right, y down, z forward).

    Attributes:
        position: metres from the camera's centre of projection.
        axis: direction of the beam (normalised when used).
        inner_deg, outer_deg: half-angles of the full-power core and of the edge of the
            beam; the intensity falls off smoothly in between.
        share: fraction of `Optics.light_power` this lamp emits.
    """

    position: RGB
    axis: RGB = (0.0, 0.0, 1.0)
    inner_deg: float = 25.0
    outer_deg: float = 50.0
    share: float = 0.5


# Two lamps at the front corners of the frame, beside and a little above the camera, as
# on a BlueROV2 with Lumen lights; toed out so that their beams cross the camera's view
# only beyond half a metre, which keeps the backscatter down.
BLUEROV2_LAMPS: tuple[Lamp, ...] = (
    Lamp(position=(-0.21, -0.10, -0.05), axis=(-0.17, 0.0, 1.0)),
    Lamp(position=(0.21, -0.10, -0.05), axis=(0.17, 0.0, 1.0)),
)


@dataclass(frozen=True)
class Optics:
    """Everything that shapes the colour image (and, optionally, degrades depth).

    Attributes:
        water: a preset name from `WATER_TYPES` or a `Water`.
        light_power: total intensity of the lamps: radiance of a white wall 1 m in front
            of them, before water. 0 turns them off.
        lamps: where the lamps are and how they point.
        daylight: radiance of open water seen horizontally through an exit, before the
            water between the exit and the camera; 0 makes a cave with no daylight.
        daylight_colour: its hue (sunlight filtered by the water column above).
        particles: marine snow, particles per cubic metre (0: none).
        noise: sensor noise, 1 = a typical ROV camera in low light, 0 = none.
        vignetting: darkening of the image corners by the lens (0-1).
        exposure: None (default) for auto-exposure: the gain brings the frame's mean
            brightness to `exposure_key`, within `gain_range`, as an ROV camera does; a
            number fixes the gain.
        exposure_key: the auto-exposure's target, on the tone curve's input scale.
        gain_range: the least and most gain the auto-exposure may use.
        white_balance: strength of the camera's auto white balance (grey world): 0
            keeps the sensor's raw colours, where distant rock turns blue-green; 1 makes
            every frame's mean grey. Cameras correct part of the way.
        rock_colour: mean reflectance of bare rock (limestone: warm grey).
        sediment_colour: reflectance of silt on up-facing surfaces.
        depth_dropout: raw depth reports no return (inf) where the lamps' returned green
            radiance is below this, as an active depth sensor does on dark or distant
            rock; 0 (default) keeps every pixel.
        depth_noise_m: standard deviation of depth noise at 10 m, growing with the square
            of depth as a stereo or time-of-flight camera's does; 0 (default) is exact.
    """

    water: str | Water = "clear"
    light_power: float = 20.0
    lamps: tuple[Lamp, ...] = BLUEROV2_LAMPS
    daylight: float = 1.0
    daylight_colour: RGB = (0.10, 0.55, 0.60)
    particles: float = 4.0
    noise: float = 1.0
    vignetting: float = 0.35
    exposure: float | None = None
    exposure_key: float = 0.25
    gain_range: tuple[float, float] = (1.0, 40.0)
    white_balance: float = 0.4
    rock_colour: RGB = (0.40, 0.37, 0.33)
    sediment_colour: RGB = (0.46, 0.40, 0.30)
    depth_dropout: float = 0.0
    depth_noise_m: float = 0.0

    def __post_init__(self) -> None:
        if isinstance(self.water, str) and self.water not in WATER_TYPES:
            raise ConfigError(
                f"unknown water type '{self.water}'; choose one of {', '.join(WATER_TYPES)}"
            )

    @property
    def water_name(self) -> str:
        """The preset's name, or "custom" for a `Water` given by its coefficients."""
        return self.water if isinstance(self.water, str) else "custom"

    @property
    def sky(self) -> np.ndarray:
        """(3,) float32 radiance of open water looking straight up through an exit."""
        return (self.daylight * np.asarray(self.daylight_colour)).astype(np.float32)

    @property
    def medium(self) -> Water:
        return WATER_TYPES[self.water] if isinstance(self.water, str) else self.water


class _OpticsTable(BaseModel):
    """The `[optics]` table of a scenario file, or the equivalent CLI options."""

    model_config = ConfigDict(extra="forbid")
    water: str | None = None
    light_power: float | None = Field(None, ge=0)
    daylight: float | None = Field(None, ge=0)
    particles: float | None = Field(None, ge=0, le=200)
    noise: float | None = Field(None, ge=0, le=20)
    vignetting: float | None = Field(None, ge=0, le=1)
    exposure: float | Literal["auto"] | None = None
    white_balance: float | None = Field(None, ge=0, le=1)
    depth_dropout: float | None = Field(None, ge=0)
    depth_noise_m: float | None = Field(None, ge=0)

    @field_validator("water")
    @classmethod
    def _known_water(cls, v: str | None) -> str | None:
        if v is not None and v not in WATER_TYPES:
            raise ValueError(f"unknown water type '{v}'; choose one of {', '.join(WATER_TYPES)}")
        return v


OPTICS_OPTIONS = tuple(_OpticsTable.model_fields)


def optics_from_table(
    table: Mapping[str, Any], base: Optics | None = None, where: str = "[optics]"
) -> Optics:
    """``base`` (default `Optics()`) with the fields a config table sets.

    Unset (None) entries keep the base value, so scenario files and CLI flags can be
    layered: `optics_from_table(cli_flags, optics_from_table(scenario.optics))`.

    Raises:
        ConfigError: an unknown key or a bad value, naming it.
    """
    try:
        model = _OpticsTable.model_validate(dict(table))
    except ValidationError as exc:
        first = exc.errors()[0]
        key = ".".join(str(p) for p in first["loc"]) or "(table)"
        raise ConfigError(f"{where}: '{key}': {first['msg']}") from None
    changes = {k: v for k, v in model.model_dump().items() if v is not None}
    if changes.get("exposure") == "auto":
        changes["exposure"] = None
    return replace(base or Optics(), **changes)


# The tone curve is tabulated over the bits of a float32: bits >> TONE_SHIFT keep the
# exponent and 10 mantissa bits, steps of 0.1% at every brightness.
TONE_SHIFT = 13
TONE_FLOOR = int(np.float32(2.0**-16).view(np.int32)) >> TONE_SHIFT  # darker is black
_TONE_CEIL = int(np.float32(256.0).view(np.int32)) >> TONE_SHIFT  # brighter is white


@lru_cache(maxsize=8)
def tone_lut(exposure: float) -> np.ndarray:
    """(24576,) uint8 map from linear radiance in [2^-16, 256) to tone-mapped sRGB.

    A Reinhard curve ``kL / (1 + kL)`` keeps detail from the lamp-lit wall at arm's
    length down to rock ten metres off, with a soft shoulder instead of clipping.
    Index: (float32 bits of the radiance >> TONE_SHIFT) - TONE_FLOOR, so that the
    table's steps are relative (0.1%), fine in the dark tones where sRGB is steep, and
    a lookup needs no square root: 24 KB, within half an 8-bit level everywhere.
    """
    index = np.arange(TONE_FLOOR, _TONE_CEIL, dtype=np.int64)
    middle = (index << TONE_SHIFT) | (1 << (TONE_SHIFT - 1))  # each step's central float
    radiance = middle.astype(np.int32).view(np.float32).astype(np.float64)
    radiance[0] = 0.0  # the first step also holds everything darker
    mapped = exposure * radiance / (1.0 + exposure * radiance)
    srgb = np.where(mapped <= 0.0031308, 12.92 * mapped, 1.055 * mapped ** (1 / 2.4) - 0.055)
    return (np.clip(srgb, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
