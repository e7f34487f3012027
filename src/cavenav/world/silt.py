"""Silt-out: the sediment a vehicle's thrust raises from a cave's floor, and how it hangs.

Cave divers fear it most: a fin kick near a silt floor turns ten metres of visibility
into none, and the cloud hangs, drifts and spreads for minutes. An ROV's thrusters do the
same. Here the water holds a cloud of silt as a few Gaussian puffs, each a mass of fine
sediment with a centre and a spread; the camera sees them as scattering and absorbing
water in front of the rock (`cavenav.sensors.kernels.integrate_silt`). Depth images and
sounders are unaffected (they are exact, as the SPEC has them).

Each step (taken to last `STEP_SECONDS`):

1. **Stirring.** Where the floor lies within `WASH_REACH_M` under the vehicle, its wash
   lifts a puff of ``STIR_G * effort * (1 - h / WASH_REACH_M)^2`` grams, h the floor's
   distance, 0.25 m above the floor and 0.4 m aft of the move, drifting aft at the wash's
   speed. Vertical thrust, which blows straight at the floor, counts fully; horizontal
   thrust half.
2. **Hanging.** Every puff spreads by turbulent diffusion (sigma^2 grows by 2 K dt),
   drifts with its decaying wash and with the cave's current where the water flows
   (`cavenav.world.current`, as it runs at the step's end: upstream, a diver's silt falls
   behind), and sinks at fine silt's settling speed. The silt keeps its own clock of
   `STEP_SECONDS` a step, whatever the move took. Puffs too thin
   to see are dropped, and past `MAX_PUFFS` the two oldest merge.

The stirring constants are assumptions, set by eye to give what divers report (a few
moves close to a silt floor, and the way back is a wall of silt): no measurement of an
ROV's wash was at hand. Each is a module constant to change. The optics of silt are
published figures (below).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from cavenav.core.types import Action, Pose

__all__ = [
    "EXTINCTION_M2_PER_G",
    "SCATTERING_M2_PER_G",
    "SILT_PHASE_G",
    "Puff",
    "SiltCloud",
]

STEP_SECONDS = 2.0  # one step: a 1 m move at a BlueROV2's 0.5 m/s cruise
WASH_REACH_M = 1.5  # the floor this close below the vehicle's centre is stirred
STIR_G = 60.0  # grams a step at full effort lifts from right at the floor
PUFF_SIGMA_M = 0.35  # spread of a freshly raised puff
DIFFUSIVITY_M2_S = 0.01  # turbulent diffusivity of a cave's still water after a wash
SETTLING_M_S = 0.0007  # Stokes settling of 30 um silt
WASH_SPEED_M_S = 0.15  # how fast a fresh puff drifts aft, decaying over WASH_DECAY_S
WASH_DECAY_S = 10.0
MAX_PUFFS = 24
# Mineral silt's mass-specific optics (Babin et al. 2003; Babin & Stramski 2004): about
# 0.5 m^2/g scattering at every colour, absorption rising toward blue (a tan cloud), and
# the strongly forward phase function of large particles.
SCATTERING_M2_PER_G = (0.5, 0.5, 0.5)  # R, G, B
EXTINCTION_M2_PER_G = (0.53, 0.55, 0.59)  # scattering plus absorption
SILT_PHASE_G = 0.9
FAINTEST_G_M3 = 0.01  # a puff whose peak concentration falls below this is dropped
Water = Callable[[np.ndarray], np.ndarray]  # the water's velocity (3,) at a point (3,)


@dataclass(frozen=True)
class Puff:
    """A Gaussian cloud of silt in the water.

    Attributes:
        centre: (3,) metres, world frame.
        sigma: spread (standard deviation), metres.
        mass_g: grams of silt it holds.
        velocity: (3,) drift, m/s (the wash that raised it, decaying).
        age_s: seconds since it was raised.
    """

    centre: tuple[float, float, float]
    sigma: float
    mass_g: float
    velocity: tuple[float, float, float] = (0.0, 0.0, 0.0)
    age_s: float = 0.0

    @property
    def peak_g_m3(self) -> float:
        """Concentration at its centre, g/m^3."""
        return self.mass_g / ((2.0 * math.pi) ** 1.5 * self.sigma**3)


@dataclass(frozen=True)
class SiltCloud:
    """The silt hanging in the water: puffs, oldest first. Empty: clear water."""

    puffs: tuple[Puff, ...] = ()

    def array(self) -> np.ndarray:
        """(m, 5) float32 rows (x, y, z, sigma, mass_g), for the renderer."""
        rows = [(*p.centre, p.sigma, p.mass_g) for p in self.puffs]
        return np.array(rows, np.float32).reshape(-1, 5)

    @property
    def mass_g(self) -> float:
        return float(sum(p.mass_g for p in self.puffs))

    def concentration(self, points: np.ndarray) -> np.ndarray:
        """(m,) silt in g/m^3 at (m, 3) world ``points``."""
        points = np.asarray(points, np.float64).reshape(-1, 3)
        total = np.zeros(len(points))
        for p in self.puffs:
            r2 = np.sum((points - np.asarray(p.centre)) ** 2, axis=1)
            total += p.peak_g_m3 * np.exp(-0.5 * r2 / p.sigma**2)
        return total

    def stirred(
        self, pose: Pose, action: Action, floor_m: float, water: Water | None = None
    ) -> SiltCloud:
        """This cloud after ``action`` ended at ``pose``, with the floor ``floor_m`` below
        the vehicle's centre (inf: none in reach), then one step of hanging in ``water``
        (the current's velocity at a point; None: still)."""
        cloud = self._hung(STEP_SECONDS, water)
        mass = STIR_G * _effort(action) * max(0.0, 1.0 - floor_m / WASH_REACH_M) ** 2
        if mass <= 0.0:
            return cloud
        move = action.forward * pose.forward + action.right * pose.right
        length = float(np.linalg.norm(move))
        aft = -move / length if length > 0 else -pose.forward  # a hover's wash goes aft
        below = pose.position - np.array([0.0, 0.0, floor_m - 0.25])
        puff = Puff(_vec(below + 0.4 * aft), PUFF_SIGMA_M, mass, _vec(WASH_SPEED_M_S * aft))
        return _capped(SiltCloud((*cloud.puffs, puff)))

    def _hung(self, seconds: float, water: Water | None = None) -> SiltCloud:
        kept = []
        for p in self.puffs:
            decay = math.exp(-seconds / WASH_DECAY_S)
            travel = np.asarray(p.velocity) * WASH_DECAY_S * (1.0 - decay)
            if water is not None:
                travel = travel + water(np.asarray(p.centre)) * seconds
            centre = np.asarray(p.centre) + travel - np.array([0.0, 0.0, SETTLING_M_S * seconds])
            sigma = math.sqrt(p.sigma**2 + 2.0 * DIFFUSIVITY_M2_S * seconds)
            moved = replace(
                p,
                centre=_vec(centre),
                sigma=sigma,
                velocity=_vec(np.asarray(p.velocity) * decay),
                age_s=p.age_s + seconds,
            )
            if moved.peak_g_m3 >= FAINTEST_G_M3:
                kept.append(moved)
        return SiltCloud(tuple(kept))


def _effort(action: Action) -> float:
    """How hard the thrusters push the water toward the floor, 0-1.5: vertical thrust
    fully (its wash strikes the floor), horizontal thrust and turning half."""
    vertical = min(1.0, abs(action.up) / 0.5)
    horizontal = min(1.0, math.hypot(action.forward, action.right) + abs(action.yaw_deg) / 45.0)
    return vertical + 0.5 * horizontal


def _capped(cloud: SiltCloud) -> SiltCloud:
    """``cloud`` with its two oldest puffs merged until it holds `MAX_PUFFS`: mass-weighted
    centre and drift, and the spread that keeps their combined second moment."""
    puffs = list(cloud.puffs)
    while len(puffs) > MAX_PUFFS:
        a, b = puffs[0], puffs[1]
        total = a.mass_g + b.mass_g
        wa, wb = a.mass_g / total, b.mass_g / total
        ca, cb = np.asarray(a.centre), np.asarray(b.centre)
        centre = wa * ca + wb * cb
        spread = wa * (a.sigma**2 + np.sum((ca - centre) ** 2) / 3.0)
        spread += wb * (b.sigma**2 + np.sum((cb - centre) ** 2) / 3.0)
        velocity = wa * np.asarray(a.velocity) + wb * np.asarray(b.velocity)
        merged = Puff(_vec(centre), math.sqrt(spread), total, _vec(velocity), max(a.age_s, b.age_s))
        puffs[:2] = [merged]
    return SiltCloud(tuple(puffs))


def _vec(v: np.ndarray) -> tuple[float, float, float]:
    return float(v[0]), float(v[1]), float(v[2])
