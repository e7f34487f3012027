"""Closed-loop moves on an ArduSub vehicle: the sticks that bring the measured pose to a
goal, and when a move counts as done.

Against ArduSub's own software-in-the-loop build (4.5.7, ``../shared/sitl``), timed
sticks do not land where they were meant: in ALT_HOLD nothing brakes the horizontal
motion (a 1.25 s push of 0.36 m coasts on to 0.98 m), the yaw and throttle sticks have
dead bands that swallow small demands, and a pose read half a second after the sticks
go neutral still moves at 0.3 m/s. So a move here is flown on the measured state:

- **Horizontal**: a speed profile. The wanted velocity is the error times
  ``approach_gain``, at most ``cruise_mps``; each stick is the one that holds its part
  of it (``stick_limit`` gives ``forward_mps``) out of the dead band, plus
  ``velocity_gain`` times the speed still missing. Arriving, the wanted speed falls to
  zero and the stick brakes.
- **Heading**: ALT_HOLD's yaw stick asks for a turn rate. The stick is the dead band
  (``stick_dead_band``, which the x and y sticks share) plus ``yaw_gain`` per degree of
  error, at most ``stick_limit``.
- **Depth**: ALT_HOLD's throttle asks for a climb rate outside its dead band and holds
  the depth inside it. The stick leaves the dead band by ``climb_gain`` per m/s of the
  wanted velocity's vertical part.

A move is *reached* when the pose is within ``position_tolerance_m`` horizontally,
``depth_tolerance_m`` vertically and ``yaw_tolerance_deg`` in heading, and *still*:
speed under ``still_mps`` (``still_climb_mps`` vertically) and turn rate under
``still_dps``, all for
``still_for_s``, judged from the vehicle's own reports (LOCAL_POSITION_NED's velocity,
ATTITUDE's yaw rate). The gains and thresholds are settings of
`cavenav.vehicle.mavlink.BridgeConfig`, tuned against the SITL
(docs/tutorials/fly-a-bluerov2.md).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Literal

from cavenav.motion.kinematics import turn_deg, wrap_angle
from cavenav.vehicle.frames import body_to_ned

__all__ = [
    "ControlSettings",
    "Ending",
    "Goal",
    "Measured",
    "MoveReport",
    "Settling",
    "goal_of",
    "manual_sticks",
    "off_target",
    "on_target",
    "still",
]

Ending = Literal["reached", "settled", "timeout"]  # how a move ended (`MoveReport`)
NEUTRAL_THROTTLE = 500  # MANUAL_CONTROL z: 0..1000, 500 holds the depth in ALT_HOLD
MIN_PUSH = 10  # of 1000: a smaller horizontal correction is left out, not chattered


@dataclass(frozen=True)
class ControlSettings:
    """The settings the controller reads, with no defaults of their own:
    `cavenav.vehicle.mavlink.BridgeConfig` holds them (its ``control``)."""

    stick_limit: int
    forward_mps: float
    lateral_mps: float
    cruise_mps: float
    approach_gain: float
    velocity_gain: float
    yaw_gain: float
    stick_dead_band: int
    climb_gain: float
    throttle_dead_band: int
    position_tolerance_m: float
    depth_tolerance_m: float
    yaw_tolerance_deg: float
    still_mps: float
    still_climb_mps: float
    still_dps: float


@dataclass(frozen=True)
class Measured:
    """The vehicle's state as it reports it: NED metres, radians clockwise from north,
    and their rates (m/s, rad/s)."""

    north: float
    east: float
    down: float
    yaw: float
    v_north: float = 0.0
    v_east: float = 0.0
    v_down: float = 0.0
    yaw_rate: float = 0.0

    @property
    def horizontal_speed(self) -> float:
        return math.hypot(self.v_north, self.v_east)


@dataclass(frozen=True)
class Goal:
    """Where a move should end: NED metres and the heading in radians."""

    north: float
    east: float
    down: float
    yaw: float


def goal_of(start: Goal | Measured, forward: float, right: float, down: float, turn: float) -> Goal:
    """Where an action ends from ``start``: the turn first, then the translation in the
    new heading's body frame (SPEC section 5). Every segment of the action aims at parts
    of this one goal, so a turn cut short is finished by the move after it, not lost;
    and a step that begins within the tolerances of the last step's goal is reckoned
    from that goal, so that the shortfalls the tolerances allow do not add up."""
    yaw = wrap_angle(start.yaw + turn)
    north, east = body_to_ned(forward, right, yaw)
    return Goal(start.north + north, start.east + east, start.down + down, yaw)


def off_target(goal: Goal, now: Measured) -> tuple[float, float, float]:
    """How far ``now`` is from ``goal``: horizontal metres, vertical metres, degrees."""
    horizontal = math.hypot(goal.north - now.north, goal.east - now.east)
    return horizontal, abs(goal.down - now.down), turn_deg(now.yaw, goal.yaw)


def on_target(goal: Goal, now: Measured, settings: ControlSettings) -> bool:
    """Within every tolerance of ``goal`` (not yet necessarily still)."""
    horizontal, vertical, degrees = off_target(goal, now)
    return (
        horizontal <= settings.position_tolerance_m
        and vertical <= settings.depth_tolerance_m
        and degrees <= settings.yaw_tolerance_deg
    )


def still(now: Measured, settings: ControlSettings) -> bool:
    """Slower than ``still_mps`` horizontally and ``still_climb_mps`` vertically, and
    turning slower than ``still_dps``, as reported. The vertical threshold is apart:
    ALT_HOLD's depth hold wavers at up to 0.15 m/s on the SITL while the depth stays
    within 0.1 m."""
    return (
        now.horizontal_speed <= settings.still_mps
        and abs(now.v_down) <= settings.still_climb_mps
        and abs(math.degrees(now.yaw_rate)) <= settings.still_dps
    )


def manual_sticks(goal: Goal, now: Measured, settings: ControlSettings) -> dict[str, int]:
    """MANUAL_CONTROL's x, y, z, r (ALT_HOLD) that bring ``now`` toward ``goal``.

    The wanted velocity is the error times ``approach_gain``, scaled down as a whole to at
    most ``cruise_mps``: every axis closes the same share of its error at once, so the
    vehicle flies the straight line the kinematics (and the shield) assume.
    """
    north, east = goal.north - now.north, goal.east - now.east
    cos, sin = math.cos(now.yaw), math.sin(now.yaw)
    error = (north * cos + east * sin, -north * sin + east * cos, now.down - goal.down)
    wanted = [settings.approach_gain * e for e in error]  # ahead, aside, up
    size = math.hypot(*wanted)
    if size > settings.cruise_mps:
        wanted = [w * settings.cruise_mps / size for w in wanted]
    speed_ahead = now.v_north * cos + now.v_east * sin
    speed_aside = -now.v_north * sin + now.v_east * cos
    return {
        "x": _translation(wanted[0], speed_ahead, settings.forward_mps, settings),
        "y": _translation(wanted[1], speed_aside, settings.lateral_mps, settings),
        "z": _throttle(error[2], wanted[2], settings),
        "r": _yaw(math.degrees(wrap_angle(goal.yaw - now.yaw)), settings),
    }


def _translation(wanted: float, speed: float, full_mps: float, s: ControlSettings) -> int:
    """One horizontal axis: the stick that holds the ``wanted`` speed, plus a push for
    the speed still missing (a brake where the vehicle is faster than wanted), out of
    the dead band; nothing for a push too small to matter."""
    push = (s.stick_limit - s.stick_dead_band) * wanted / full_mps
    push += s.velocity_gain * (wanted - speed)
    if abs(push) < MIN_PUSH:
        return 0
    return round(math.copysign(min(s.stick_dead_band + abs(push), s.stick_limit), push))


def _yaw(error_deg: float, s: ControlSettings) -> int:
    """The yaw stick: nothing within half the tolerance (ALT_HOLD holds the heading),
    else out of the dead band in proportion to the error."""
    if abs(error_deg) <= s.yaw_tolerance_deg / 2:
        return 0
    size = min(s.stick_dead_band + s.yaw_gain * abs(error_deg), s.stick_limit)
    return round(math.copysign(size, error_deg))  # r > 0: clockwise


def _throttle(rise_m: float, wanted_mps: float, s: ControlSettings) -> int:
    """The throttle: neutral (ALT_HOLD holds the depth) within half the depth tolerance,
    else out of the dead band by ``climb_gain`` per m/s of climb wanted (> 0: up)."""
    if abs(rise_m) <= s.depth_tolerance_m / 2:
        return NEUTRAL_THROTTLE
    size = min(s.throttle_dead_band + s.climb_gain * abs(wanted_mps), NEUTRAL_THROTTLE)
    return NEUTRAL_THROTTLE + round(math.copysign(size, rise_m))


class Settling:
    """Whether a vehicle has been `still` for ``still_for_s`` (*steady*), and whether it
    has also come no nearer its goal meanwhile (*stalled*: it has stopped trying, as a
    position controller short of its target does; a slow final approach is no stall)."""

    def __init__(self, settings: ControlSettings, still_for_s: float):
        self.settings, self.still_for_s = settings, still_for_s
        self._since: float | None = None
        self._off_then = (math.inf, math.inf, math.inf)

    def update(self, goal: Goal, now: Measured, clock: float) -> tuple[bool, bool]:
        """(steady, stalled) at the monotonic time ``clock``."""
        off = off_target(goal, now)
        if not still(now, self.settings):
            self._since = None
            return False, False
        if self._since is None:
            self._since, self._off_then = clock, off
        if clock - self._since < self.still_for_s:
            return False, False
        s = self.settings
        halves = (s.position_tolerance_m / 2, s.depth_tolerance_m / 2, s.yaw_tolerance_deg / 2)
        progress = [then - now_ for then, now_ in zip(self._off_then, off, strict=True)]
        stalled = all(gain < half for gain, half in zip(progress, halves, strict=True))
        if not stalled:  # still nearing it: judge the next window from here
            self._since, self._off_then = clock, off
        return True, stalled


@dataclass(frozen=True)
class MoveReport:
    """How one step's move went on the vehicle, for steps.jsonl's ``vehicle``.

    Attributes:
        asked: the action the pilot (or the shield) asked for.
        flown: the action flown: ``asked`` with its vertical part cut at the depth limits.
        ended: "reached" (within the tolerances and still), "settled" (still, off the
            goal: the vehicle stopped trying) or "timeout" (neither in time: a failure).
        off_m, off_deg: the settled pose's distance and heading from the flown action's goal.
        seconds: how long the move took, stillness included.
    """

    asked: str
    flown: str
    ended: Ending
    off_m: float
    off_deg: float
    seconds: float

    @property
    def depth_limited(self) -> bool:
        return self.asked != self.flown

    def to_dict(self) -> dict[str, object]:
        return {**asdict(self), "depth_limited": self.depth_limited}
