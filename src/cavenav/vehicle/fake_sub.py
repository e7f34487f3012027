"""A simulated ArduSub autopilot (a "fake sub") that speaks MAVLink over UDP.

A ground-station bridge to a BlueROV2 has to be tested in a closed loop, and neither a
vehicle nor an ArduSub SITL build is at hand in a test run. This module stands in for the
autopilot: it emulates what ArduSub documents and does (GCS_MAVLINK_Sub.cpp, failsafe.cpp,
mode.h, the parameters FS_PILOT_INPUT, FS_PILOT_TIMEOUT and SYSID_MYGCS) and nothing that is
cavenav's own. A bridge that flies this fake should fly the real vehicle, and one that leans
on a convenience ArduSub lacks should fail here rather than in the water.

What it emulates:

* HEARTBEAT at 1 Hz (MAV_TYPE_SUBMARINE, ArduSub's base_mode bits, custom_mode = mode
  number, system_status STANDBY / ACTIVE, CRITICAL while a failsafe is active);
* arming and disarming (COMMAND_LONG or COMMAND_INT MAV_CMD_COMPONENT_ARM_DISARM) and mode
  changes (SET_MODE, answered like ArduPilot with a COMMAND_ACK whose command is the message
  id 11, and MAV_CMD_DO_SET_MODE), each answered with a COMMAND_ACK;
* MANUAL_CONTROL from the ground station SYSID_MYGCS only, aimed at this system only;
* the pilot-input failsafe (neutral sticks, "Lost manual control", disarm with FS_PILOT_INPUT
  = 2), once per loss of input, in every mode, armed or not, from boot;
* GUIDED position and velocity targets (SET_POSITION_TARGET_LOCAL_NED) in ArduSub's frames
  and type_mask semantics;
* ATTITUDE and LOCAL_POSITION_NED streams, MAV_CMD_SET_MESSAGE_INTERVAL and
  MAV_CMD_REQUEST_MESSAGE for them.

What it simplifies: the vehicle is kinematic (velocities are reached at once, roll and pitch
stay zero), the water has no surface and no bottom (SURFACE mode stops at depth 0), CIRCLE
holds position instead of orbiting, AUTO is always refused (there is no mission), an RC
override never expires by itself, joystick buttons and parameters are not emulated, and
there is no ground-station heartbeat failsafe.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from pymavlink import mavutil

from cavenav.errors import ConfigError
from cavenav.kinematics import wrap_angle

__all__ = [
    "ACRO",
    "ALT_HOLD",
    "AUTO",
    "CIRCLE",
    "GUIDED",
    "MANUAL",
    "MODES",
    "NEUTRAL_STICKS",
    "POSHOLD",
    "STABILIZE",
    "SURFACE",
    "FakeSub",
    "FakeSubConfig",
    "FakeSubState",
    "GuidedCommand",
    "ModeTraits",
    "read_position_target",
    "serve",
]

MAV = mavutil.mavlink

# ArduSub's flight-mode numbers (ArduSub/mode.h), the HEARTBEAT's custom_mode.
STABILIZE = 0
ACRO = 1
ALT_HOLD = 2
AUTO = 3
GUIDED = 4
CIRCLE = 7
SURFACE = 9
POSHOLD = 16
MANUAL = 19

BOOT_MODE = MANUAL  # ArduSub starts in MANUAL
AUTOPILOT_COMPONENT = 1  # MAV_COMP_ID_AUTOPILOT1
NEUTRAL_STICKS = (0, 0, 500, 0)  # MANUAL_CONTROL x, y, z, r with no pilot input
PILOT_FAILSAFES = ("disarm", "warn", "off")  # FS_PILOT_INPUT 2, 1, 0
GUIDED_VELOCITY_TIMEOUT_S = 3.0  # ArduSub stops a velocity target not renewed within 3 s
GAIN_REDRAW_S = 1.0  # how long one draw of the thrusters' gain error lasts

# SET_POSITION_TARGET_LOCAL_NED type_mask groups as ArduSub tests them: one ignore bit of a
# group set counts as the whole group ignored (MAVLINK_SET_POS_TYPE_MASK_*_IGNORE).
POSITION_IGNORE = 0b000_000_111
VELOCITY_IGNORE = 0b000_111_000
ACCELERATION_IGNORE = 0b111_000_000
YAW_IGNORE = MAV.POSITION_TARGET_TYPEMASK_YAW_IGNORE
YAW_RATE_IGNORE = MAV.POSITION_TARGET_TYPEMASK_YAW_RATE_IGNORE
TARGET_FRAMES = (
    MAV.MAV_FRAME_LOCAL_NED,
    MAV.MAV_FRAME_LOCAL_OFFSET_NED,
    MAV.MAV_FRAME_BODY_NED,
    MAV.MAV_FRAME_BODY_OFFSET_NED,
)
BODY_FRAMES = (MAV.MAV_FRAME_BODY_NED, MAV.MAV_FRAME_BODY_OFFSET_NED)

STREAMED = (MAV.MAVLINK_MSG_ID_ATTITUDE, MAV.MAVLINK_MSG_ID_LOCAL_POSITION_NED)


@dataclass(frozen=True)
class ModeTraits:
    """How one ArduSub mode treats the position estimate, the pilot and the water current.

    Attributes:
        name: ArduSub's name of the mode.
        needs_position: ArduSub's ``requires_GPS()``: refused without a position estimate.
        pilot_translates: the forward, lateral and throttle sticks command velocities.
        holds_depth: a depth controller runs, so a vertical current does not move the vehicle.
        holds_position: a position controller runs, so no current moves the vehicle.
    """

    name: str
    needs_position: bool
    pilot_translates: bool
    holds_depth: bool
    holds_position: bool


MODES: dict[int, ModeTraits] = {
    STABILIZE: ModeTraits("STABILIZE", False, True, False, False),
    ACRO: ModeTraits("ACRO", False, True, False, False),
    ALT_HOLD: ModeTraits("ALT_HOLD", False, True, True, False),
    AUTO: ModeTraits("AUTO", True, False, True, True),
    GUIDED: ModeTraits("GUIDED", True, False, True, True),
    CIRCLE: ModeTraits("CIRCLE", True, False, True, True),
    SURFACE: ModeTraits("SURFACE", False, False, True, False),
    POSHOLD: ModeTraits("POSHOLD", True, True, True, True),
    MANUAL: ModeTraits("MANUAL", False, True, False, False),
}


@dataclass(frozen=True)
class FakeSubConfig:
    """Everything the fake sub is told before it starts; checked when made.

    Attributes:
        address: the pymavlink connection string it talks over. ``udpout`` sends to the
            ground station, which listens with ``udpin`` as a GCS behind BlueOS does.
        system_id: this vehicle's MAVLink system id (SYSID_THISMAV).
        gcs_system_id: the only ground station whose MANUAL_CONTROL counts (SYSID_MYGCS).
        max_speed_mps: forward and lateral speed at full stick.
        max_vertical_mps: vertical speed at full throttle deflection.
        max_yaw_rate_dps: yaw rate at full yaw stick.
        guided_speed_mps: the GUIDED position controller's 3-D speed limit.
        guided_yaw_rate_dps: the GUIDED heading controller's turn-rate limit.
        current_ned_mps: a water current (north, east, down) that drifts the vehicle unless a
            controller holds against it.
        noise: relative execution noise (0 for none): a gain error on stick velocities
            redrawn each second, and a miss of each GUIDED target in proportion to its offset.
        seed: seeds the noise, so that a test is reproducible in distribution.
        start_ned: the start position (north, east, down) in metres.
        start_yaw_deg: the start heading, clockwise from north.
        position_estimate: a DVL or similar is present: LOCAL_POSITION_NED is sent and the
            modes that need a position (GUIDED, POSHOLD, CIRCLE) can be entered.
        pilot_timeout_s: FS_PILOT_TIMEOUT: pilot input older than this is lost.
        pilot_failsafe: FS_PILOT_INPUT: "disarm", "warn" (neutral sticks only) or "off".
        physics_hz: how often the pose is integrated and the failsafe checked.
        telemetry_hz: the default rate of ATTITUDE and LOCAL_POSITION_NED (sent from the
            physics loop, so at most physics_hz).
    """

    address: str = "udpout:127.0.0.1:14550"
    system_id: int = 1
    gcs_system_id: int = 255
    max_speed_mps: float = 1.0
    max_vertical_mps: float = 0.5
    max_yaw_rate_dps: float = 90.0
    guided_speed_mps: float = 0.5
    guided_yaw_rate_dps: float = 45.0
    current_ned_mps: tuple[float, float, float] = (0.0, 0.0, 0.0)
    noise: float = 0.0
    seed: int = 0
    start_ned: tuple[float, float, float] = (0.0, 0.0, 5.0)
    start_yaw_deg: float = 0.0
    position_estimate: bool = True
    pilot_timeout_s: float = 3.0
    pilot_failsafe: str = "disarm"
    physics_hz: float = 50.0
    telemetry_hz: float = 10.0

    def __post_init__(self) -> None:
        if not isinstance(self.address, str) or not self.address.strip():
            raise ConfigError(
                f"address must be a pymavlink connection string, not {self.address!r}"
            )
        for name in ("system_id", "gcs_system_id"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or not 1 <= value <= 255:
                raise ConfigError(f"{name} must be a MAVLink system id 1..255, not {value!r}")
        for name in (
            "max_speed_mps",
            "max_vertical_mps",
            "max_yaw_rate_dps",
            "guided_speed_mps",
            "guided_yaw_rate_dps",
            "pilot_timeout_s",
            "physics_hz",
            "telemetry_hz",
        ):
            value = _finite(name, getattr(self, name))
            if value <= 0.0:
                raise ConfigError(f"{name} must be positive, not {value!r}")
        if _finite("noise", self.noise) < 0.0:
            raise ConfigError(f"noise must be 0 or more, not {self.noise!r}")
        _finite("start_yaw_deg", self.start_yaw_deg)
        for name in ("current_ned_mps", "start_ned"):
            object.__setattr__(self, name, _vector3(name, getattr(self, name)))
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise ConfigError(f"seed must be a non-negative integer, not {self.seed!r}")
        if self.pilot_failsafe not in PILOT_FAILSAFES:
            raise ConfigError(
                f"pilot_failsafe must be one of {', '.join(PILOT_FAILSAFES)}, "
                f"not {self.pilot_failsafe!r}"
            )


@dataclass(frozen=True)
class FakeSubState:
    """A consistent snapshot of the fake sub, for tests and a command line's status line.

    Attributes:
        armed: the motors are armed.
        mode: the ArduSub mode number; mode_name its name.
        north, east, down: the position in metres (NED, down = depth).
        yaw_deg: the heading, clockwise from north, in [-180, 180).
        sticks: the MANUAL_CONTROL x, y, z, r in effect (neutral: (0, 0, 500, 0)).
        failsafe: the pilot-input failsafe has fired and pilot input has not come back.
        manual_controls: MANUAL_CONTROL messages accepted so far.
        position_targets: SET_POSITION_TARGET_LOCAL_NED messages acted on so far.
        guided_target: the GUIDED target asked for (north, east, down, yaw_deg) while the
            vehicle is still on its way; None when there is none or it has been reached.
    """

    armed: bool
    mode: int
    mode_name: str
    north: float
    east: float
    down: float
    yaw_deg: float
    sticks: tuple[int, int, int, int]
    failsafe: bool
    manual_controls: int
    position_targets: int
    guided_target: tuple[float, float, float, float] | None


@dataclass(frozen=True)
class GuidedCommand:
    """A SET_POSITION_TARGET_LOCAL_NED as ArduSub reads it, resolved to the local NED frame.

    Exactly one of position and velocity is set.

    Attributes:
        position: the target (north, east, down) in metres.
        velocity: the target velocity (north, east, down) in m/s.
        yaw: the absolute target heading in radians (NED), None to hold the heading.
        yaw_rate: rad/s; with a yaw the turn rate, alone a continuous turn; None if ignored.
    """

    position: tuple[float, float, float] | None
    velocity: tuple[float, float, float] | None
    yaw: float | None
    yaw_rate: float | None


@dataclass(frozen=True)
class _Guidance:
    """What the GUIDED controllers are doing; the default holds the current pose.

    goal and goal_yaw are where the vehicle will really end (the target plus the execution
    noise); commanded is the target as asked for, reported until both are reached.
    """

    goal: tuple[float, float, float] | None = None
    goal_yaw: float | None = None
    turn_rate: float = 0.0
    yaw_rate: float | None = None
    velocity: tuple[float, float, float] | None = None
    velocity_until: float = 0.0
    commanded: tuple[float, float, float, float] | None = None


def _finite(name: str, value: object) -> float:
    """``value`` as a float, or a ConfigError naming the field if it is not a finite number."""
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise ConfigError(f"{name} must be a finite number, not {value!r}")
    return float(value)


def _vector3(name: str, value: object) -> tuple[float, float, float]:
    """``value`` as three finite floats (a list from a command line is fine)."""
    if not isinstance(value, tuple | list) or len(value) != 3:
        raise ConfigError(f"{name} must be three numbers (north, east, down), not {value!r}")
    north, east, down = (_finite(name, v) for v in value)
    return (north, east, down)


def wrap_degrees(angle_deg: float) -> float:
    """An angle in degrees wrapped to [-180, 180), as FakeSubState reports headings."""
    wrapped = (angle_deg + 180.0) % 360.0 - 180.0
    return wrapped - 360.0 if wrapped >= 180.0 else wrapped


def body_to_ned(forward: float, right: float, yaw: float) -> tuple[float, float]:
    """A horizontal body-frame vector as (north, east) for a heading ``yaw`` (rad, NED)."""
    cos_yaw, sin_yaw = math.cos(yaw), math.sin(yaw)
    return forward * cos_yaw - right * sin_yaw, forward * sin_yaw + right * cos_yaw


def stick_command(
    sticks: tuple[int, int, int, int], config: FakeSubConfig
) -> tuple[float, float, float, float]:
    """The body velocities the sticks ask for: forward, right, up (m/s), yaw rate (rad/s).

    MANUAL_CONTROL as ArduSub maps it: x forward, y right, r clockwise in -1000..1000, z the
    throttle in 0..1000 around 500.
    """
    x, y, z, r = sticks
    return (
        x / 1000.0 * config.max_speed_mps,
        y / 1000.0 * config.max_speed_mps,
        (z - 500) / 500.0 * config.max_vertical_mps,
        math.radians(r / 1000.0 * config.max_yaw_rate_dps),
    )


def heartbeat_flags(mode: int, armed: bool, failsafe: bool) -> tuple[int, int]:
    """HEARTBEAT (base_mode, system_status) as GCS_MAVLINK_Sub fills them in.

    base_mode always has STABILIZE, MANUAL_INPUT and CUSTOM_MODE set, GUIDED for the modes
    that fly to positions, SAFETY_ARMED when armed; system_status is CRITICAL while any
    failsafe is active, else ACTIVE when armed and STANDBY when not.
    """
    base_mode = (
        MAV.MAV_MODE_FLAG_STABILIZE_ENABLED
        | MAV.MAV_MODE_FLAG_MANUAL_INPUT_ENABLED
        | MAV.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    )
    if mode in (AUTO, GUIDED, CIRCLE, POSHOLD):
        base_mode |= MAV.MAV_MODE_FLAG_GUIDED_ENABLED
    if armed:
        base_mode |= MAV.MAV_MODE_FLAG_SAFETY_ARMED
    if failsafe:
        return base_mode, MAV.MAV_STATE_CRITICAL
    return base_mode, MAV.MAV_STATE_ACTIVE if armed else MAV.MAV_STATE_STANDBY


def step_toward(position: np.ndarray, goal: np.ndarray, max_step: float) -> tuple[np.ndarray, bool]:
    """One straight-line step of at most ``max_step`` toward ``goal``; True once there.

    The last step lands on the goal exactly, so that a reached target reads as reached.
    """
    offset = goal - position
    distance = float(np.linalg.norm(offset))
    if distance <= max_step:
        return goal.copy(), True
    return position + offset * (max_step / distance), False


def turn_toward(yaw: float, goal_yaw: float, max_turn: float) -> tuple[float, bool]:
    """One turn of at most ``max_turn`` (rad) the shortest way toward ``goal_yaw``."""
    error = wrap_angle(goal_yaw - yaw)
    if abs(error) <= max_turn:
        return wrap_angle(goal_yaw), True
    return wrap_angle(yaw + math.copysign(max_turn, error)), False


def read_position_target(
    message: Any, position: tuple[float, float, float], yaw: float
) -> GuidedCommand | None:
    """A SET_POSITION_TARGET_LOCAL_NED read as ArduSub's GUIDED mode reads it, or None if
    ArduSub would not act on it.

    Frames LOCAL_NED, LOCAL_OFFSET_NED, BODY_NED and BODY_OFFSET_NED: body frames rotate x, y
    by the current heading, every frame but LOCAL_NED adds the current position (z too), and
    the yaw is absolute except in BODY_OFFSET_NED, where it is relative to the heading. As in
    ArduSub, one ignore bit of a group ignores the group; a position target and a velocity
    target are flown, a position with a velocity (a moving target) and anything with an
    acceleration are not.

    Args:
        message: the decoded MAVLink message (its fields are read by name).
        position: the vehicle's position (north, east, down) when the message arrives.
        yaw: the vehicle's heading (rad, NED) then.
    """
    frame, mask = message.coordinate_frame, message.type_mask
    use_position = not mask & POSITION_IGNORE
    use_velocity = not mask & VELOCITY_IGNORE
    if frame not in TARGET_FRAMES or not mask & ACCELERATION_IGNORE or use_position == use_velocity:
        return None
    target_yaw = None if mask & YAW_IGNORE else float(message.yaw)
    yaw_rate = None if mask & YAW_RATE_IGNORE else float(message.yaw_rate)
    if use_position:
        vector = (float(message.x), float(message.y), float(message.z))
    else:
        vector = (float(message.vx), float(message.vy), float(message.vz))
    used = [*vector, *(v for v in (target_yaw, yaw_rate) if v is not None)]
    if not all(math.isfinite(v) for v in used):
        return None
    if target_yaw is not None:
        relative = frame == MAV.MAV_FRAME_BODY_OFFSET_NED
        target_yaw = wrap_angle(target_yaw + (yaw if relative else 0.0))
    north, east, down = vector
    if frame in BODY_FRAMES:
        north, east = body_to_ned(north, east, yaw)
    if not use_position:
        return GuidedCommand(None, (north, east, down), target_yaw, yaw_rate)
    if frame != MAV.MAV_FRAME_LOCAL_NED:
        north, east, down = north + position[0], east + position[1], down + position[2]
    return GuidedCommand((north, east, down), None, target_yaw, yaw_rate)


def _next_due(due: float, period: float, now: float) -> float:
    """The next time a periodic job is due; a late loop skips ahead instead of bursting."""
    due += period
    return due if due > now else now + period


class FakeSub:
    """The simulated autopilot: one background thread receives, integrates and sends.

    Every change of state happens under one lock (on that thread, but for
    `pause_heartbeat`), so `state` may be called from any thread and sees one instant.
    """

    def __init__(self, config: FakeSubConfig | None = None):
        self.config = config if config is not None else FakeSubConfig()
        seeds = np.random.SeedSequence(self.config.seed).spawn(2)
        # Separate streams: the gain draws depend on wall-clock time, the target misses only
        # on the targets sent, so the misses repeat exactly for the same seed and targets.
        self._gain_rng = np.random.default_rng(seeds[0])
        self._target_rng = np.random.default_rng(seeds[1])
        self._lock = threading.Lock()
        self._stopping = threading.Event()
        self._thread: threading.Thread | None = None
        self._conn: Any = None
        self._position = np.array(self.config.start_ned, dtype=float)
        self._velocity = np.zeros(3)
        self._yaw = wrap_angle(math.radians(self.config.start_yaw_deg))
        self._yaw_rate = 0.0
        self._armed = False
        self._mode = BOOT_MODE
        self._sticks = NEUTRAL_STICKS
        self._failsafe = False
        self._manual_controls = 0
        self._position_targets = 0
        self._guidance = _Guidance()
        self._gains = np.ones(4)  # forward, right, up, yaw
        self._heartbeat_paused = False
        default_interval = 1.0 / self.config.telemetry_hz
        self._intervals: dict[int, float | None] = dict.fromkeys(STREAMED, default_interval)
        self._boot = self._last_step = self._last_pilot_input = 0.0
        self._next_heartbeat = self._next_gain_draw = 0.0
        self._next_stream: dict[int, float] = dict.fromkeys(STREAMED, 0.0)
        self._crash: BaseException | None = None

    # -- life cycle ------------------------------------------------------------------------

    def start(self) -> FakeSub:
        """Open the connection and start the thread; the first HEARTBEAT goes out at once,
        so that a ground station listening with ``udpin`` learns where to answer."""
        if self._stopping.is_set():
            raise RuntimeError("a FakeSub runs once; make a new one to start again")
        if self._thread is not None:
            return self
        try:
            self._conn = mavutil.mavlink_connection(
                self.config.address,
                source_system=self.config.system_id,
                source_component=AUTOPILOT_COMPONENT,
            )
        except (OSError, ValueError) as error:
            raise ConfigError(f"cannot open {self.config.address!r}: {error}") from error
        now = time.monotonic()
        # ArduSub's pilot-input timer starts at boot: no input for FS_PILOT_TIMEOUT after
        # boot fires the failsafe (disarmed, it only warns).
        self._boot = self._last_step = self._last_pilot_input = now
        self._next_heartbeat = self._next_gain_draw = now
        self._next_stream = dict.fromkeys(STREAMED, now)
        self._thread = threading.Thread(target=self._run, name="fake-sub", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop the thread and close the socket; returns within a loop period, and may be
        called any number of times."""
        self._stopping.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        if self._conn is not None:
            self._conn.close()
            self._conn = None

    def __enter__(self) -> FakeSub:
        return self.start()

    def __exit__(self, *exc_info: object) -> None:
        self.stop()

    def state(self) -> FakeSubState:
        """A snapshot of the vehicle as it is now; raises if the thread has died, so that a
        test fails on the cause rather than on a vehicle that stopped answering."""
        if self._crash is not None:
            raise RuntimeError(f"the fake sub's thread died: {self._crash!r}") from self._crash
        with self._lock:
            north, east, down = (float(v) for v in self._position)
            return FakeSubState(
                armed=self._armed,
                mode=self._mode,
                mode_name=MODES[self._mode].name,
                north=north,
                east=east,
                down=down,
                yaw_deg=wrap_degrees(math.degrees(self._yaw)),
                sticks=self._sticks,
                failsafe=self._failsafe,
                manual_controls=self._manual_controls,
                position_targets=self._position_targets,
                guided_target=self._guidance.commanded,
            )

    def pause_heartbeat(self, paused: bool) -> None:
        """A test hook: stop (or resume) sending HEARTBEAT, to look like a stale link while
        everything else runs on."""
        with self._lock:
            self._heartbeat_paused = paused

    # -- the loop --------------------------------------------------------------------------

    def _run(self) -> None:
        """Receive whatever has arrived, step the physics when due, and wait on the socket
        until the next step, so that commands are answered without waiting for a tick."""
        try:
            self._loop()
        except BaseException as error:  # kept for state() to raise, then reported as usual
            self._crash = error
            raise

    def _loop(self) -> None:
        period = 1.0 / self.config.physics_hz
        next_step = time.monotonic()
        while not self._stopping.is_set():
            for _ in range(100):  # bounded, so that a flood of messages cannot stop the physics
                message = self._conn.recv_msg()
                if message is None:
                    break
                with self._lock:
                    self._handle(message, time.monotonic())
            now = time.monotonic()
            if now >= next_step:
                with self._lock:
                    self._tick(now)
                next_step = _next_due(next_step, period, now)
            self._conn.select(min(max(next_step - time.monotonic(), 0.0), 0.05))

    def _tick(self, now: float) -> None:
        """One physics step: noise, the pilot-input failsafe, motion, then what is due out."""
        dt = now - self._last_step
        self._last_step = now
        if self.config.noise > 0.0 and now >= self._next_gain_draw:
            self._gains = 1.0 + self.config.noise * self._gain_rng.standard_normal(4)
            self._next_gain_draw = _next_due(self._next_gain_draw, GAIN_REDRAW_S, now)
        self._check_pilot_input(now)
        if dt > 0.0:
            self._move(now, dt)
        if now >= self._next_heartbeat:
            if not self._heartbeat_paused:
                self._send_heartbeat()
            self._next_heartbeat = _next_due(self._next_heartbeat, 1.0, now)
        for message_id, interval in self._intervals.items():
            if interval is not None and now >= self._next_stream[message_id]:
                self._send(message_id, now)
                self._next_stream[message_id] = _next_due(
                    self._next_stream[message_id], interval, now
                )

    def _check_pilot_input(self, now: float) -> None:
        """ArduSub's failsafe_pilot_input_check: act once per loss of pilot input."""
        if self.config.pilot_failsafe == "off":
            self._failsafe = False
            return
        if now < self._last_pilot_input + self.config.pilot_timeout_s:
            self._failsafe = False
            return
        if self._failsafe:
            return
        self._failsafe = True
        self._statustext(MAV.MAV_SEVERITY_CRITICAL, "Lost manual control")
        self._sticks = NEUTRAL_STICKS
        if self.config.pilot_failsafe == "disarm":
            self._disarm()

    def _move(self, now: float, dt: float) -> None:
        """Integrate the pose over ``dt`` as the current mode and controllers make it move."""
        traits = MODES[self._mode]
        current = np.array(self.config.current_ned_mps)
        before, yaw_before = self._position.copy(), self._yaw
        if not self._armed:
            # Disarmed, ArduSub resets the waypoint controller every loop: a target is lost.
            self._guidance = _Guidance()
            self._position = self._position + current * dt
        else:
            command = np.array(stick_command(self._sticks, self.config)) * self._gains
            forward, right, up, yaw_rate = (float(v) for v in command)
            if traits.holds_position and not traits.pilot_translates:
                self._guide(now, dt, yaw_rate)
            else:
                if self._mode == SURFACE:
                    forward = right = 0.0
                    up = self.config.max_vertical_mps if self._position[2] > 0.0 else 0.0
                north, east = body_to_ned(forward, right, self._yaw + 0.5 * yaw_rate * dt)
                horizontal_drift = 0.0 if traits.holds_position else 1.0
                vertical_drift = 0.0 if traits.holds_depth else 1.0
                drift = current * [horizontal_drift, horizontal_drift, vertical_drift]
                self._position = self._position + (np.array([north, east, -up]) + drift) * dt
                if self._mode == SURFACE:
                    self._position[2] = max(self._position[2], 0.0)
                self._yaw = wrap_angle(self._yaw + yaw_rate * dt)
        self._velocity = (self._position - before) / dt
        self._yaw_rate = wrap_angle(self._yaw - yaw_before) / dt

    def _guide(self, now: float, dt: float, pilot_yaw_rate: float) -> None:
        """GUIDED (and the modes that hold like it): fly the target against any current."""
        guidance = self._guidance
        if guidance.velocity is not None:
            if now < guidance.velocity_until:
                self._position = self._position + np.array(guidance.velocity) * self._gains[:3] * dt
        elif guidance.goal is not None:
            max_step = self.config.guided_speed_mps * dt
            self._position, arrived = step_toward(self._position, np.array(guidance.goal), max_step)
            if arrived:
                guidance = replace(guidance, goal=None)
        if pilot_yaw_rate != 0.0:
            # The pilot's yaw stick takes the heading over (ArduSub's AUTO_YAW_HOLD).
            self._yaw = wrap_angle(self._yaw + pilot_yaw_rate * dt)
            guidance = replace(guidance, goal_yaw=None, yaw_rate=None)
        elif guidance.goal_yaw is not None:
            self._yaw, turned = turn_toward(self._yaw, guidance.goal_yaw, guidance.turn_rate * dt)
            if turned:
                guidance = replace(guidance, goal_yaw=None)
        elif guidance.yaw_rate is not None:
            self._yaw = wrap_angle(self._yaw + guidance.yaw_rate * dt)
        if guidance.goal is None and guidance.goal_yaw is None:
            guidance = replace(guidance, commanded=None)
        self._guidance = guidance

    # -- what arrives ----------------------------------------------------------------------

    def _handle(self, message: Any, now: float) -> None:
        """Dispatch one received message; anything not handled here is ignored, as ArduSub
        ignores what it does not act on."""
        kind = message.get_type()
        if kind == "MANUAL_CONTROL":
            self._on_manual_control(message, now)
        elif kind in ("COMMAND_LONG", "COMMAND_INT"):
            self._on_command(message, now)
        elif kind == "SET_MODE":
            if message.target_system in (0, self.config.system_id):
                result = self._set_mode_common(message.base_mode, message.custom_mode)
                # ArduPilot acknowledges SET_MODE with COMMAND_ACK, command = the message id.
                self._ack(MAV.MAVLINK_MSG_ID_SET_MODE, result)
        elif kind == "SET_POSITION_TARGET_LOCAL_NED":
            self._on_position_target(message, now)

    def _addressed_to_us(self, message: Any) -> bool:
        """MAVLink routing: for this system (or broadcast) and its autopilot (or all)."""
        return message.target_system in (0, self.config.system_id) and (
            message.target_component in (0, AUTOPILOT_COMPONENT)
        )

    def _on_manual_control(self, message: Any, now: float) -> None:
        """Sticks from SYSID_MYGCS aimed at this system replace those in effect and refresh
        the pilot-input timer, armed or not; ArduSub ignores everyone else's."""
        if message.get_srcSystem() != self.config.gcs_system_id:
            return
        if message.target != self.config.system_id:
            return
        self._sticks = (
            min(max(int(message.x), -1000), 1000),
            min(max(int(message.y), -1000), 1000),
            min(max(int(message.z), 0), 1000),
            min(max(int(message.r), -1000), 1000),
        )
        self._last_pilot_input = now
        self._manual_controls += 1

    def _on_command(self, message: Any, now: float) -> None:
        """COMMAND_LONG / COMMAND_INT (the same params 1 and 2): act, then answer with a
        COMMAND_ACK; commands this fake does not know are UNSUPPORTED."""
        if not self._addressed_to_us(message):
            return
        command, first, second = message.command, message.param1, message.param2
        if command == MAV.MAV_CMD_COMPONENT_ARM_DISARM:
            result = self._arm_disarm(first)
        elif command == MAV.MAV_CMD_DO_SET_MODE:
            result = self._set_mode_common(int(first), int(second))
        elif command == MAV.MAV_CMD_SET_MESSAGE_INTERVAL:
            result = self._set_interval(int(first), second, now)
        elif command == MAV.MAV_CMD_REQUEST_MESSAGE:
            result = self._request_message(int(first), now)
        else:
            result = MAV.MAV_RESULT_UNSUPPORTED
        self._ack(command, result)

    def _arm_disarm(self, arm: float) -> int:
        """GCS_MAVLINK's arm/disarm handling: 1 arms, 0 disarms, either when already done is
        accepted, anything else is unsupported. The one arming check ArduSub would fail here,
        a mode that needs a position without one, cannot arise: such a mode is never entered
        without a position estimate."""
        if arm == 1.0:
            self._armed = True
            return MAV.MAV_RESULT_ACCEPTED
        if arm == 0.0:
            self._disarm()
            return MAV.MAV_RESULT_ACCEPTED
        return MAV.MAV_RESULT_UNSUPPORTED

    def _disarm(self) -> None:
        self._armed = False
        self._guidance = _Guidance()

    def _set_mode_common(self, base_mode: int, custom_mode: int) -> int:
        """ArduPilot's _set_mode_common: only custom modes are understood."""
        if not base_mode & MAV.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            return MAV.MAV_RESULT_DENIED
        return MAV.MAV_RESULT_ACCEPTED if self._set_mode(custom_mode) else MAV.MAV_RESULT_FAILED

    def _set_mode(self, number: int) -> bool:
        """Sub::set_mode: unknown modes and modes that need a missing position are refused
        with a warning; a new mode starts by holding the current pose."""
        if number == self._mode:
            return True
        traits = MODES.get(number)
        if traits is None:
            self._statustext(MAV.MAV_SEVERITY_WARNING, f"No such mode {number}")
            return False
        if traits.needs_position and not self.config.position_estimate:
            self._statustext(
                MAV.MAV_SEVERITY_WARNING, f"Mode change failed: {traits.name} requires position"
            )
            return False
        if number == AUTO:  # AUTO needs a mission of two commands or more; there is none
            self._statustext(MAV.MAV_SEVERITY_WARNING, "Flight mode change failed")
            return False
        self._mode = number
        self._guidance = _Guidance()
        return True

    def _set_interval(self, message_id: int, interval_us: float, now: float) -> int:
        """MAV_CMD_SET_MESSAGE_INTERVAL for the streamed messages: -1 stops one, 0 restores
        the default rate, anything else is the interval in microseconds."""
        if message_id not in self._intervals:
            return MAV.MAV_RESULT_FAILED
        if interval_us < 0.0:
            self._intervals[message_id] = None
        elif interval_us == 0.0:
            self._intervals[message_id] = 1.0 / self.config.telemetry_hz
        else:
            self._intervals[message_id] = interval_us / 1e6
        self._next_stream[message_id] = now
        return MAV.MAV_RESULT_ACCEPTED

    def _request_message(self, message_id: int, now: float) -> int:
        """MAV_CMD_REQUEST_MESSAGE: send one HEARTBEAT, ATTITUDE or LOCAL_POSITION_NED."""
        if message_id == MAV.MAVLINK_MSG_ID_HEARTBEAT:
            self._send_heartbeat()
            return MAV.MAV_RESULT_ACCEPTED
        if message_id in STREAMED and self._send(message_id, now):
            return MAV.MAV_RESULT_ACCEPTED
        return MAV.MAV_RESULT_FAILED

    def _on_position_target(self, message: Any, now: float) -> None:
        """SET_POSITION_TARGET_LOCAL_NED, acted on in GUIDED only (as in ArduSub)."""
        if not self._addressed_to_us(message) or self._mode != GUIDED:
            return
        position = (float(self._position[0]), float(self._position[1]), float(self._position[2]))
        command = read_position_target(message, position, self._yaw)
        if command is None:
            return
        self._position_targets += 1
        self._guidance = self._guidance_for(command, now)

    def _guidance_for(self, command: GuidedCommand, now: float) -> _Guidance:
        """The controllers' new goal: the target, missed by the execution noise in
        proportion to how far (and how much of a turn) away it is."""
        max_turn_rate = math.radians(self.config.guided_yaw_rate_dps)
        turn_rate = max_turn_rate
        continuous_rate = None
        if command.yaw_rate is not None and command.yaw is not None and command.yaw_rate != 0.0:
            turn_rate = min(abs(command.yaw_rate), max_turn_rate)
        if command.yaw_rate is not None and command.yaw is None:
            continuous_rate = min(max(command.yaw_rate, -max_turn_rate), max_turn_rate)
        noise = self.config.noise
        goal_yaw = command.yaw
        if goal_yaw is not None and noise > 0.0:
            turn = abs(wrap_angle(goal_yaw - self._yaw))
            goal_yaw = wrap_angle(goal_yaw + noise * turn * self._target_rng.standard_normal())
        if command.velocity is not None:
            velocity = np.array(command.velocity)
            speed = float(np.linalg.norm(velocity))
            if speed > self.config.guided_speed_mps:
                velocity *= self.config.guided_speed_mps / speed
            return _Guidance(
                goal_yaw=goal_yaw,
                turn_rate=turn_rate,
                yaw_rate=continuous_rate,
                velocity=(float(velocity[0]), float(velocity[1]), float(velocity[2])),
                velocity_until=now + GUIDED_VELOCITY_TIMEOUT_S,
            )
        goal = np.array(command.position, dtype=float)
        if noise > 0.0:
            offset = float(np.linalg.norm(goal - self._position))
            goal = goal + noise * offset * self._target_rng.standard_normal(3)
        asked_yaw = command.yaw if command.yaw is not None else self._yaw
        return _Guidance(
            goal=(float(goal[0]), float(goal[1]), float(goal[2])),
            goal_yaw=goal_yaw,
            turn_rate=turn_rate,
            yaw_rate=continuous_rate,
            commanded=(*command.position, wrap_degrees(math.degrees(asked_yaw))),
        )

    # -- what goes out ---------------------------------------------------------------------

    def _ack(self, command: int, result: int) -> None:
        """COMMAND_ACK; under MAVLink 1 framing it has no room to name its addressee."""
        self._conn.mav.command_ack_send(command, result)

    def _statustext(self, severity: int, text: str) -> None:
        self._conn.mav.statustext_send(severity, text.encode("ascii")[:50])

    def _send_heartbeat(self) -> None:
        base_mode, system_status = heartbeat_flags(self._mode, self._armed, self._failsafe)
        self._conn.mav.heartbeat_send(
            MAV.MAV_TYPE_SUBMARINE,
            MAV.MAV_AUTOPILOT_ARDUPILOTMEGA,
            base_mode,
            self._mode,
            system_status,
        )

    def _send(self, message_id: int, now: float) -> bool:
        """Send one ATTITUDE or LOCAL_POSITION_NED; False if there is nothing to send (no
        position estimate, no LOCAL_POSITION_NED)."""
        boot_ms = int((now - self._boot) * 1000.0) & 0xFFFFFFFF
        if message_id == MAV.MAVLINK_MSG_ID_ATTITUDE:
            self._conn.mav.attitude_send(boot_ms, 0.0, 0.0, self._yaw, 0.0, 0.0, self._yaw_rate)
            return True
        if not self.config.position_estimate:
            return False
        north, east, down = (float(v) for v in self._position)
        v_north, v_east, v_down = (float(v) for v in self._velocity)
        self._conn.mav.local_position_ned_send(boot_ms, north, east, down, v_north, v_east, v_down)
        return True


def serve(
    config: FakeSubConfig,
    stop: threading.Event | None = None,
    on_state: Callable[[FakeSubState], None] | None = None,
    every_s: float = 1.0,
) -> None:
    """Run a fake sub until ``stop`` is set (or KeyboardInterrupt), calling ``on_state``
    every ``every_s`` seconds (a command line's status line)."""
    if _finite("every_s", every_s) <= 0.0:
        raise ConfigError(f"every_s must be positive, not {every_s!r}")
    stop = stop if stop is not None else threading.Event()
    with FakeSub(config) as sub:
        try:
            while not stop.wait(every_s):
                if on_state is not None:
                    on_state(sub.state())
        except KeyboardInterrupt:
            pass
