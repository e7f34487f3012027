"""Underwater image formation: the parameters, the water presets and the tone curve.

Per pixel, in linear light, for a ray from the camera that hits rock at path length r:

    L = ( rho * sum_k E_k                                            vehicle lamps
          + sum_k s G_k E_k                                          wet rock's glint
          + rho * D(face) ) * exp(-c r)                              daylight; the way back
        + B(pixel, r)                                                backscatter veil

    E_k = P_k beam_k(x) cos_k / d_k^2 * exp(-c d_k)

with per-channel attenuation c = a + b (absorption + scattering; red is lost first),
lamp k of power P_k (from its lumens and colour temperature) at distance d_k from the
surface point, beam_k its angular profile (`Lamp`), cos_k the incidence on the wall (the
normal tilted by the rock's small relief), s the specular reflectance and G_k the
normalised Blinn-Phong lobe toward the camera. D is the daylight a wall receives through
the cave's openings
(`cavenav.sensors.lighting` precomputes it per triangle, with one bounce), rho the rock
albedo (seeded noise, sediment on floors, darker in crevices). B integrates the lamps'
light scattered back toward the camera along the ray (a Henyey-Greenstein phase
function); it depends only on the pixel and r, so it is tabulated once per camera.
A ray that leaves the cave sees open water: daylight, brighter toward the surface, dimmed
by the water between the camera and the cave's bounds. Marine snow adds lamp-lit specks,
defocused near the lens. The camera then applies white balance, vignetting, sensor noise
and its gain (auto exposure up to a ceiling), a noise filter, a black clamp, a curve that
clips white, and JPEG compression. Everything is seeded: the same seed and pose give the
same image.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, replace
from functools import lru_cache
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from cavenav.core.errors import ConfigError

__all__ = [
    "BLACK_DISK_CONTRAST",
    "BLUEROV2_LAMPS",
    "CAVE_WATERS",
    "FULL_SCALE_NITS",
    "JERLOV_KD",
    "KARST_SPRING_BLACK_DISK_M",
    "KELVIN_LIMITS",
    "LAMP_MOUNTS",
    "LUMA",
    "Lamp",
    "MEASURED_FIRST",
    "Optics",
    "PHOTOPIC_BAND",
    "PUBLISHED_JERLOV_GREEN",
    "PURE_WATER_BLACK_DISK_M",
    "TONE_FLOOR",
    "TONE_SHIFT",
    "VISIBILITY_CONTRAST",
    "WATER_TYPES",
    "Water",
    "black_clamp",
    "bluerov2_lamps",
    "camera_curve",
    "jerlov_water",
    "lamp_colour",
    "optics_from_table",
    "published_scattering",
    "tone_lut",
    "visibility_m",
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

    @property
    def forward_fraction(self) -> float:
        """The share of scattered light deflected by less than `FORWARD_CONE_DEG`: for
        the Henyey-Greenstein function, 1 - (1 - g^2) / (2 g) ((1 + g^2 - 2 g mu)^-1/2
        - (1 + g)^-1) at mu = cos(cone); 0.80 at g = 0.92."""
        g, mu = self.phase_g, math.cos(math.radians(FORWARD_CONE_DEG))
        if g <= 0.0:
            return (1.0 - mu) / 2.0  # isotropic: the cone's share of the sphere
        beyond = (1 - g * g) / (2 * g) * ((1 + g * g - 2 * g * mu) ** -0.5 - 1 / (1 + g))
        return 1.0 - beyond

    @property
    def kept_attenuation(self) -> np.ndarray:
        """(3,) float32 attenuation of light when what is scattered forward counts as
        still arriving: c - b x `forward_fraction` (light that reaches a wall about the
        lamps' spot, or the camera about the image of what sent it: blurred, not lost)."""
        kept = self.attenuation - np.asarray(self.scattering) * self.forward_fraction
        return kept.astype(np.float32)


# Forward scatter: natural waters deflect most of the light they scatter by a few degrees
# (the Henyey-Greenstein function of g = 0.92 sends 80% within 20 degrees). That light is
# not lost: it lands about the lamps' spot, and reaches the camera about the image of the
# rock that sent it, as a halo. The halo's blur is a Gaussian of HALO_SIGMA_DEG: light
# deflected by theta somewhere along the path seems to come from about theta / 2 off,
# and the spread of deflections within the cone is about 8 degrees.
FORWARD_CONE_DEG = 20.0
HALO_SIGMA_DEG = 4.0


# Jerlov's optical water types: the diffuse attenuation Kd of downwelling daylight, 1/m,
# from 450 to 650 nm in steps of 25 nm (Jerlov 1976, Marine Optics, 2nd ed., Table XXVII,
# p. 135). Ocean types I (clearest) to III; coastal types 1 to 9 (greener, then browner).
JERLOV_NM = (450, 475, 500, 525, 550, 575, 600, 625, 650)
JERLOV_KD: dict[str, tuple[float, ...]] = {
    "I": (0.019, 0.018, 0.027, 0.043, 0.063, 0.089, 0.235, 0.305, 0.36),
    "IA": (0.026, 0.025, 0.032, 0.048, 0.067, 0.094, 0.24, 0.31, 0.37),
    "IB": (0.036, 0.033, 0.042, 0.054, 0.072, 0.099, 0.245, 0.315, 0.375),
    "II": (0.068, 0.062, 0.07, 0.076, 0.089, 0.115, 0.26, 0.335, 0.4),
    "III": (0.135, 0.116, 0.115, 0.116, 0.12, 0.148, 0.295, 0.375, 0.445),
    "1C": (0.25, 0.17, 0.14, 0.13, 0.12, 0.15, 0.3, 0.37, 0.45),
    "3C": (0.39, 0.29, 0.22, 0.2, 0.19, 0.21, 0.33, 0.4, 0.46),
    "5C": (0.56, 0.43, 0.36, 0.31, 0.3, 0.33, 0.4, 0.48, 0.54),
    "7C": (0.89, 0.71, 0.58, 0.49, 0.46, 0.46, 0.48, 0.54, 0.63),
    "9C": (1.6, 1.23, 0.99, 0.78, 0.63, 0.58, 0.6, 0.65, 0.76),
}
# The camera's broad bands (R, G, B) in nanometres, as `lamp_colour` integrates them.
CAMERA_BANDS_NM = ((600, 650), (520, 570), (450, 490))
PARTICLE_BACKSCATTER = 0.0183  # share scattered backward: Petzold's average particles
PARTICLE_G = 0.924  # their mean cosine (the Henyey-Greenstein g that matches it)


# What the presets stand for. Jerlov's types as published, (a, b) in 1/m at 525 and 550 nm
# (the wavelengths of JERLOV_NM in the camera's green band, which `jerlov_water` averages):
# Solonenko and Mobley (2015, Inherent optical properties of Jerlov water types, Appl.
# Opt. 54(17), 5392, Tables 4-8), fitted to Jerlov's Kd with bio-optical models; and
# Williamson and Hollins (2022, Measured IOPs of Jerlov water types, Appl. Opt. 61(33),
# 9951), from measured a and b (types IB to 5C). Read from the tables of the `jerlov`
# package (github.com/tishibashi-cpu/jerlov), which transcribes both.
PUBLISHED_JERLOV_GREEN: dict[str, dict[str, tuple[tuple[float, float], ...]]] = {
    "Solonenko and Mobley 2015": {
        "I": ((0.046, 0.00205), (0.062, 0.0017)),
        "IA": ((0.0468, 0.00402), (0.0622, 0.00354)),
        "IB": ((0.0469, 0.0565), (0.0623, 0.0536)),
        "II": ((0.0469, 0.387), (0.0622, 0.358)),
        "III": ((0.0507, 1.06), (0.0646, 0.980)),
        "1C": ((0.068, 0.395), (0.076, 0.365)),
        "3C": ((0.078, 1.15), (0.082, 1.06)),
        "5C": ((0.127, 1.44), (0.117, 1.33)),
        "7C": ((0.233, 2.54), (0.195, 2.35)),
        "9C": ((0.430, 3.38), (0.348, 3.12)),
    },
    "Williamson and Hollins 2022": {
        "IB": ((0.0516, 0.125), (0.0655, 0.122)),
        "II": ((0.0609, 0.181), (0.0724, 0.177)),
        "III": ((0.0821, 0.292), (0.0878, 0.287)),
        "1C": ((0.0972, 0.433), (0.0988, 0.427)),
        "3C": ((0.132, 0.654), (0.128, 0.644)),
        "5C": ((0.174, 1.21), (0.159, 1.19)),
    },
}
# The source `jerlov_water` takes a type's scattering from: the one that measured it.
MEASURED_FIRST = ("Williamson and Hollins 2022", "Solonenko and Mobley 2015")


def _band_mean(values: tuple[float, ...], band: tuple[int, int]) -> tuple[float, float]:
    """(mean value, mean wavelength) of Jerlov's entries within ``band`` (nm)."""
    inside = [(v, nm) for v, nm in zip(values, JERLOV_NM, strict=True) if band[0] <= nm <= band[1]]
    return sum(v for v, _ in inside) / len(inside), sum(nm for _, nm in inside) / len(inside)


def _seawater_scattering(nm: float) -> float:
    """Scattering by pure seawater's molecules, 1/m (Morel 1974): half of it backward."""
    return 0.0029 * (500.0 / nm) ** 4.32


def published_scattering(name: str) -> float:
    """Jerlov type ``name``'s scattering b in the camera's green band (525 and 550 nm
    averaged), 1/m, from the first source of `MEASURED_FIRST` that gives it:
    Williamson and Hollins measured a and b in waters of types IB to 5C; Solonenko and
    Mobley's values, fitted to Jerlov's Kd by bio-optical models, fill in the rest."""
    for source in MEASURED_FIRST:
        if name in PUBLISHED_JERLOV_GREEN[source]:
            pairs = PUBLISHED_JERLOV_GREEN[source][name]
            return sum(b for _, b in pairs) / len(pairs)
    raise KeyError(name)


def jerlov_water(name: str) -> Water:
    """The absorption and scattering, per camera band, of Jerlov's water type ``name``
    (a key of `JERLOV_KD`).

    Jerlov measured Kd, not the a and b an image needs. Near the surface, under a high
    sun, Kd = a + b_b to within about 10% (the light is nearly collimated, and only what
    is scattered backward is lost to it), which is why his clearest type matches pure
    water's absorption (Pope and Fry 1997). Kd fixes b_b, 1.8% of a particle's b, and
    so says next to nothing of b itself, which sets how far one sees. So b is the
    published one (`published_scattering`, in green), the particles' part falling as
    1 / wavelength into the other bands (Gordon and Morel 1983), and the absorption is
    what remains of Kd once b_b is taken out. The phase function's g is the scatterers'
    mean: 0 for the molecules, `PARTICLE_G` for the particles.
    """
    if name not in JERLOV_KD:
        raise ConfigError(
            f"unknown Jerlov water type '{name}'; choose one of {', '.join(JERLOV_KD)}"
        )
    kd = JERLOV_KD[name]
    green_nm = _band_mean(kd, CAMERA_BANDS_NM[1])[1]
    load_green = max(published_scattering(name) - _seawater_scattering(green_nm), 0.0)
    a, b, load = [], [], []
    for band in CAMERA_BANDS_NM:
        k, nm = _band_mean(kd, band)
        molecules, particles = _seawater_scattering(nm), load_green * green_nm / nm
        a.append(round(k - 0.5 * molecules - PARTICLE_BACKSCATTER * particles, 4))
        b.append(round(molecules + particles, 4))
        load.append(particles)
    return Water(
        absorption=(a[0], a[1], a[2]),
        scattering=(b[0], b[1], b[2]),
        phase_g=round(PARTICLE_G * load[1] / b[1], 3),
    )


# Broad-band camera channels (R ~ 600-650 nm, G ~ 520-570 nm, B ~ 450-490 nm), after
# pure-water absorption (Pope and Fry 1997) plus typical particle and organic loads;
# then Jerlov's types, as `jerlov_water` derives them ("jerlov-II", "jerlov-3C", ...).
# Against them, by their green a + b_b: clear lies between types IA and IB, ocean near
# IB, coastal near II and turbid near 1C; coastal and turbid scatter as much as the
# published II and 1C do (Williamson and Hollins 2022), so they see as far: 15 and 8 m.
WATER_TYPES: dict[str, Water] = {
    # Spring-fed karst (cenotes, Florida springs): visibility of tens of metres.
    "clear": Water(absorption=(0.29, 0.060, 0.020), scattering=(0.010, 0.012, 0.015)),
    # Open ocean, Jerlov type I-II.
    "ocean": Water(absorption=(0.31, 0.065, 0.030), scattering=(0.040, 0.050, 0.060)),
    # Coastal water: greener, walls beyond five metres fade into the lamps' haze.
    "coastal": Water(absorption=(0.34, 0.085, 0.11), scattering=(0.15, 0.17, 0.19)),
    # Silty water after rain or a careless fin kick: rock beyond 3 m is lost in the veil.
    "turbid": Water(absorption=(0.40, 0.14, 0.22), scattering=(0.34, 0.36, 0.38)),
} | {f"jerlov-{name}": jerlov_water(name) for name in JERLOV_KD}
CAVE_WATERS = ("clear", "ocean", "coastal", "turbid")  # the presets made for caves


# Visibility. Looking horizontally through uniform water, the difference between the
# radiance of a target and that of the water behind it falls as exp(-c r) at every
# wavelength, c the beam attenuation (Duntley 1963, Light in the Sea; Zaneveld and Pegau
# 2003, Robust underwater visibility parameter): the light the water scatters into the
# path fills a black target in toward the background. So a black target's contrast falls
# to a threshold at r = ln(1 / threshold) / c; 2% is Koschmieder's threshold for the
# daytime visual range. A diver sights a large black disk farther, to about 4.8 / c
# (Davies-Colley 1988, Measuring water clarity with a black disk; Hou, Lee and Weidemann
# 2007): an effective threshold of exp(-4.8), 0.8%.
VISIBILITY_CONTRAST = 0.02
BLACK_DISK_CONTRAST = math.exp(-4.8)
PHOTOPIC_BAND = 1  # G (520-570 nm): the camera band that holds the eye's peak, 555 nm


def visibility_m(water: Water, contrast: float = VISIBILITY_CONTRAST) -> float:
    """Horizontal visibility in ``water``, metres: the range at which a black target's
    contrast against the water behind it falls to ``contrast`` (2%), ln(1 / contrast) / c.

    c is the beam attenuation a + b (`Water.attenuation`), not `Water.kept_attenuation`:
    what the water scatters forward still arrives, but as a halo that no longer shows
    the target's edges. It is taken in the green band (520-570 nm), which holds the
    photopic peak, as visibility meters take c near 532 nm (Zaneveld and Pegau 2003).
    A luminance-weighted c would not do: a target's luminance contrast is a weighted sum
    of exp(-c_k r), which the least attenuated band dominates at range, not the
    exponential of a weighted c. Infinite where green passes unattenuated.

    This is visibility by the water's own light, as tables of water types state it. By
    the vehicle's lamps the veil they light in front of the lens lowers every contrast
    further, the more the nearer the lamps sit to the lens.

    Raises:
        ValueError: a contrast outside (0, 1).
    """
    if not 0.0 < contrast < 1.0:
        raise ValueError(f"contrast {contrast} is not between 0 and 1")
    c = float(water.attenuation[PHOTOPIC_BAND])
    return math.log(1.0 / contrast) / c if c > 0.0 else math.inf


# Black-disk sighting ranges, metres, in the clearest karst spring measured and in pure
# water: Te Waikoropupu Springs (New Zealand), 63 m by divers in 1993 (Davies-Colley and
# Smith 1995, Optically pure waters in Waikoropupu Springs) and about 75 m from a green
# beam transmissometer in 2017-18; pure water about 83 m (NIWA 2018, A clearer look at
# Te Waikoropupu Springs).
KARST_SPRING_BLACK_DISK_M = (63.0, 75.0)
PURE_WATER_BLACK_DISK_M = 83.0


@dataclass(frozen=True)
class Lamp:
    """A lamp on the vehicle, in the camera frame (x right, y down, z forward).

    An LED lamp's intensity falls off from its axis as a wide lobe with a brighter core
    (the hot spot its optic makes): I(theta) = I0 ((1 - h) cos^m theta + h cos^n theta),
    with m and n set by the full angles at which each lobe halves (the beam angle a
    lamp's data sheet gives is the wide lobe's), and nothing behind the lamp.

    Attributes:
        position: metres from the camera's centre of projection.
        axis: direction of the beam (normalised when used).
        beam_deg: full angle at which the wide lobe falls to half its on-axis intensity.
        hot_spot: share of the on-axis intensity that comes from the narrow core.
        hot_spot_deg: full angle at which the core falls to half.
        share: fraction of the vehicle's lamp output this lamp emits.
    """

    position: RGB
    axis: RGB = (0.0, 0.0, 1.0)
    beam_deg: float = 90.0
    hot_spot: float = 0.35
    hot_spot_deg: float = 30.0
    share: float = 0.5

    @property
    def exponents(self) -> tuple[float, float]:
        """(m, n): cos^m halves at beam_deg / 2 off axis, cos^n at hot_spot_deg / 2."""
        return (
            math.log(0.5) / math.log(math.cos(math.radians(self.beam_deg) / 2)),
            math.log(0.5) / math.log(math.cos(math.radians(self.hot_spot_deg) / 2)),
        )

    @property
    def solid_angle_sr(self) -> float:
        """Luminous flux over on-axis intensity: the integral of the profile over the
        forward hemisphere, 2 pi ((1 - h) / (m + 1) + h / (n + 1)) steradians."""
        m, n = self.exponents
        return 2 * math.pi * ((1 - self.hot_spot) / (m + 1) + self.hot_spot / (n + 1))


# Where lamps sit on a BlueROV2's frame, in the order they are fitted: the two upper
# corners beside the camera's dome (the two-lamp kit), then the two lower corners (four
# lamps). Each is toed out by 10 degrees, so that the beams' cores cross the camera's
# view only ahead of the vehicle, which keeps the backscatter down.
LAMP_MOUNTS: tuple[RGB, ...] = (
    (-0.21, -0.10, -0.05),
    (0.21, -0.10, -0.05),
    (-0.21, 0.12, -0.05),
    (0.21, 0.12, -0.05),
)


def bluerov2_lamps(count: int = 2, beam_deg: float = 90.0) -> tuple[Lamp, ...]:
    """``count`` (1-4) equal lamps on a BlueROV2's mounts (`LAMP_MOUNTS`)."""
    if not 1 <= count <= len(LAMP_MOUNTS):
        raise ConfigError(f"lamps: {count} lamps; a BlueROV2 carries 1 to {len(LAMP_MOUNTS)}")
    return tuple(
        Lamp(
            position=mount,
            axis=(math.copysign(0.17, mount[0]), 0.0, 1.0),
            beam_deg=beam_deg,
            share=1.0 / count,
        )
        for mount in LAMP_MOUNTS[:count]
    )


BLUEROV2_LAMPS: tuple[Lamp, ...] = bluerov2_lamps()

# The camera's full scale at its least gain, in cd/m^2 (nits) of radiance at the lens:
# a low-light camera at f/2 and 1/30 s exposes 18% grey at about 2 nits at base gain.
# Radiance in the renderer is in these units, so 1.0 is the brightest a pixel can hold
# at gain 1.
FULL_SCALE_NITS = 12.0


def lamp_colour(kelvin: float) -> np.ndarray:
    """(3,) relative power of a source at colour temperature ``kelvin`` in the camera's
    R, G, B bands (600-650, 520-570, 450-490 nm, as the water model's), from Planck's
    law, scaled so that green is 1 and a 6,500 K source (daylight) is white.

    LED lamps are not black bodies, but their colour temperature is defined by the black
    body they match, which is what a data sheet gives.
    """

    def bands(t: float) -> np.ndarray:
        out = []
        for lo, hi in ((600, 650), (520, 570), (450, 490)):
            nm = np.linspace(lo, hi, 26) * 1e-9
            planck = nm**-5 / np.expm1(1.4387769e-2 / (nm * t))
            out.append(planck.mean())
        return np.asarray(out)

    colour = bands(kelvin) / bands(6500.0)
    return (colour / colour[1]).astype(np.float32)


# The colour temperatures a white balance may name, in kelvin: the black-body locus is
# tabulated over them (`cavenav.sensors.white_balance`), wider than any camera's control.
KELVIN_LIMITS = (1000.0, 40000.0)


@dataclass(frozen=True)
class Optics:
    """Everything that shapes the colour image (and, optionally, degrades depth).

    Radiance is in units of the camera's full scale at its least gain
    (`FULL_SCALE_NITS`), so that lamps rated in lumens and the camera's gain meet.

    Attributes:
        water: a preset name from `WATER_TYPES` or a `Water`.
        lamp_count: lamps on the vehicle (1-4, on `LAMP_MOUNTS`; a BlueROV2 carries 2 or 4).
        lamp_lumens: luminous flux of each lamp (a Lumen light: about 1,500 lm).
        lamp_beam_deg: full beam angle of each lamp in water, at half intensity. A Lumen
            light's data sheet gives 135 degrees; we take that as measured in air, so
            that its flat window narrows it in water to about 90 degrees (Snell's law:
            sin 67.5 / 1.33 = sin 44).
        lamp_kelvin: the lamps' colour temperature (cool-white LEDs: 5,000-7,000 K).
        light_power: None (default) to take the lamps' output from their lumens; a number
            sets their total instead, as the radiance of a white wall 1 m ahead on the
            lamps' axes (about 32 for two Lumen lights); 0 turns them off.
        lamps: where the lamps are and how they shine; None: the vehicle's own
            (`bluerov2_lamps` of `lamp_count` and `lamp_beam_deg`).
        daylight: radiance of open water seen horizontally through an exit, before the
            water between the exit and the camera; 0 makes a cave with no daylight.
        daylight_colour: its hue (sunlight filtered by the water column above).
        particles: marine snow, particles per cubic metre (0: none).
        silt_out: whether the vehicle's thrust near the floor raises silt that hangs in
            the water and clouds the camera (`cavenav.world.silt`); None (default): the
            cave's choice, on in the crawl family and off elsewhere.
        noise: sensor noise, 1 = a typical ROV camera in low light, 0 = none.
        vignetting: darkening of the image corners by the lens (0-1).
        exposure: None (default) for auto-exposure: the gain brings the frame's mean
            brightness to `exposure_key`, within `gain_range`, as an ROV camera does; a
            number fixes the gain.
        exposure_key: the auto-exposure's target for the mean, linear (18% grey).
        gain_range: the least and most exposure the auto-exposure may use, relative to
            the base exposure (1/30 s at the least gain). The least is the shortest
            shutter, 1/1500 s: a wall at arm's length is not bound to clip. The most is
            the gain ceiling (24 dB), which lets the unlit cave go black: a camera cannot
            brighten what its sensor does not see above its noise.
        black_level: the camera's black clamp, as a fraction of full scale taken off the
            luma after the gain and white balance, every channel scaled alike so that
            hues stay: the noise floor (the read noise at the gain ceiling is a tenth of
            it) and the faintest light read black, as a video camera's black level and
            the toe of its curve make them.
        tone: "camera" (default): a video camera's curve, linear up to a knee, then a
            short shoulder, and clipped white above 1.2 times full scale; "soft": a
            Reinhard curve that never clips (cavenav's images before scenario set 2).
        denoise: strength of the camera's spatial noise filter (0: off, 1: full).
        compression: quality of the lossy compression a video camera applies (JPEG,
            1-100; 0: none).
        white_balance: None (default) for the camera's own auto white balance, as the
            BlueROV2's camera does it (`cavenav.sensors.white_balance`): a colour
            temperature on the black-body locus, found from the frame's mean colour and
            held within `white_balance_range`, so a blue-green cast off the locus stays;
            a number for grey world at that strength instead (the white balance before
            the camera's, 0.7 then): 0 keeps the sensor's raw colours, where distant
            rock turns blue-green; 1 makes every frame's mean grey.
        white_balance_kelvin: None (default), or a fixed colour temperature, as the
            camera's manual control (V4L2 ``white_balance_temperature`` with
            ``white_balance_automatic`` off): gains that make a source of this
            temperature white, whatever the frame. 6,500 K keeps the sensor's colours.
        white_balance_range: the least and most colour temperature, in kelvin, that the
            camera's auto white balance may choose: the BlueROV2 camera's control range,
            2,800-6,500 K (incandescent to daylight, the range V4L2 asks of a driver).
        rock_colour: mean reflectance of bare rock (limestone: warm grey).
        sediment_colour: reflectance of silt on up-facing surfaces.
        specular: reflectance of wet rock toward the mirror direction at normal
            incidence (0: matte). Calcite against water reflects about 1%; polished
            flowstone and crystal faces more, so the rock's texture varies it.
        depth_dropout: raw depth reports no return (inf) where the lamps' returned green
            radiance is below this, as an active depth sensor does on dark or distant
            rock; 0 (default) keeps every pixel.
        depth_noise_m: standard deviation of depth noise at 10 m, growing with the square
            of depth as a stereo or time-of-flight camera's does; 0 (default) is exact.
    """

    water: str | Water = "clear"
    lamp_count: int = 2
    lamp_lumens: float = 1500.0
    lamp_beam_deg: float = 90.0
    lamp_kelvin: float = 6200.0
    light_power: float | None = None
    lamps: tuple[Lamp, ...] | None = None
    daylight: float = 1.0
    daylight_colour: RGB = (0.10, 0.55, 0.60)
    particles: float = 4.0
    silt_out: bool | None = None
    noise: float = 1.0
    vignetting: float = 0.35
    exposure: float | None = None
    exposure_key: float = 0.18
    gain_range: tuple[float, float] = (0.02, 16.0)
    black_level: float = 0.04
    tone: Literal["camera", "soft"] = "camera"
    denoise: float = 1.0
    compression: int = 85
    white_balance: float | None = None
    white_balance_kelvin: float | None = None
    white_balance_range: tuple[float, float] = (2800.0, 6500.0)
    rock_colour: RGB = (0.40, 0.37, 0.33)
    sediment_colour: RGB = (0.46, 0.40, 0.30)
    specular: float = 0.02
    depth_dropout: float = 0.0
    depth_noise_m: float = 0.0

    def __post_init__(self) -> None:
        if isinstance(self.water, str) and self.water not in WATER_TYPES:
            raise ConfigError(
                f"unknown water type '{self.water}'; choose one of {', '.join(WATER_TYPES)}"
            )
        bluerov2_lamps(self.lamp_count, self.lamp_beam_deg)  # refuse a count no vehicle has
        self._check_white_balance()

    def _check_white_balance(self) -> None:
        """Refuse a white balance no camera has: two modes at once, a strength outside
        0-1, a temperature off the tabulated locus (`KELVIN_LIMITS`)."""
        if self.white_balance is not None and self.white_balance_kelvin is not None:
            raise ConfigError(
                f"white balance: grey world (white_balance={self.white_balance}) and a fixed "
                f"temperature (white_balance_kelvin={self.white_balance_kelvin}) both set; "
                "set one, or neither for the camera's own auto white balance"
            )
        if self.white_balance is not None and not 0.0 <= self.white_balance <= 1.0:
            raise ConfigError(f"white_balance: {self.white_balance}; a strength from 0 to 1")
        low, high = self.white_balance_range
        fixed = () if self.white_balance_kelvin is None else (self.white_balance_kelvin,)
        lowest, highest = KELVIN_LIMITS
        if not lowest <= low <= high <= highest or not all(lowest <= k <= highest for k in fixed):
            raise ConfigError(
                f"white balance: {self.white_balance_range} K, {self.white_balance_kelvin} K; "
                f"temperatures from {lowest:,.0f} to {highest:,.0f} K, the range's least first"
            )

    @property
    def white_balance_mode(self) -> Literal["camera", "grey-world", "manual"]:
        """Which white balance the camera applies: its own auto white balance, grey world
        (`white_balance` set) or a fixed temperature (`white_balance_kelvin` set)."""
        if self.white_balance_kelvin is not None:
            return "manual"
        return "camera" if self.white_balance is None else "grey-world"

    @property
    def fitted_lamps(self) -> tuple[Lamp, ...]:
        """The lamps that shine: `lamps` when given, else the vehicle's own
        (`bluerov2_lamps` of `lamp_count` and `lamp_beam_deg`), so that
        ``replace(optics, lamp_count=4)`` fits four."""
        if self.lamps is not None:
            return self.lamps
        return bluerov2_lamps(self.lamp_count, self.lamp_beam_deg)

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

    @property
    def lamp_power(self) -> np.ndarray:
        """(k, 3) float32 per lamp and colour channel: the radiance of a white wall 1 m
        ahead on the lamp's axis, in camera units (what the kernels call power).

        From the lumens: on-axis intensity I0 = flux / `Lamp.solid_angle_sr` candela, a
        white Lambertian wall's radiance I0 / pi nits at 1 m, in units of
        `FULL_SCALE_NITS`; tinted by `lamp_colour` with green kept, since lumens weigh
        mostly green. `light_power`, when set, rescales the total.
        """
        lamps = self.fitted_lamps
        flux = self.lamp_lumens * len(lamps)
        green = np.array(
            [flux * lamp.share / lamp.solid_angle_sr / math.pi / FULL_SCALE_NITS for lamp in lamps]
        )
        if self.light_power is not None:
            green *= self.light_power / max(green.sum(), 1e-12)
        return (green[:, None] * lamp_colour(self.lamp_kelvin)[None, :]).astype(np.float32)

    @property
    def lit(self) -> bool:
        """Whether the lamps shine at all."""
        return bool(self.fitted_lamps) and float(self.lamp_power.sum()) > 0.0


class _OpticsTable(BaseModel):
    """The `[optics]` table of a scenario file, or the equivalent CLI options."""

    model_config = ConfigDict(extra="forbid")
    water: str | None = None
    light_power: float | None = Field(None, ge=0)
    daylight: float | None = Field(None, ge=0)
    particles: float | None = Field(None, ge=0, le=200)
    silt_out: bool | None = None
    noise: float | None = Field(None, ge=0, le=20)
    vignetting: float | None = Field(None, ge=0, le=1)
    exposure: float | Literal["auto"] | None = None
    white_balance: Annotated[float, Field(ge=0, le=1)] | Literal["camera"] | None = None
    white_balance_kelvin: float | None = Field(None, ge=KELVIN_LIMITS[0], le=KELVIN_LIMITS[1])
    white_balance_range: tuple[float, float] | None = None
    lamp_count: int | None = Field(None, ge=1, le=len(LAMP_MOUNTS))
    lamp_lumens: float | None = Field(None, ge=0, le=100_000)
    lamp_beam_deg: float | None = Field(None, ge=10, le=170)
    lamp_kelvin: float | None = Field(None, ge=1500, le=20_000)
    gain_max: float | None = Field(None, ge=1, le=10_000)
    black_level: float | None = Field(None, ge=0, le=0.5)
    tone: Literal["camera", "soft"] | None = None
    denoise: float | None = Field(None, ge=0, le=1)
    compression: int | None = Field(None, ge=0, le=100)
    specular: float | None = Field(None, ge=0, le=1)
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
    _white_balance_changes(changes, where)
    base = base or Optics()
    if "gain_max" in changes:
        changes["gain_range"] = (base.gain_range[0], changes.pop("gain_max"))
    return replace(base, **changes)


def _white_balance_changes(changes: dict[str, Any], where: str) -> None:
    """The white balance as a layer of settings gives it, in ``changes`` (in place).

    The layer that sets the white balance decides it whole, so that layers stack: a
    strength (grey world, the one setting of files written before the camera's own auto
    white balance, which keep their meaning) or "camera" clears a fixed temperature
    beneath, and a fixed temperature clears a strength beneath.
    """
    strength, kelvin = changes.get("white_balance"), changes.get("white_balance_kelvin")
    if strength is not None and kelvin is not None:
        raise ConfigError(
            f"{where}: 'white_balance' ({strength}) and 'white_balance_kelvin' ({kelvin}) "
            "both set; keep one: a strength for grey world, 'camera' for the camera's "
            "own auto white balance, or a fixed temperature"
        )
    if strength is not None:
        changes["white_balance"] = None if strength == "camera" else strength
        changes["white_balance_kelvin"] = None
    elif kelvin is not None:
        changes["white_balance"] = None


# The tone curve is tabulated over the bits of a float32: bits >> TONE_SHIFT keep the
# exponent and 10 mantissa bits, steps of 0.1% at every brightness.
TONE_SHIFT = 13
TONE_FLOOR = int(np.float32(2.0**-16).view(np.int32)) >> TONE_SHIFT  # darker is black
_TONE_CEIL = int(np.float32(256.0).view(np.int32)) >> TONE_SHIFT  # brighter is white


KNEE = 0.8  # the camera curve is linear up to here, as a video camera's is ...
WHITE_CLIP = 1.2  # ... then bends into white, reached (and clipped) here


LUMA = (0.299, 0.587, 0.114)  # Rec. 601 luma weights (R, G, B), as JPEG and H.264 code it


def black_clamp(signal: np.ndarray, black_level: float) -> np.ndarray:
    """(..., 3) white-balanced linear ``signal`` after the camera's black clamp, which
    works on luma Y (`LUMA`): every channel is scaled by max(Y - b, 0) / ((1 - b) Y), so
    a pixel whose luma is at or below ``black_level`` reads black and the rest darken
    alike in every channel, keeping their hue. `kernels.develop_image` applies the same
    clamp per pixel.
    """
    y = np.asarray(signal, np.float64) @ np.asarray(LUMA)
    scale = np.maximum(y - black_level, 0.0) / ((1.0 - black_level) * np.maximum(y, 1e-30))
    return signal * scale[..., None]


def camera_curve(signal: np.ndarray, tone: str = "camera") -> np.ndarray:
    """Linear signal after the gain and black clamp (1 = full scale) to display-linear
    values in [0, 1].

    "camera": linear to `KNEE`, a parabolic shoulder whose slope starts at 1 and reaches
    0 at `WHITE_CLIP`, white beyond (clipped highlights); or "soft": Reinhard's
    x / (1 + x), which never clips.
    """
    x = np.maximum(signal, 0.0)
    if tone == "soft":
        return x / (1.0 + x)
    width = WHITE_CLIP - KNEE
    over = np.clip((x - KNEE) / width, 0.0, 1.0)
    shoulder = KNEE + (1.0 - KNEE) * (1.0 - (1.0 - over) ** 2)
    return np.where(x < KNEE, x, shoulder)


@lru_cache(maxsize=8)
def tone_lut(exposure: float = 1.0, tone: str = "camera") -> np.ndarray:
    """(24576,) uint8 map from linear signal in [2^-16, 256) to 8-bit sRGB: ``exposure``
    times the signal through `camera_curve`, then the sRGB transfer function.

    Index: (float32 bits of the value >> TONE_SHIFT) - TONE_FLOOR, so that the table's
    steps are relative (0.1%), fine in the dark tones where sRGB is steep, and a lookup
    needs no square root: 24 KB, within half an 8-bit level everywhere.
    """
    index = np.arange(TONE_FLOOR, _TONE_CEIL, dtype=np.int64)
    middle = (index << TONE_SHIFT) | (1 << (TONE_SHIFT - 1))  # each step's central float
    radiance = middle.astype(np.int32).view(np.float32).astype(np.float64)
    radiance[0] = 0.0  # the first step also holds everything darker
    mapped = camera_curve(exposure * radiance, tone)
    srgb = np.where(mapped <= 0.0031308, 12.92 * mapped, 1.055 * mapped ** (1 / 2.4) - 0.055)
    return (np.clip(srgb, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
