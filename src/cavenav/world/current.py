"""Water that flows: a cave's current, and how it carries the vehicle through a move.

Water in a flooded cave flows along the passage, and by continuity faster where the
passage narrows: for a discharge Q (m^3/s) the mean speed at arc length s along the
passage is Q / A(s), where A(s) is the cross-section there. `CurrentField` measures A(s)
on the cave itself: every `SECTION_SPACING_M` along the centre line it casts
`SECTION_RAYS` rays in the plane across the passage, from the centre line and from four
points `SECTION_OFFSET_M` beside, above and below it, and takes the largest area a star
of rays outlines. A point inside rock or a boulder (an even number of surfaces above it)
casts no star, and a section with none is taken from its neighbours. Flow area hidden
behind a boulder from all five points is missed, so speeds beside boulders are somewhat
high.

Real flow is turbulent: on top of the mean, slow gusts of a `Current.gusts` fraction (their
RMS over the mean speed) change the speed along the passage and push across it (0.7 of
that across, as in open-channel turbulence). Each gust is a sum of sinusoids with periods
of 11 to 67 s and seeded phases, carried down the passage with the mean flow (Taylor's
frozen turbulence), so a gust met here arrives downstream later. The water at a point is
that of the nearest section of the centre line: a side passage or a dead end off it
(a maze's) flows as the passage beside it, where real water would stand nearly still.

A positive discharge flows from the exit toward the start, against the vehicle: the
outflow of a spring, which cave divers swim up. A negative one flows toward the exit, as
into a siphon.

**How the water carries the vehicle** (`carry`). A BlueROV2 without a DVL cannot hold its
position, so the current carries it: the move is flown through the water at the
vehicle's cruise speed (`cavenav.core.types.Cruise`): first the turn, then the straight move
of SPEC section 5. For the move's duration the water adds its own horizontal velocity. A
BlueROV2 does hold its depth (pressure sensor) and heading (compass), so it does not go
up or down with the water and does not turn with it. Its thrusters work against the water's
vertical speed instead, and the energy model counts that work
(`cavenav.motion.energy`). The time the pilot takes to decide is not flown: the water waits
while the model thinks, as the SPEC's step-then-wait loop does.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from cavenav.core.errors import ConfigError
from cavenav.core.types import Action, Cruise, Pose
from cavenav.world.procedural import along, arc_length, cpu_independent
from cavenav.world.raycast import RayCaster

__all__ = ["Current", "CurrentField", "Passage", "carry", "cruise_seconds"]

SECTION_SPACING_M = 0.5  # centre-line spacing of the measured cross-sections
SECTION_RAYS = 64
SECTION_OFFSET_M = 1.0
SECTION_REACH_M = 20.0  # a ray that finds no wall counts this far (open water)
SMALLEST_SECTION_M2 = 0.1  # no cave of ours is narrower; keeps Q / A finite
ACROSS_GUSTS = 0.7  # transverse over streamwise turbulence intensity (open channels)
GUST_PERIODS_S = (11.0, 23.0, 41.0, 67.0)
TIME_STEP_S = 0.25  # the carried move is integrated in steps no longer than this


# A scenario file's [water] bound, for every other way in too (flags, gymnasium.make):
# far above any cave's flow, far below a number that carries the vehicle through rock.
MAX_DISCHARGE_M3S = 1e4


@dataclass(frozen=True)
class Current:
    """The flow a cave is given.

    Attributes:
        discharge_m3s: the water flowing through the passage, m^3/s; positive against
            the vehicle (from the exit toward the start), negative with it, 0 still water
            (SPEC section 5's kinematics, exactly).
        gusts: RMS of the gusts over the local mean speed (0 to 1): slow turbulence.
    """

    discharge_m3s: float = 0.0
    gusts: float = 0.2

    def __post_init__(self) -> None:
        if not (math.isfinite(self.discharge_m3s) and abs(self.discharge_m3s) <= MAX_DISCHARGE_M3S):
            raise ConfigError(
                f"discharge {self.discharge_m3s}: give a finite number of m³/s within "
                f"±{MAX_DISCHARGE_M3S:g} (a scenario file's bound)"
            )
        if not (math.isfinite(self.gusts) and 0.0 <= self.gusts <= 1.0):
            raise ConfigError(f"gusts {self.gusts}: give a fraction from 0 to 1")

    @property
    def still(self) -> bool:
        return self.discharge_m3s == 0.0


def _frames(tangents: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors across each tangent (n, 3): one horizontal, one at right angles
    to it and the tangent (up, for a level passage)."""
    side = np.cross(tangents, [0.0, 0.0, 1.0])
    flat = np.linalg.norm(side, axis=1) < 1e-6  # a vertical shaft
    side[flat] = [1.0, 0.0, 0.0]
    side /= np.linalg.norm(side, axis=1, keepdims=True)
    return side, np.cross(side, tangents)


def _resample(line: np.ndarray, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """Points every ``spacing`` metres along a polyline, and their arc lengths."""
    total = arc_length(line)[-1]
    s = np.linspace(0.0, total, max(2, int(math.ceil(total / spacing)) + 1))
    return along(line, s), s


def _star_areas(
    caster: RayCaster, origins: np.ndarray, side: np.ndarray, up: np.ndarray
) -> np.ndarray:
    """(n,) the area of the star of rays from each origin across the passage, m^2."""
    angles = np.linspace(0.0, 2.0 * math.pi, SECTION_RAYS, endpoint=False)
    cos, sin = cpu_independent(math.cos, angles), cpu_independent(math.sin, angles)
    directions = cos[None, :, None] * side[:, None] + sin[None, :, None] * up[:, None]
    rays_from = np.broadcast_to(origins[:, None], directions.shape)
    reach = np.minimum(caster.first_hit(rays_from, directions).astype(np.float64), SECTION_REACH_M)
    # The star polygon: triangles between neighbouring rays.
    return 0.5 * math.sin(angles[1]) * (reach * np.roll(reach, -1, axis=1)).sum(axis=1)


def _section_areas(caster: RayCaster, points: np.ndarray, tangents: np.ndarray) -> np.ndarray:
    """The cross-section of the passage at each point, m^2 (module docstring)."""
    side, up = _frames(tangents)
    shifts = SECTION_OFFSET_M * np.array([[0, 0], [1, 0], [-1, 0], [0, 1], [0, -1]])
    origins = points[None] + shifts[:, None, :1] * side + shifts[:, None, 1:] * up
    flat = origins.reshape(-1, 3)
    stars = _star_areas(caster, flat, np.tile(side, (5, 1)), np.tile(up, (5, 1)))
    up = caster.count_intersections(flat, np.broadcast_to([0.0, 0.0, 1.0], flat.shape))
    in_water = (up % 2 == 1).reshape(5, -1)
    if in_water[0].sum() < max(2, len(points) // 2):  # not a closed mesh: no test
        in_water[:] = True
    areas = np.where(in_water, stars.reshape(5, -1), 0.0).max(axis=0)
    known = in_water.any(axis=0)
    if known.any():
        s = np.arange(len(points))
        areas = np.interp(s, s[known], areas[known])
    # Rounded, so that the last bits of a ray cast, which may differ between CPUs, rarely
    # reach the water's speed.
    return np.round(np.maximum(areas, SMALLEST_SECTION_M2), 3)


@dataclass(frozen=True, eq=False)
class CurrentField:
    """The water's velocity everywhere in one cave, for one `Current`.

    Attributes:
        current: the discharge and gusts.
        points: (n, 3) centre line, every `SECTION_SPACING_M`, start to exit.
        arcs: (n,) arc length of each point.
        tangents: (n, 3) unit direction of the passage (toward the exit) at each point.
        areas: (n,) cross-section, m^2.
        phases: (3, len(GUST_PERIODS_S)) the gusts' seeded phases.
    """

    current: Current
    points: np.ndarray
    arcs: np.ndarray
    tangents: np.ndarray
    areas: np.ndarray
    phases: np.ndarray

    @classmethod
    def measure(
        cls, caster: RayCaster, centreline: np.ndarray, current: Current, seed: int
    ) -> CurrentField:
        """Measure the cave along ``centreline`` (start to exit); ``seed`` draws the gusts."""
        if len(centreline) < 2:
            raise ConfigError("a current needs a centre line of two points or more")
        points, arcs = _resample(np.asarray(centreline, np.float64), SECTION_SPACING_M)
        tangents = np.gradient(points, axis=0)
        tangents /= np.maximum(np.linalg.norm(tangents, axis=1, keepdims=True), 1e-12)
        phases = np.random.default_rng(seed).uniform(0.0, 2.0 * math.pi, (3, len(GUST_PERIODS_S)))
        return cls(
            current, points, arcs, tangents, _section_areas(caster, points, tangents), phases
        )

    @cached_property
    def speeds(self) -> np.ndarray:
        """(n,) mean speed along the passage at each section, m/s (Q / A)."""
        return abs(self.current.discharge_m3s) / self.areas

    @cached_property
    def _gust_speed(self) -> float:
        """How fast gusts travel down the passage: the mean flow's speed."""
        return max(float(self.speeds.mean()), 1e-6)

    def _gust(self, tau: float) -> np.ndarray:
        """(3,) unit-RMS gusts (along, side, up) at advected time ``tau``; through the C
        library's sine, the same on every CPU (`cpu_independent`)."""
        omega = 2.0 * math.pi / np.asarray(GUST_PERIODS_S)
        waves = cpu_independent(math.sin, omega * tau + self.phases)
        return waves.sum(axis=1) * math.sqrt(2.0 / len(GUST_PERIODS_S))

    def velocity(self, position: np.ndarray, time_s: float) -> np.ndarray:
        """(3,) the water's velocity at ``position`` and ``time_s``, m/s (world frame)."""
        if self.current.still:
            return np.zeros(3)
        k = int(np.argmin(((self.points - position) ** 2).sum(axis=1)))
        downstream = -math.copysign(1.0, self.current.discharge_m3s)  # +1: toward the exit
        tau = time_s - downstream * self.arcs[k] / self._gust_speed  # gusts go with the flow
        along, side, up = self.current.gusts * self._gust(tau) * [1, ACROSS_GUSTS, ACROSS_GUSTS]
        side_axis, up_axis = _frames(self.tangents[k : k + 1])
        flow = (1.0 + along) * self.tangents[k] + side * side_axis[0] + up * up_axis[0]
        return downstream * self.speeds[k] * flow


def cruise_seconds(action: Action, cruise: Cruise) -> tuple[float, float]:
    """How long ``action`` takes through the water: (the turn, the straight move)."""
    distance = math.sqrt(action.forward**2 + action.right**2 + action.up**2)
    return abs(action.yaw_deg) / cruise.yaw_deg_s, distance / cruise.speed_m_s


@dataclass(frozen=True)
class Passage:
    """A move flown through the water.

    Attributes:
        carried_m: (x, y) metres the water carried the vehicle off the move; (0, 0) in
            still water (`cavenav.motion.kinematics.carried` adds them to the move).
        seconds: how long it took.
        dt: (k,) the integration's time steps, s.
        through_water: (k, 3) the vehicle's velocity through the water in each, body frame
            (forward, right, up), m/s: what its thrusters work against.
    """

    carried_m: tuple[float, float]
    seconds: float
    dt: np.ndarray
    through_water: np.ndarray


def carry(
    field: CurrentField | None,
    pose: Pose,
    action: Action,
    moved: Pose,
    clock_s: float,
    cruise: Cruise,
) -> Passage:
    """Fly ``action`` from ``pose`` starting at ``clock_s`` (module docstring): ``moved``
    is where the move alone takes the vehicle (`cavenav.motion.kinematics.Motion.move`), along
    which the water is met; with no field, or still water, nothing is carried."""
    turn_s, move_s = cruise_seconds(action, cruise)
    turn_k, move_k = math.ceil(turn_s / TIME_STEP_S), math.ceil(move_s / TIME_STEP_S)
    dt = np.concatenate(
        [np.full(turn_k, turn_s / max(turn_k, 1)), np.full(move_k, move_s / max(move_k, 1))]
    )
    mid = np.cumsum(dt) - dt / 2
    commanded_speed = np.array([action.forward, action.right, action.up]) / max(move_s, 1e-12)
    through_water = np.where((np.arange(len(dt)) >= turn_k)[:, None], commanded_speed, 0.0)
    if field is None or field.current.still or len(dt) == 0:
        return Passage((0.0, 0.0), turn_s + move_s, dt, through_water)
    start, delta = pose.position, moved.position - pose.position
    drift = np.zeros(3)
    for i in range(len(dt)):
        along = 0.0 if move_s == 0 else min(max((mid[i] - turn_s) / move_s, 0.0), 1.0)
        water = field.velocity(start + along * delta + drift, clock_s + mid[i])
        drift[:2] += water[:2] * dt[i]  # carried across; the depth is held
        through_water[i, 2] -= water[2]  # and held against the water's rise or fall
    return Passage((float(drift[0]), float(drift[1])), turn_s + move_s, dt, through_water)
