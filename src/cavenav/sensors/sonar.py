"""Imaging sonars, rendered with the cave's ray caster: a Ping360-like mechanically
scanned sonar and a forward-looking multibeam (Oculus M750d-like).

A beam is a fan of rays across its vertical aperture (and, for the scanning sonar's wider
beam, across its horizontal width), spanning 1.5 times its -3 dB width, weighted by its
two-way beam pattern (a Gaussian main lobe, -6 dB two ways at the stated width). Each ray
that hits rock returns an echo into the range bin of its distance, as sonar equations
give it for an area target:

    energy = cos(incidence) / r^2 * 10^(-2 alpha r / 10)

per unit solid angle: Lambert's law (backscatter strength proportional to cos^2 of the
incidence) over a patch of r^2 / cos(incidence) per steradian, with spherical spreading
and absorption both ways. The receiver's time-varied gain (20 log r + 2 alpha r, the gain
imaging sonars apply for area and volume targets) makes a wall's echo independent of its
range, and lifts the receiver's noise with range: far echoes drown in noise first, as on
a real display. Silt in the water returns volume backscatter in proportion to its
concentration (it hazes the image, it does not blind it), marine snow a few bright specks,
and every bin is speckled (gamma-distributed energy of four looks, the speckle of a
coherent echo averaged over a few samples). Bins inside the blanking distance read 0.

The absorption comes from Francois and Garrison (1982), with the water's temperature and
salinity: 0.15 dB/m at 750 kHz in fresh water at 15 C, 0.21 dB/m in sea water.

The output is what the devices give: a (beams, bins) array of 8-bit echo strengths, first
bin nearest, and its fan (multibeam) or disc (scanning sonar) as Ping Viewer and the Oculus
software draw it, heading up. The scanning sonar's head turns in gradians (400 a turn, as
the Ping360's protocol counts), one ping per angle step; a ping lasts the echo's round trip
over the range plus a fixed `ping_overhead_s` (the head's step and the data's transfer), so
one observation sees only the angles swept since the last, and the disc keeps the rest as
it was last seen, as Ping Viewer's does.
"""

from __future__ import annotations

import functools
import hashlib
import math
import struct
from dataclasses import dataclass
from typing import Literal

import numba
import numpy as np

from cavenav.core.errors import ConfigError
from cavenav.core.types import Pose, SonarImage
from cavenav.sensors.kernels import _parallel_kernel, mix
from cavenav.world.procedural import cpu_independent
from cavenav.world.raycast import RayCaster
from cavenav.world.silt import SiltCloud

__all__ = [
    "MULTIBEAM",
    "PING360",
    "SONARS",
    "Sonar",
    "SonarConfig",
    "absorption_db_per_m",
    "fan_lookup",
]

GRADIANS = 400  # a Ping360 head's angles per turn


def absorption_db_per_m(
    frequency_khz: float,
    temperature_c: float = 15.0,
    salinity_psu: float = 0.0,
    depth_m: float = 0.0,
) -> float:
    """Sound absorption in water, dB per metre, after Francois and Garrison (1982): boric
    acid and magnesium sulphate relaxations (salt water only) plus pure water's viscosity."""
    t, s, d, f = temperature_c, salinity_psu, depth_m, frequency_khz
    c = 1412.0 + 3.21 * t + 1.19 * s + 0.0167 * d
    kelvin = t + 273.0
    boric = 0.0
    magnesium = 0.0
    if s > 0:
        f1 = 2.8 * math.sqrt(s / 35.0) * 10 ** (4.0 - 1245.0 / kelvin)
        boric = 8.86 / c * 10 ** (0.78 * 8.0 - 5.0) * f1 * f**2 / (f1**2 + f**2)
        f2 = 8.17 * 10 ** (8.0 - 1990.0 / kelvin) / (1.0 + 0.0018 * (s - 35.0))
        a2 = 21.44 * s / c * (1.0 + 0.025 * t)
        p2 = 1.0 - 1.37e-4 * d + 6.2e-9 * d**2
        magnesium = a2 * p2 * f2 * f**2 / (f2**2 + f**2)
    if t <= 20.0:
        a3 = 4.937e-4 - 2.59e-5 * t + 9.11e-7 * t**2 - 1.50e-8 * t**3
    else:
        a3 = 3.964e-4 - 1.146e-5 * t + 1.45e-7 * t**2 - 6.5e-10 * t**3
    water = a3 * (1.0 - 3.83e-5 * d + 4.9e-10 * d**2) * f**2
    return (boric + magnesium + water) / 1000.0


@dataclass(frozen=True)
class SonarConfig:
    """One imaging sonar's settings.

    Attributes:
        kind: "ping360" (a mechanically scanned single beam) or "multibeam" (a fixed fan).
        frequency_khz: the carrier: it sets the absorption.
        beam_width_deg: one beam's horizontal width (Ping360: 2 degrees; an M750d's
            beams: about 1 degree at 750 kHz).
        aperture_deg: the vertical aperture (Ping360 25, M750d 20 at 750 kHz).
        range_m: the far end of the range; the near end is `blanking_m`.
        samples: range bins over it (Ping360: 200-1200; Ping Viewer takes 1200 at any
            range up to 50 m).
        fov_deg: the multibeam's horizontal fan (130 at 750 kHz).
        beams: the multibeam's beams across it (512).
        sector_deg: the scanning sonar's sector, centred ahead (360: a full turn).
        step_grad: its head's step in gradians (1 = 0.9 degrees).
        ping_overhead_s: what a ping costs besides the echo's round trip.
        pulse_us: the transmitted pulse: an echo spreads over c * pulse / 2 of range;
            None: as Ping Viewer sets a Ping360's, round(8000 * range / c) microseconds
            (107 at 20 m), within 5-500.
        blanking_m: bins nearer than this read 0 (the transducer still rings).
        gain_db: receiver gain over the display's floor.
        dynamic_db: the decibels the 8 bits span.
        noise_db: the receiver's noise before the time-varied gain, relative to a wall's
            echo at 1 m and normal incidence.
        rays_vertical, rays_horizontal: rays cast per beam.
        temperature_c, salinity_psu: the water, for the absorption and the speed of sound.
        silt_backscatter: volume backscatter per g/m^3 of silt per metre of range (each
            sample hears the pulse's length of water), relative to a wall's echo.
        snow_per_m3: marine snow's scatterers per cubic metre.
    """

    kind: Literal["ping360", "multibeam"]
    frequency_khz: float
    beam_width_deg: float
    aperture_deg: float
    range_m: float = 20.0
    samples: int = 1200
    fov_deg: float = 0.0
    beams: int = 1
    sector_deg: float = 120.0
    step_grad: int = 1
    ping_overhead_s: float = 0.02
    pulse_us: float | None = None
    blanking_m: float = 0.3
    gain_db: float = 0.0
    dynamic_db: float = 45.0
    noise_db: float = -78.0
    rays_vertical: int = 12
    rays_horizontal: int = 1
    temperature_c: float = 15.0
    salinity_psu: float = 0.0
    silt_backscatter: float = 2e-4
    snow_per_m3: float = 0.05

    def __post_init__(self) -> None:
        checks = {
            "range_m": self.range_m > self.blanking_m >= 0,
            "samples": 16 <= self.samples <= 4096,
            "beams": self.beams >= 1,
            "sector_deg": 0 < self.sector_deg <= 360,
            "step_grad": 1 <= self.step_grad <= 50,
            "rays": self.rays_vertical >= 1 and self.rays_horizontal >= 1,
            "frequency_khz": 10 <= self.frequency_khz <= 3000,
        }
        bad = [name for name, ok in checks.items() if not ok]
        if bad:
            raise ConfigError(
                f"sonar {self.kind}: bad {', '.join(bad)} (range {self.range_m} m over "
                f"blanking {self.blanking_m} m, 16-4096 samples, a sector of 0-360 degrees, "
                "a step of 1-50 gradians, 10-3000 kHz)"
            )

    @property
    def bin_m(self) -> float:
        return self.range_m / self.samples

    @property
    def sound_speed_m_s(self) -> float:
        """Speed of sound of the water (the same formula's, Francois and Garrison)."""
        return 1412.0 + 3.21 * self.temperature_c + 1.19 * self.salinity_psu

    @property
    def pulse_s(self) -> float:
        """The transmitted pulse's length (`pulse_us`, or Ping Viewer's automatic one)."""
        if self.pulse_us is not None:
            return self.pulse_us * 1e-6
        return min(max(round(8000.0 * self.range_m / self.sound_speed_m_s), 5), 500) * 1e-6

    @property
    def ping_s(self) -> float:
        """One ping: the echo's round trip over the range, plus the overhead."""
        return 2.0 * self.range_m / self.sound_speed_m_s + self.ping_overhead_s

    def bearings_deg(self) -> np.ndarray:
        """Every beam's bearing, right of ahead positive: the multibeam's fan, or the
        scanning head's angles over its sector (a full turn: all of them)."""
        if self.kind == "multibeam":
            half = self.fov_deg / 2.0
            return np.linspace(-half, half, self.beams)
        steps = GRADIANS // self.step_grad
        angles = np.arange(steps) * self.step_grad * 360.0 / GRADIANS
        return np.where(angles > 180.0, angles - 360.0, angles)


# Blue Robotics' published figures: 750 kHz, 2 x 25 degree beam, 0.75-50 m.
PING360 = SonarConfig(
    kind="ping360", frequency_khz=750.0, beam_width_deg=2.0, aperture_deg=25.0,
    blanking_m=0.75, rays_vertical=12, rays_horizontal=3,
)  # fmt: skip
# Blueprint Subsea's Oculus M750d at its low frequency: 130 x 20 degrees, 512 beams.
MULTIBEAM = SonarConfig(
    kind="multibeam", frequency_khz=750.0, beam_width_deg=1.0, aperture_deg=20.0, samples=512,
    fov_deg=130.0, beams=512, rays_vertical=10, blanking_m=0.2,
)  # fmt: skip
SONARS = {"ping360": PING360, "multibeam": MULTIBEAM}


@functools.lru_cache(maxsize=8)
def fan_lookup(config: SonarConfig, size: int) -> np.ndarray:
    """(size, width) indices into the (beams, bins) array, flattened, for each pixel of the
    displayed image (-1: outside the fan): a multibeam's fan with its apex at the bottom
    centre, or the scanning sonar's disc with the head at its centre; heading up, bearings
    to the right of ahead on the right. The angles come from the C library, so the image
    sent to a model is the same on every CPU; computed once per sonar and size (shared:
    read it, never write it)."""
    bearings = config.bearings_deg()
    if config.kind == "multibeam":
        half = math.radians(config.fov_deg / 2.0)
        width = 2 * math.ceil(size * math.sin(min(half, math.pi / 2)))
        x = np.arange(width) - width / 2 + 0.5
        y = size - np.arange(size)[:, None] - 0.5
    else:
        width = size
        x = np.arange(size) - size / 2 + 0.5
        y = size / 2 - np.arange(size)[:, None] - 0.5
    scale = config.range_m / (size if config.kind == "multibeam" else size / 2)
    x, y = np.broadcast_arrays(x, y)
    r = np.sqrt(x * x + y * y) * scale
    # The C library's arctangent, pixel by pixel: numpy's may round otherwise on another CPU.
    atan2 = [math.atan2(a, b) for a, b in zip(x.ravel().tolist(), y.ravel().tolist(), strict=True)]
    bearing = np.degrees(np.array(atan2).reshape(x.shape))
    span = bearings[-1] - bearings[0] if config.kind == "multibeam" else 360.0
    pitch = span / max(len(bearings) - 1, 1) if config.kind == "multibeam" else span / len(bearings)
    if config.kind == "multibeam":
        beam = np.rint((bearing - bearings[0]) / pitch).astype(np.int64)
        inside = (beam >= 0) & (beam < len(bearings))
    else:
        beam = np.rint(np.mod(bearing, 360.0) / pitch).astype(np.int64) % len(bearings)
        inside = np.ones_like(beam, bool)
    bins = np.floor(r / config.bin_m).astype(np.int64)
    inside &= bins < config.samples
    lookup = np.where(inside, beam * config.samples + bins, -1)
    lookup.setflags(write=False)  # shared by every sonar of this kind and size
    return lookup


@dataclass(frozen=True)
class _Head:
    """Where the scanning head is: its angle (index into `bearings_deg`), the direction it
    turns (+1 or -1, back and forth over a sector), and the time owed to the next ping."""

    index: int = 0
    direction: int = 1
    owed_s: float = 0.0


def _sector_indices(config: SonarConfig) -> np.ndarray:
    """The head's angles (indices into `bearings_deg`) in its sector, left to right."""
    bearings = config.bearings_deg()
    half = config.sector_deg / 2.0
    inside = np.flatnonzero(np.abs(bearings) <= half + 1e-9)
    return inside[np.argsort(bearings[inside])]


def _swept(config: SonarConfig, head: _Head, seconds: float) -> tuple[np.ndarray, _Head]:
    """The angles (indices into the sector) the head pings in ``seconds`` from ``head``,
    and where it is then: round and round for a full turn, back and forth otherwise."""
    count = len(_sector_indices(config))
    pings = int((seconds + head.owed_s) / config.ping_s + 1e-9)  # a sweep's own time: all of it
    owed = seconds + head.owed_s - pings * config.ping_s
    index, direction, visited = head.index, head.direction, []
    full_turn = config.sector_deg >= 360.0
    for _ in range(min(pings, 4 * count)):
        visited.append(index)
        if full_turn:
            index = (index + 1) % count
        else:
            if not 0 <= index + direction < count:
                direction = -direction
            index = index + direction if count > 1 else index
    return np.array(visited, np.int64), _Head(index, direction, owed)


class Sonar:
    """One imaging sonar on one vehicle in one cave: renders its echoes at a pose.

    Stateful only for the scanning sonar, whose head turns between observations: `reset`
    at an episode's start puts it at the left end of its sector.
    """

    def __init__(self, caster: RayCaster, config: SonarConfig, image_size: int = 400):
        self.caster, self.config = caster, config
        self._bearings = config.bearings_deg()
        self._sector = _sector_indices(config) if config.kind == "ping360" else None
        self._alpha = absorption_db_per_m(
            config.frequency_khz, config.temperature_c, config.salinity_psu
        )
        v, h = config.rays_vertical, config.rays_horizontal
        self._elevations = np.radians(_offsets(v) * config.aperture_deg)
        self._widths = np.radians(_offsets(h) * config.beam_width_deg)
        # The two-way beam pattern over the rays, width-major as `_body_rays` lays them.
        pattern = np.outer(_pattern(_offsets(h)), _pattern(_offsets(v))).ravel()
        self._pattern = pattern / pattern.sum()
        self._rays = self._body_rays(self._bearings)  # every beam's, (beams, rays, 3)
        self._lookup = fan_lookup(config, image_size)
        centres = (np.arange(config.samples) + 0.5) * config.bin_m
        absorbed = cpu_independent(lambda x: 10.0**x, 0.2 * self._alpha * centres)
        gain = centres**2 * absorbed  # the time-varied gain, 20 log r + 2 alpha r
        self._noise = 10 ** (config.noise_db / 10.0) * gain
        self._steps = _level_steps(config)
        self._pulse_m = config.sound_speed_m_s * config.pulse_s / 2.0
        self._pulse_bins = max(1, round(self._pulse_m / config.bin_m))
        self._blanked = centres < config.blanking_m
        # Marine snow: the chance that a beam's slice of a bin (r^2 * solid angle * bin of
        # water) holds a speck (`SPECK`).
        solid = math.radians(config.beam_width_deg) * math.radians(config.aperture_deg)
        chance = config.snow_per_m3 * solid * centres**2 * config.bin_m
        self._snow = np.minimum(chance, 1.0).astype(np.float32)
        self.reset()

    def reset(self) -> None:
        """Start an episode: an empty disc, the head at the left end of its sector."""
        self._echoes = np.zeros((len(self._bearings), self.config.samples), np.uint8)
        self._age_s = np.full(len(self._bearings), np.inf)
        self._heading_at = np.zeros(len(self._bearings))  # radians, the vehicle's at each ping
        self._moved_m = np.zeros(len(self._bearings))  # how far it went since each ping
        self._last: Pose | None = None
        self._head = _Head()

    def observe(
        self, pose: Pose, seconds: float, seed: int = 0, silt: SiltCloud | None = None
    ) -> SonarImage:
        """What the sonar shows at ``pose`` after ``seconds`` since the last observation
        (the scanning head turns meanwhile; the multibeam pings once, whatever the time);
        ``seed`` draws the speckle, with the pose."""
        if self._sector is None:
            fresh = np.arange(len(self._bearings))
        else:
            swept, self._head = _swept(self.config, self._head, max(seconds, 0.0))
            fresh = np.unique(self._sector[swept])
        self._age_s += max(seconds, 0.0)
        if self._last is not None:
            self._moved_m += math.dist(pose.position, self._last.position)
        self._last = pose
        if len(fresh):
            bearings = self._bearings[fresh]
            self._echoes[fresh] = self._ping(pose, self._rays[fresh], bearings, seed, silt)
            self._age_s[fresh] = 0.0
            self._heading_at[fresh] = pose.psi
            self._moved_m[fresh] = 0.0
        turned = (np.degrees(pose.psi - self._heading_at) + 180.0) % 360.0 - 180.0
        return SonarImage(
            kind=self.config.kind,
            echoes=self._echoes.copy(),
            bearings_deg=self._bearings,
            range_m=self.config.range_m,
            fan=self.fan(self._echoes),
            age_s=self._age_s.copy(),
            turned_deg=turned,
            moved_m=self._moved_m.copy(),
            frequency_khz=self.config.frequency_khz,
            beam_width_deg=self.config.beam_width_deg,
            aperture_deg=self.config.aperture_deg,
        )

    @property
    def sweep_s(self) -> float:
        """How long one sweep takes: the scanning head's sector, or one multibeam ping."""
        pings = 1 if self._sector is None else len(self._sector)
        return pings * self.config.ping_s

    def fan(self, echoes: np.ndarray) -> np.ndarray:
        """The displayed image of a (beams, bins) array (0 outside the fan)."""
        flat = np.append(echoes.ravel(), np.uint8(0))
        return flat[self._lookup]  # -1 picks the appended 0

    def ping(
        self, pose: Pose, bearings_deg: np.ndarray, seed: int = 0, silt: SiltCloud | None = None
    ) -> np.ndarray:
        """(n, bins) uint8 echo strengths of beams at ``bearings_deg`` from ``pose``."""
        bearings = np.asarray(bearings_deg, np.float64)
        return self._ping(pose, self._body_rays(bearings), bearings, seed, silt)

    def _ping(
        self,
        pose: Pose,
        body_rays: np.ndarray,
        bearings_deg: np.ndarray,
        seed: int,
        silt: SiltCloud | None,
    ) -> np.ndarray:
        """`ping` of the beams whose rays in the body frame are ``body_rays``."""
        cfg = self.config
        b = body_rays.reshape(-1, 3)
        # Turned into the world by the heading alone: products and sums, no function that
        # a CPU's vector unit might round otherwise.
        directions = b[:, :1] * pose.forward + b[:, 1:2] * pose.right
        directions[:, 2] += b[:, 2]
        per_beam = body_rays.shape[1]
        rays = np.empty((len(directions), 6), np.float32)
        rays[:, :3] = pose.position
        rays[:, 3:] = directions
        hit = self.caster.cast_raw_rays(rays)
        t = hit["t_hit"].astype(np.float64)
        n = hit["primitive_normals"].astype(np.float64)
        cosine = np.abs(
            n[:, 0] * directions[:, 0] + n[:, 1] * directions[:, 1] + n[:, 2] * directions[:, 2]
        )
        beam = np.repeat(np.arange(len(bearings_deg)), per_beam)
        keep = np.isfinite(t) & (t < cfg.range_m)
        weight = np.tile(self._pattern, len(bearings_deg))[keep]
        energy = cosine[keep] * weight  # after the time-varied gain (module docstring)
        index = beam[keep] * cfg.samples + (t[keep] / cfg.bin_m).astype(np.int64)
        shape = (len(bearings_deg), cfg.samples)
        echo = np.bincount(index, energy, minlength=shape[0] * shape[1]).reshape(shape)
        echo = _smeared(echo, self._pulse_bins)
        # Sound goes no farther than a beam's nearest rock: nothing in the water beyond.
        nearest = np.where(keep, t, np.inf).reshape(-1, per_beam).min(axis=1)
        reach = np.minimum(nearest / cfg.bin_m, cfg.samples).astype(np.int64)
        if silt is not None and silt.puffs:
            shadowed = np.arange(cfg.samples)[None, :] >= reach[:, None]
            echo += np.where(shadowed, 0.0, self._silt_echo(pose, body_rays, silt))
        out = np.empty(shape, np.uint8)
        key = np.uint64(_ping_key(seed, pose, bearings_deg))
        _develop(echo, self._noise, self._snow, reach, key, self._steps, _EXPONENTIAL, out)
        out[:, self._blanked] = 0
        return out

    def _silt_echo(self, pose: Pose, body_rays: np.ndarray, silt: SiltCloud) -> np.ndarray:
        """(n, bins) volume echo of the silt along each beam's middle ray, in proportion to
        its concentration (after the time-varied gain: module docstring)."""
        cfg = self.config
        centres = (np.arange(cfg.samples) + 0.5) * cfg.bin_m
        middle = body_rays[:, body_rays.shape[1] // 2]
        axes = middle[:, :1] * pose.forward + middle[:, 1:2] * pose.right
        axes[:, 2] += middle[:, 2]
        points = pose.position + axes[:, None, :] * centres[None, :, None]
        grams = silt.concentration(points.reshape(-1, 3)).reshape(len(axes), cfg.samples)
        return cfg.silt_backscatter * grams * self._pulse_m  # the water one sample hears

    def _body_rays(self, bearings_deg: np.ndarray) -> np.ndarray:
        """(n, rays, 3) the unit rays of beams at ``bearings_deg`` in the body frame
        (forward, right, up): across each beam's width, then up its aperture, with the C
        library's sines and cosines (`cpu_independent`): the same rays on every CPU."""
        across = (np.radians(bearings_deg)[:, None] + self._widths[None, :]).reshape(-1)
        cos_a, sin_a = (cpu_independent(f, across) for f in (math.cos, math.sin))
        cos_e, sin_e = (cpu_independent(f, self._elevations) for f in (math.cos, math.sin))
        rays = np.stack(
            [
                cos_a[:, None] * cos_e[None, :],
                sin_a[:, None] * cos_e[None, :],
                np.broadcast_to(sin_e[None, :], (len(across), len(cos_e))),
            ],
            axis=-1,
        )
        return rays.reshape(len(bearings_deg), -1, 3)


# A beam's rays reach out to this many times its -3 dB width (a ray per 1/n of it).
_SPAN = 1.5


def _offsets(count: int) -> np.ndarray:
    """Where ``count`` rays sit across a beam, in units of its -3 dB width: centred, and
    spanning `_SPAN` of it (one ray: on the axis)."""
    return ((np.arange(count) + 0.5) / count - 0.5) * (_SPAN if count > 1 else 0.0)


def _pattern(offsets: np.ndarray) -> np.ndarray:
    """The two-way (transmit times receive) sensitivity at ``offsets`` from the axis, in
    units of the -3 dB width: a Gaussian main lobe, -3 dB one way at the width's edge, so
    -6 dB two ways."""
    return cpu_independent(lambda x: 10.0**x, -0.6 * (2.0 * offsets) ** 2)


def _develop_bins(
    echo: np.ndarray,
    noise: np.ndarray,
    snow: np.ndarray,
    reach: np.ndarray,
    key: np.uint64,
    steps: np.ndarray,
    exponential: np.ndarray,
    out: np.ndarray,
) -> None:
    """Write ``out`` (n, bins) uint8: ``echo`` with marine snow (with chance ``snow`` per
    bin, up to the beam's first rock at bin ``reach``), speckle (the gamma of four looks,
    a coherent echo averaged over four samples: the mean of four exponentials) and the
    receiver's ``noise`` (exponential energy per bin), as the number of ``steps`` (the
    energies between the 8-bit levels, rising) it reaches. The exponentials are read
    from ``exponential``, a table of their quantiles at a 16-bit index: no logarithm is
    taken, and each bin draws from a hash of ``key`` and its index, the same bits in any
    order and on every CPU."""
    mask = np.uint64(0xFFFF)
    bins = echo.shape[1]
    for b in numba.prange(echo.shape[0]):
        for j in range(bins):
            h = mix(key + np.uint64(b * bins + j) * _GOLDEN)
            speckle = 0.0
            for k in range(4):
                speckle += exponential[(h >> np.uint64(16 * k)) & mask]
            h2 = mix(h)
            u = float(h2 & np.uint64(0xFFFFFFFF)) / 4294967296.0
            signal = echo[b, j] + (SPECK if u < snow[j] and j < reach[b] else 0.0)
            energy = 0.25 * signal * speckle + noise[j] * exponential[h2 >> np.uint64(48)]
            low, high = 0, len(steps)
            while low < high:  # how many steps lie at or below the energy
                middle = (low + high) // 2
                if energy >= steps[middle]:
                    low = middle + 1
                else:
                    high = middle
            out[b, j] = low


# Split over the cores; no fast-math liberties.
_develop = _parallel_kernel(_develop_bins, fastmath=False)
# Quantiles of the unit exponential at 65,536 evenly spaced probabilities, through the C
# library's logarithm (`cpu_independent`): the same table on every CPU.
_EXPONENTIAL = -cpu_independent(math.log, (np.arange(65536) + 0.5) / 65536.0)
_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
SPECK = 0.003  # one speck of marine snow's echo, relative to a wall's (-25 dB)


def _level_steps(config: SonarConfig) -> np.ndarray:
    """(255,) the energies at which the 8-bit echo strength steps up from each level to the
    next: 255 levels over `SonarConfig.dynamic_db` decibels above the display's floor,
    ``gain_db`` raising the echoes; the powers of ten through the C library."""
    levels = np.arange(255) + 0.5
    decibels = levels / 255.0 * config.dynamic_db - config.dynamic_db - config.gain_db
    return cpu_independent(lambda x: 10.0**x, decibels / 10.0)


def _smeared(echo: np.ndarray, width: int) -> np.ndarray:
    """(n, bins) echoes spread over ``width`` bins after their start, as a pulse of that
    length spreads them (a running sum along range)."""
    if width <= 1:
        return echo
    total = np.cumsum(echo, axis=1)
    total[:, width:] -= total[:, :-width].copy()
    return total / width


def _ping_key(seed: int, pose: Pose, bearings_deg: np.ndarray) -> int:
    """A seed for one observation's speckle: the episode's seed, the pose's exact bits and
    the beams pinged."""
    data = (
        struct.pack("<q4d", seed, pose.x, pose.y, pose.z, pose.psi)
        + np.asarray(bearings_deg, np.float64).tobytes()
    )
    return int.from_bytes(hashlib.blake2b(data, digest_size=8).digest(), "little")
