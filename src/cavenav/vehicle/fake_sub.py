"""A simulated ArduSub autopilot (a "fake sub") that speaks MAVLink over UDP.

It stands in for the vehicle when the bridge (`cavenav.vehicle.mavlink`) is tested or tried
with ``cavenav fake-sub``, and emulates only what ArduSub documents and does
(GCS_MAVLINK_Sub.cpp, failsafe.cpp, mode.h; the parameters SYSID_MYGCS, FS_PILOT_INPUT and
FS_PILOT_TIMEOUT), so that a bridge that flies this fake should fly the real vehicle:

* HEARTBEAT at 1 Hz (MAV_TYPE_SUBMARINE, ArduSub's base_mode bits, custom_mode = mode
  number, system_status STANDBY / ACTIVE, CRITICAL while a failsafe is active);
* COMMAND_LONG MAV_CMD_COMPONENT_ARM_DISARM, MAV_CMD_DO_SET_MODE and
  MAV_CMD_SET_MESSAGE_INTERVAL (for the streamed messages below), and the SET_MODE
  message, each answered with a COMMAND_ACK; other commands are UNSUPPORTED;
* the modes MANUAL (at boot), STABILIZE, ALT_HOLD and GUIDED; other mode numbers are
  refused with "No such mode", GUIDED without a position estimate too;
* MANUAL_CONTROL from the ground station SYSID_MYGCS only, aimed at this system only;
* the pilot-input failsafe (neutral sticks, "Lost manual control", disarm with FS_PILOT_INPUT
  = 2), once per loss of input, in every mode, armed or not, from boot;
* GUIDED position targets (SET_POSITION_TARGET_LOCAL_NED with velocity and acceleration
  ignored) in MAV_FRAME_LOCAL_NED, LOCAL_OFFSET_NED and BODY_OFFSET_NED, with a yaw or
  holding the heading;
* ATTITUDE, VFR_HUD (the depth as a negative altitude and the heading, as ArduSub fills
  it in with an EKF origin set), SCALED_PRESSURE2 (a Bar30 in fresh water under a
  standard atmosphere) and LOCAL_POSITION_NED streams; without a position estimate, no
  LOCAL_POSITION_NED, as ArduSub sends none when its EKF has no horizontal position.

* the motion of ArduSub's SITL, as measured against it: inertia and drag (a push coasts on
  after the sticks go neutral; nothing brakes it in ALT_HOLD), the yaw rate and its lag,
  the stick and throttle dead bands, buoyancy (disarmed it rises to float at the surface)
  and a position estimate that comes late.

What it simplifies: roll and pitch stay zero, the water has a surface but no bottom, GUIDED
flies straight at its speed limit (slowing in its last metre) instead of ArduSub's
S-curves, GUIDED velocity targets and yaw rates are ignored, and buttons, parameters and
the ground-station heartbeat failsafe are not emulated.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator
from pymavlink import mavutil

from cavenav.core.errors import ConfigError, VehicleError, invalid_field
from cavenav.motion.kinematics import wrap_angle
from cavenav.vehicle.frames import body_to_ned
from cavenav.vehicle.mavlink import check_address, check_device

__all__ = [
    "ALT_HOLD",
    "GUIDED",
    "MANUAL",
    "MODE_NAMES",
    "NEUTRAL_STICKS",
    "STABILIZE",
    "FakeSub",
    "FakeSubConfig",
    "FakeSubState",
    "serve",
]

MAV = mavutil.mavlink

# ArduSub's flight-mode numbers (ArduSub/mode.h), the HEARTBEAT's custom_mode.
STABILIZE, ALT_HOLD, GUIDED, MANUAL = 0, 2, 4, 19
MODE_NAMES = {STABILIZE: "STABILIZE", ALT_HOLD: "ALT_HOLD", GUIDED: "GUIDED", MANUAL: "MANUAL"}

AUTOPILOT_COMPONENT = 1  # MAV_COMP_ID_AUTOPILOT1
NEUTRAL_STICKS = (0, 0, 500, 0)  # MANUAL_CONTROL x, y, z, r with no pilot input
GAIN_REDRAW_S = 1.0  # how long one draw of the thrusters' gain error lasts
ARRIVED_M = 1e-3  # GUIDED: this near the goal is on it
STREAMED = (
    MAV.MAVLINK_MSG_ID_ATTITUDE,
    MAV.MAVLINK_MSG_ID_VFR_HUD,
    MAV.MAVLINK_MSG_ID_SCALED_PRESSURE2,
    MAV.MAVLINK_MSG_ID_LOCAL_POSITION_NED,
)
SURFACE_HPA, FRESH_WATER_HPA_PER_M = 1013.25, 1000.0 * 9.80665 / 100.0
TARGET_FRAMES = (
    MAV.MAV_FRAME_LOCAL_NED,
    MAV.MAV_FRAME_LOCAL_OFFSET_NED,
    MAV.MAV_FRAME_BODY_OFFSET_NED,
)
# SET_POSITION_TARGET_LOCAL_NED type_mask groups as ArduSub tests them: one ignore bit of a
# group set counts as the whole group ignored.
POSITION_IGNORE, VELOCITY_IGNORE, ACCELERATION_IGNORE = 0b111, 0b111_000, 0b111_000_000


class FakeSubConfig(BaseModel):
    """Everything the fake sub is told before it starts; a bad value is a ConfigError.

    Attributes:
        address: the pymavlink connection string it talks over. ``udpout`` sends to the
            ground station, which listens with ``udpin`` as a GCS behind BlueOS does.
        system_id: this vehicle's MAVLink system id (SYSID_THISMAV).
        gcs_system_id: the only ground station whose MANUAL_CONTROL counts (SYSID_MYGCS).
        max_speed_mps, max_vertical_mps, max_yaw_rate_dps: the forward and lateral speed,
            the climb rate and the yaw rate the full stick holds; a stick asks for its
            share beyond the dead band.
        stick_dead_band: x, y and r sticks this near 0 ask for nothing (RCn_DZ through
            JS_GAIN); throttle_dead_band the same around 500 (THR_DZ), where ALT_HOLD
            holds the depth.
        inertia: False reaches the velocities the sticks ask for at once, and stops at
            once when they are let go (a kinematic vehicle, for tests of the messages).
        drag_per_m, drag_per_s: the water's drag on the horizontal motion, quadratic
            (per metre) and linear (per second): what the vehicle coasts on with.
        yaw_lag_s, climb_lag_s: how quickly the yaw rate and climb rate follow the sticks.
        buoyant_rise_mps: how fast the vehicle rises where nothing holds its depth
            (disarmed, or in MANUAL and STABILIZE); float_depth_m: where it floats.
        position_after_s: LOCAL_POSITION_NED only this long after the start (the SITL's
            EKF needs 20-45 s for an origin); GUIDED is refused until then.
        guided_after_s: GUIDED refused until this long after the start too: ArduSub's
            EKF reports a position some seconds before it trusts it for GUIDED.
        guided_speed_mps, guided_yaw_rate_dps: GUIDED's speed and turn-rate limits.
        guided_delay_s: how long GUIDED's planner takes to set off after a target.
        guided_approach_per_s: GUIDED slows to this speed per metre (and turn rate per
            radian) still to go.
        depth_hold_per_s: ALT_HOLD's climb rate per metre off the depth it holds.
        current_ned_mps: a water current (north, east, down) that drifts the vehicle unless a
            controller holds against it (ALT_HOLD the depth, GUIDED everything).
        noise: relative execution noise (0 for none): a gain error on stick velocities
            redrawn each second, and a miss of each GUIDED target in proportion to its offset.
        seed: seeds the noise.
        start_ned, start_yaw_deg: the start position (metres) and heading (clockwise from
            north).
        position_estimate: a DVL or similar is present: LOCAL_POSITION_NED is sent and GUIDED
            can be entered.
        pilot_timeout_s: FS_PILOT_TIMEOUT: pilot input older than this is lost.
        pilot_failsafe: FS_PILOT_INPUT: "disarm", "warn" (neutral sticks only) or "off".
        physics_hz: how often the pose is integrated and the failsafe checked.
        telemetry_hz: the default rate of ATTITUDE and LOCAL_POSITION_NED (at most
            physics_hz).
    """

    model_config = ConfigDict(
        frozen=True, extra="forbid", allow_inf_nan=False, str_strip_whitespace=True
    )

    address: str = Field("udpout:127.0.0.1:14550", min_length=1)
    system_id: int = Field(1, ge=1, le=255)
    gcs_system_id: int = Field(255, ge=1, le=255)
    # What ArduSub 4.5.7's SITL does with the BlueROV2 frame at JS_GAIN 0.5 (measured with
    # sticks held and let go; docs/tutorials/fly-a-bluerov2.md): stick 400 holds 0.386 m/s
    # and turns 24.5 deg/s, nothing within 100 of 0 or a throttle within 125 of 500 moves
    # it, and let go it coasts (0.37 m/s to 0.05 in 2.5 s) and turns on about 8 deg.
    max_speed_mps: float = Field(1.16, gt=0)
    max_vertical_mps: float = Field(1.0, gt=0)
    max_yaw_rate_dps: float = Field(73.5, gt=0)
    stick_dead_band: int = Field(100, ge=0, le=999)
    throttle_dead_band: int = Field(125, ge=0, le=499)
    inertia: bool = True
    drag_per_m: float = Field(6.0, ge=0)
    drag_per_s: float = Field(0.43, ge=0)
    yaw_lag_s: float = Field(0.25, ge=0)
    climb_lag_s: float = Field(0.3, ge=0)
    buoyant_rise_mps: float = Field(0.04, ge=0)
    float_depth_m: float = Field(0.17, ge=0)
    position_after_s: float = Field(0.0, ge=0)
    guided_after_s: float = Field(0.0, ge=0)
    guided_speed_mps: float = Field(0.5, gt=0)
    guided_yaw_rate_dps: float = Field(45.0, gt=0)
    guided_delay_s: float = Field(0.7, ge=0)
    guided_approach_per_s: float = Field(1.0, gt=0)
    depth_hold_per_s: float = Field(2.0, gt=0)
    current_ned_mps: tuple[float, float, float] = (0.0, 0.0, 0.0)
    noise: float = Field(0.0, ge=0)
    seed: int = Field(0, ge=0)
    start_ned: tuple[float, float, float] = (0.0, 0.0, 30.0)  # room below the 0.3 m limit
    start_yaw_deg: float = 0.0
    position_estimate: bool = True
    pilot_timeout_s: float = Field(3.0, gt=0)
    pilot_failsafe: Literal["disarm", "warn", "off"] = "disarm"
    physics_hz: float = Field(50.0, gt=0)
    telemetry_hz: float = Field(10.0, gt=0)

    def __init__(self, **values: Any) -> None:
        try:
            super().__init__(**values)
        except ValidationError as error:
            raise invalid_field(error, "fake sub settings") from None

    @field_validator("address")
    @classmethod
    def _one_link_address(cls, address: str) -> str:
        # the bridge's forms (pymavlink would guess a serial port); the device is looked
        # for when the fake sub starts, so that settings load on any machine
        return check_address(address)


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


def _beyond(stick: float, dead_band: float, full: float) -> float:
    """The share of the full stick a deflection asks for beyond its dead band, signed."""
    return math.copysign(max(abs(stick) - dead_band, 0.0) / (full - dead_band), stick)


def _lagged(dt: float, lag_s: float) -> float:
    """How much of the way to its target a first-order lag of ``lag_s`` goes in ``dt``."""
    return 1.0 if lag_s <= 0.0 else 1.0 - math.exp(-dt / lag_s)


def _next_due(due: float, period: float, now: float) -> float:
    """The next time a periodic job is due; a late loop skips ahead instead of bursting."""
    due += period
    return due if due > now else now + period


class FakeSub:
    """The simulated autopilot: one background thread receives, integrates and sends.

    Every change of state happens under one lock, so `state` may be called from any thread
    and sees one instant.
    """

    def __init__(self, config: FakeSubConfig | None = None):
        self.config = config if config is not None else FakeSubConfig()
        gain_seed, target_seed = np.random.SeedSequence(self.config.seed).spawn(2)
        # Separate streams: the gain draws depend on wall-clock time, the target misses only
        # on the targets sent, so the misses repeat exactly for the same seed and targets.
        self._gain_rng = np.random.default_rng(gain_seed)
        self._target_rng = np.random.default_rng(target_seed)
        self._lock = threading.Lock()
        self._stopping = threading.Event()
        self._thread: threading.Thread | None = None
        self._conn: Any = None
        self._crash: BaseException | None = None
        self._position = np.array(self.config.start_ned, dtype=float)
        self._velocity = np.zeros(3)  # as reported: the position's rate of change
        self._water_velocity = np.zeros(3)  # through the water, NED
        self._turn_rate = 0.0  # the yaw rate the sticks have built up, rad/s
        self._held_depth: float | None = None  # ALT_HOLD's depth, inside the dead band
        self._goal_since = 0.0  # GUIDED: when the target came
        self._yaw = wrap_angle(math.radians(self.config.start_yaw_deg))
        self._yaw_rate = 0.0
        self._armed = False
        self._mode = MANUAL  # ArduSub boots in MANUAL
        self._sticks = NEUTRAL_STICKS
        self._failsafe = False
        self._goal: np.ndarray | None = None  # GUIDED: where the vehicle will end
        self._goal_yaw: float | None = None
        self._gains = np.ones(4)  # forward, right, up, yaw
        self._heartbeat_paused = False
        self._intervals: dict[int, float | None] = dict.fromkeys(
            STREAMED, 1.0 / self.config.telemetry_hz
        )
        self._boot = self._last_step = self._last_pilot_input = 0.0
        self._next_heartbeat = self._next_gain_draw = 0.0
        self._next_stream = dict.fromkeys(STREAMED, 0.0)

    # -- life cycle ------------------------------------------------------------------------

    def start(self) -> FakeSub:
        """Open the connection and start the thread; the first HEARTBEAT goes out at once,
        so that a ground station listening with ``udpin`` learns where to answer."""
        if self._stopping.is_set():
            raise RuntimeError("a FakeSub runs once; make a new one to start again")
        if self._thread is not None:
            return self
        try:
            check_device(self.config.address)  # a serial device named by the settings
        except VehicleError as missing:  # the fake sub's own settings: bad input
            raise ConfigError(str(missing)) from None
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
        """Stop the thread and close the socket; may be called any number of times."""
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
                mode_name=MODE_NAMES[self._mode],
                north=north,
                east=east,
                down=down,
                yaw_deg=math.degrees(self._yaw),
                sticks=self._sticks,
                failsafe=self._failsafe,
            )

    def pause_heartbeat(self, paused: bool) -> None:
        """A test hook: stop (or resume) sending HEARTBEAT, to look like a stale link while
        everything else runs on."""
        with self._lock:
            self._heartbeat_paused = paused

    # -- the loop --------------------------------------------------------------------------

    def _run(self) -> None:
        try:
            self._loop()
        except BaseException as error:  # kept for state() to raise, then reported as usual
            self._crash = error
            raise

    def _loop(self) -> None:
        """Receive whatever has arrived, step the physics when due, and wait on the socket
        until the next step, so that commands are answered without waiting for a tick."""
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
            self._move(dt, now)
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
        if self.config.pilot_failsafe == "off" or (
            now < self._last_pilot_input + self.config.pilot_timeout_s
        ):
            self._failsafe = False
            return
        if self._failsafe:
            return
        self._failsafe = True
        self._statustext(MAV.MAV_SEVERITY_CRITICAL, "Lost manual control")
        self._sticks = NEUTRAL_STICKS
        if self.config.pilot_failsafe == "disarm":
            self._disarm()

    def _move(self, dt: float, now: float) -> None:
        """Integrate the pose over ``dt``: the sticks (MANUAL_CONTROL x forward, y right, r
        clockwise in -1000..1000, z the throttle in 0..1000 around 500) drive the vehicle
        except in GUIDED, where its planner does; the current carries it, except along
        what a controller holds (ALT_HOLD the depth, GUIDED everything)."""
        before, yaw_before = self._position.copy(), self._yaw
        current = np.array(self.config.current_ned_mps)
        if self._armed and self._mode == GUIDED:
            self._guide(dt, now)
            current[:] = 0.0
        else:
            self._drive(dt)
            if self._armed and self._mode == ALT_HOLD:
                current[2] = 0.0
        self._position = self._position + (self._water_velocity + current) * dt
        if self._position[2] < self.config.float_depth_m:  # it floats: no higher
            self._position[2] = self.config.float_depth_m
            self._water_velocity[2] = max(self._water_velocity[2], 0.0)
        self._velocity = (self._position - before) / dt
        self._yaw_rate = wrap_angle(self._yaw - yaw_before) / dt

    def _drive(self, dt: float) -> None:
        """The sticks' thrust against the water's drag, the yaw rate they ask for, and the
        depth: held by ALT_HOLD inside the throttle's dead band, else climbing as asked,
        with buoyancy where nothing holds it."""
        c = self.config
        x, y, z, r = self._sticks if self._armed else NEUTRAL_STICKS
        gains = self._gains  # forward, right, up, yaw
        ahead = gains[0] * c.max_speed_mps * _beyond(x, c.stick_dead_band, 1000)
        aside = gains[1] * c.max_speed_mps * _beyond(y, c.stick_dead_band, 1000)
        wanted = np.array(body_to_ned(ahead, aside, self._yaw))
        turn = gains[3] * math.radians(c.max_yaw_rate_dps) * _beyond(r, c.stick_dead_band, 1000)
        climb = self._climb(z - 500, gains[2])
        if not c.inertia:
            self._water_velocity[:] = (*wanted, -climb)
            self._yaw = wrap_angle(self._yaw + turn * dt)
            return
        moving = self._water_velocity[:2]
        # The thrust that would hold the wanted speed; the drag taken implicitly, stable
        # at any step.
        thrust = wanted * (c.drag_per_m * float(np.linalg.norm(wanted)) + c.drag_per_s)
        resistance = c.drag_per_m * float(np.linalg.norm(moving)) + c.drag_per_s
        self._water_velocity[:2] = (moving + thrust * dt) / (1.0 + resistance * dt)
        self._turn_rate += (turn - self._turn_rate) * _lagged(dt, c.yaw_lag_s)
        self._yaw = wrap_angle(self._yaw + self._turn_rate * dt)
        self._water_velocity[2] += (-climb - self._water_velocity[2]) * _lagged(dt, c.climb_lag_s)

    def _climb(self, throttle: int, gain: float) -> float:
        """The climb rate (m/s up) the throttle asks for, or ALT_HOLD's hold of the depth
        where it entered the dead band; buoyancy where no controller holds the depth."""
        c = self.config
        if not self._armed or self._mode != ALT_HOLD:
            asked = c.max_vertical_mps * throttle / 500 if self._armed else 0.0
            self._held_depth = None
            return asked + c.buoyant_rise_mps
        asked = _beyond(throttle, c.throttle_dead_band, 500)
        if asked != 0.0:
            self._held_depth = None
            return gain * c.max_vertical_mps * asked
        if self._held_depth is None:
            self._held_depth = float(self._position[2])
        error = float(self._position[2]) - self._held_depth
        return max(-c.max_vertical_mps, min(c.max_vertical_mps, c.depth_hold_per_s * error))

    def _guide(self, dt: float, now: float) -> None:
        """GUIDED: after the planner's delay, fly straight to the goal at the speed limit,
        slowing in the last metre, and turn the shortest way to the heading, slowing in the
        last degrees; hold against any current."""
        c = self.config
        self._water_velocity[:] = 0.0
        if self._goal is not None and now >= self._goal_since + c.guided_delay_s:
            offset = self._goal - self._position
            distance = float(np.linalg.norm(offset))
            speed = min(c.guided_speed_mps, c.guided_approach_per_s * distance)
            if distance <= ARRIVED_M:  # on it, exactly, so that it reads as reached
                self._water_velocity[:] = offset / dt
            else:
                self._water_velocity[:] = offset * min(speed / distance, 1.0 / dt)
        pilot_yaw = _beyond(self._sticks[3], c.stick_dead_band, 1000)
        if pilot_yaw != 0.0:  # the pilot's yaw stick takes the heading over (AUTO_YAW_HOLD)
            self._yaw = wrap_angle(self._yaw + math.radians(c.max_yaw_rate_dps) * pilot_yaw * dt)
            self._goal_yaw = None
        elif self._goal_yaw is not None and now >= self._goal_since + c.guided_delay_s:
            error = wrap_angle(self._goal_yaw - self._yaw)
            rate = min(math.radians(c.guided_yaw_rate_dps), c.guided_approach_per_s * abs(error))
            self._yaw = wrap_angle(self._yaw + math.copysign(min(rate * dt, abs(error)), error))

    # -- what arrives ----------------------------------------------------------------------

    def _handle(self, message: Any, now: float) -> None:
        """Dispatch one received message; anything else is ignored, as ArduSub ignores what
        it does not act on."""
        kind = message.get_type()
        if kind == "MANUAL_CONTROL":
            self._on_manual_control(message, now)
        elif kind == "COMMAND_LONG" and self._addressed_to_us(message):
            self._on_command(message, now)
        elif kind == "SET_MODE" and message.target_system in (0, self.config.system_id):
            result = self._set_mode_common(message.base_mode, message.custom_mode)
            # ArduPilot acknowledges SET_MODE with COMMAND_ACK, command = the message id.
            self._ack(MAV.MAVLINK_MSG_ID_SET_MODE, result)
        elif kind == "SET_POSITION_TARGET_LOCAL_NED" and self._addressed_to_us(message):
            self._on_position_target(message)

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

    def _on_command(self, message: Any, now: float) -> None:
        """COMMAND_LONG: act, then answer with a COMMAND_ACK."""
        command, first, second = message.command, message.param1, message.param2
        if command == MAV.MAV_CMD_COMPONENT_ARM_DISARM:
            result = self._arm_disarm(first)
        elif command == MAV.MAV_CMD_DO_SET_MODE:
            result = self._set_mode_common(int(first), int(second))
        elif command == MAV.MAV_CMD_SET_MESSAGE_INTERVAL:
            result = self._set_interval(int(first), second, now)
        else:
            result = MAV.MAV_RESULT_UNSUPPORTED
        self._ack(command, result)

    def _arm_disarm(self, arm: float) -> int:
        """GCS_MAVLINK's arm/disarm handling: 1 arms, 0 disarms, either when already done is
        accepted, anything else is unsupported. (The one arming check ArduSub would fail
        here, GUIDED without a position, cannot arise: GUIDED is then never entered.)"""
        if arm == 1.0:
            self._armed = True
            return MAV.MAV_RESULT_ACCEPTED
        if arm == 0.0:
            self._disarm()
            return MAV.MAV_RESULT_ACCEPTED
        return MAV.MAV_RESULT_UNSUPPORTED

    def _disarm(self) -> None:
        """Disarmed, ArduSub resets the waypoint controller every loop: a target is lost."""
        self._armed = False
        self._goal = self._goal_yaw = None

    def _set_mode_common(self, base_mode: int, number: int) -> int:
        """ArduPilot's _set_mode_common and Sub::set_mode: only custom modes are understood;
        unknown modes, and GUIDED without a position, are refused with a warning; a new mode
        starts by holding the current pose."""
        if not base_mode & MAV.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            return MAV.MAV_RESULT_DENIED
        if number == self._mode:
            return MAV.MAV_RESULT_ACCEPTED
        if number not in MODE_NAMES:
            self._statustext(MAV.MAV_SEVERITY_WARNING, f"No such mode {number}")
            return MAV.MAV_RESULT_FAILED
        now = time.monotonic()
        if number == GUIDED and not (
            self._has_position(now) and now >= self._boot + self.config.guided_after_s
        ):
            self._statustext(
                MAV.MAV_SEVERITY_WARNING, "Mode change failed: GUIDED requires position"
            )
            return MAV.MAV_RESULT_FAILED
        self._mode = number
        self._goal = self._goal_yaw = None
        return MAV.MAV_RESULT_ACCEPTED

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

    def _on_position_target(self, message: Any) -> None:
        """SET_POSITION_TARGET_LOCAL_NED in GUIDED, as ArduSub reads it: BODY_OFFSET_NED
        rotates x, y by the heading, the offset frames add the current position (z too), and
        the yaw is absolute except in BODY_OFFSET_NED. Disarmed, ArduSub resets its waypoint
        controller every loop, so a target sent then is lost. The goal misses the target by
        the execution noise in proportion to the offset (and the turn)."""
        frame, mask = message.coordinate_frame, message.type_mask
        if (
            self._mode != GUIDED
            or not self._armed
            or frame not in TARGET_FRAMES
            or mask & POSITION_IGNORE
            or not mask & VELOCITY_IGNORE
            or not mask & ACCELERATION_IGNORE
        ):
            return
        target = np.array([message.x, message.y, message.z], dtype=float)
        yaw = None if mask & MAV.POSITION_TARGET_TYPEMASK_YAW_IGNORE else float(message.yaw)
        if not np.isfinite(target).all() or (yaw is not None and not math.isfinite(yaw)):
            return
        if frame == MAV.MAV_FRAME_BODY_OFFSET_NED:
            target[:2] = body_to_ned(target[0], target[1], self._yaw)
            yaw = None if yaw is None else yaw + self._yaw
        if frame != MAV.MAV_FRAME_LOCAL_NED:
            target += self._position
        noise = self.config.noise
        offset = float(np.linalg.norm(target - self._position))
        self._goal = target + noise * offset * self._target_rng.standard_normal(3)
        if yaw is not None:
            turn = abs(wrap_angle(yaw - self._yaw))
            yaw = wrap_angle(yaw + noise * turn * self._target_rng.standard_normal())
        self._goal_yaw = yaw
        self._goal_since = time.monotonic()

    # -- what goes out ---------------------------------------------------------------------

    def _ack(self, command: int, result: int) -> None:
        self._conn.mav.command_ack_send(command, result)

    def _statustext(self, severity: int, text: str) -> None:
        self._conn.mav.statustext_send(severity, text.encode("ascii")[:50])

    def _send_heartbeat(self) -> None:
        """HEARTBEAT as GCS_MAVLINK_Sub fills it in: base_mode always has STABILIZE,
        MANUAL_INPUT and CUSTOM_MODE set, GUIDED in GUIDED, SAFETY_ARMED when armed;
        system_status is CRITICAL in a failsafe, else ACTIVE armed and STANDBY not."""
        base_mode = (
            MAV.MAV_MODE_FLAG_STABILIZE_ENABLED
            | MAV.MAV_MODE_FLAG_MANUAL_INPUT_ENABLED
            | MAV.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
            | (MAV.MAV_MODE_FLAG_GUIDED_ENABLED if self._mode == GUIDED else 0)
            | (MAV.MAV_MODE_FLAG_SAFETY_ARMED if self._armed else 0)
        )
        status = MAV.MAV_STATE_ACTIVE if self._armed else MAV.MAV_STATE_STANDBY
        self._conn.mav.heartbeat_send(
            MAV.MAV_TYPE_SUBMARINE,
            MAV.MAV_AUTOPILOT_ARDUPILOTMEGA,
            base_mode,
            self._mode,
            MAV.MAV_STATE_CRITICAL if self._failsafe else status,
        )

    def _has_position(self, now: float) -> bool:
        """A position estimate, and its EKF has had time to make one."""
        return self.config.position_estimate and now >= self._boot + self.config.position_after_s

    def _send(self, message_id: int, now: float) -> None:
        """Send one ATTITUDE, VFR_HUD or SCALED_PRESSURE2, or one LOCAL_POSITION_NED if
        there is a position estimate."""
        boot_ms = int((now - self._boot) * 1000.0) & 0xFFFFFFFF
        if message_id == MAV.MAVLINK_MSG_ID_ATTITUDE:
            self._conn.mav.attitude_send(boot_ms, 0.0, 0.0, self._yaw, 0.0, 0.0, self._yaw_rate)
        elif message_id == MAV.MAVLINK_MSG_ID_VFR_HUD:
            speed = float(np.hypot(*self._velocity[:2]))
            heading = round(math.degrees(self._yaw)) % 360
            climb, altitude = -float(self._velocity[2]), -float(self._position[2])
            self._conn.mav.vfr_hud_send(speed, speed, heading, 0, altitude, climb)
        elif message_id == MAV.MAVLINK_MSG_ID_SCALED_PRESSURE2:
            pressure = SURFACE_HPA + FRESH_WATER_HPA_PER_M * float(self._position[2])
            self._conn.mav.scaled_pressure2_send(boot_ms, pressure, 0.0, 1200, 0)
        elif self._has_position(now):
            self._conn.mav.local_position_ned_send(
                boot_ms, *(float(v) for v in self._position), *(float(v) for v in self._velocity)
            )


def serve(
    config: FakeSubConfig,
    stop: threading.Event | None = None,
    on_state: Callable[[FakeSubState], None] | None = None,
    every_s: float = 1.0,
) -> None:
    """Run a fake sub until ``stop`` is set (or KeyboardInterrupt), calling ``on_state``
    every ``every_s`` seconds (a command line's status line)."""
    if not 0.0 < every_s < math.inf:
        raise ConfigError(f"every_s must be a positive number of seconds, not {every_s!r}")
    stop = stop if stop is not None else threading.Event()
    with FakeSub(config) as sub:
        try:
            while not stop.wait(every_s):
                if on_state is not None:
                    on_state(sub.state())
        except KeyboardInterrupt:
            pass
