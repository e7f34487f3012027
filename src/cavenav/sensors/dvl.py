"""A Doppler velocity log, Water Linked DVL A50-like: velocity over the ground and altitude
from four beams, ranged with the cave's ray caster.

The A50's published figures (waterlinked.github.io/docs/dvl/dvl-a50, Blue Robotics'
product page): four beams 22.5 degrees from vertical, 1 MHz, altitude 0.05-50 m, a ping
rate of 4-26 Hz that falls with altitude (its range modes: 15 Hz below 0.6 m, 10 Hz to
3 m, 5-6 Hz to 14 m, 7-8 Hz to 36 m, 2-4 Hz beyond), long-term accuracy of +-1.01% of the
speed and +-0.1 cm/s (standard edition).

Modelled: each episode draws a scale error within +-1.01% and an offset within
+-0.1 cm/s per axis (the long-term accuracy: constant over a dive), and each ping adds
white noise of `DvlConfig.ping_noise_m_s` (an assumption: the A50's datasheet gives no
single-ping figure); the reading over a move is the mean of the pings it lasted, so its
noise falls with the square root of their number. Bottom lock needs at least three beams
that find a surface within 50 m and an altitude of at least 0.05 m; without it the
velocity is NaN, as the A50 reports ``velocity_valid`` false. In a cave the "bottom" is
whatever the four downward beams hit: floor, or a wall close by.
"""

from __future__ import annotations

import hashlib
import math
import struct
from dataclasses import dataclass

import numpy as np

from cavenav.core.types import DvlReading, Pose
from cavenav.world.raycast import RayCaster

__all__ = ["A50", "DopplerLog", "DvlConfig", "ping_rate_hz"]


@dataclass(frozen=True)
class DvlConfig:
    """A DVL's figures (defaults: the A50's, module docstring)."""

    beam_angle_deg: float = 22.5
    min_altitude_m: float = 0.05
    max_range_m: float = 50.0
    scale_error: float = 0.0101
    offset_error_m_s: float = 0.001
    ping_noise_m_s: float = 0.01
    beams_for_lock: int = 3


A50 = DvlConfig()

# (altitude below which, pings a second): the A50's range modes, each at its mid rate.
_RATES = ((0.6, 15.0), (3.0, 10.0), (14.0, 5.5), (36.0, 7.5), (math.inf, 3.0))


def ping_rate_hz(altitude_m: float) -> float:
    """The A50's ping rate at ``altitude_m`` (its range modes, module docstring)."""
    return next(rate for below, rate in _RATES if altitude_m < below)


class DopplerLog:
    """A DVL on one vehicle in one cave; `reset` draws a dive's long-term errors."""

    def __init__(self, caster: RayCaster, config: DvlConfig = A50):
        self.caster, self.config = caster, config
        tilt = math.radians(config.beam_angle_deg)
        # Beams in an X, between the body's axes (forward, right, down), as the A50's.
        azimuths = [math.radians(a) for a in (45.0, 135.0, 225.0, 315.0)]
        self._beams = np.array(
            [[math.sin(tilt) * math.cos(a), math.sin(tilt) * math.sin(a), -math.cos(tilt)]
             for a in azimuths]
        )  # fmt: skip
        self.reset(0)

    def reset(self, seed: int) -> None:
        """Draw this dive's scale and offset errors from ``seed``."""
        rng = np.random.default_rng([seed, 0xD71])
        cfg = self.config
        self._scale = 1.0 + rng.uniform(-cfg.scale_error, cfg.scale_error, 3)
        self._offset = rng.uniform(-cfg.offset_error_m_s, cfg.offset_error_m_s, 3)
        self._seed = seed

    def beam_ranges(self, pose: Pose) -> np.ndarray:
        """(4,) each beam's slant range at ``pose``, ``inf`` beyond the maximum."""
        forward, right = pose.forward, pose.right
        world = (
            self._beams[:, :1] * forward + self._beams[:, 1:2] * right
            + self._beams[:, 2:] * np.array([0.0, 0.0, 1.0])
        )  # fmt: skip
        t = self.caster.first_hit(np.tile(pose.position, (4, 1)), world).astype(np.float64)
        return np.where(t <= self.config.max_range_m, t, np.inf)

    def measure(self, before: Pose, after: Pose, seconds: float) -> DvlReading:
        """What the DVL reports for the move from ``before`` to ``after`` over ``seconds``:
        the mean velocity over the ground, in the body frame at ``after`` (forward, left,
        up), ranged at ``after``."""
        cfg = self.config
        ranges = self.beam_ranges(after)
        found = np.isfinite(ranges)
        altitude = (
            float(np.mean(ranges[found]) * math.cos(math.radians(cfg.beam_angle_deg)))
            if found.any()
            else math.nan
        )
        locked = int(found.sum()) >= cfg.beams_for_lock and altitude >= cfg.min_altitude_m
        pings = max(1, round(seconds * ping_rate_hz(altitude))) if locked else 1
        sigma = cfg.ping_noise_m_s / math.sqrt(pings)
        if not locked or seconds <= 0:
            velocity = np.full(3, math.nan)
        else:
            moved = after.position - before.position
            body = np.array([moved @ after.forward, -(moved @ after.right), moved[2]])
            rng = np.random.default_rng(_move_key(self._seed, after))
            velocity = body / seconds * self._scale + self._offset + rng.normal(0, sigma, 3)
        return DvlReading(
            velocity_m_s=velocity,
            locked=bool(locked and seconds > 0),
            altitude_m=altitude if locked else math.nan,
            beam_ranges_m=ranges,
            seconds=float(seconds),
            sigma_m_s=sigma,
        )


def _move_key(seed: int, pose: Pose) -> int:
    data = struct.pack("<q4d", seed, pose.x, pose.y, pose.z, pose.psi)
    return int.from_bytes(hashlib.blake2b(data, digest_size=8).digest(), "little")
