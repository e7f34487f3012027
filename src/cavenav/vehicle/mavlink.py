"""Carry out cavenav actions on an ArduSub vehicle (a BlueROV2) over MAVLink.

An action runs the way the kinematics of SPEC section 5 do: the turn first, then one
straight translation, each a *segment*, and both aimed at one goal worked out from where
the step began (`cavenav.vehicle.control.goal_of`), so that a turn cut short is finished
by the move after it. Each is flown on the measured pose until the vehicle is within the
tolerances of its goal and still, or a timeout that the move's report records
(`cavenav.vehicle.control.MoveReport`). Two ways to drive a segment, chosen by the user:

- ``manual``: ALT_HOLD mode, MANUAL_CONTROL sticks at ``control_hz`` from a controller on
  the reported position, velocity, heading and yaw rate (`cavenav.vehicle.control`):
  ArduSub's ALT_HOLD brakes nothing horizontally, and its sticks have dead bands.
- ``guided``: GUIDED mode, one ``SET_POSITION_TARGET_LOCAL_NED`` at the goal in
  ``MAV_FRAME_LOCAL_NED`` with an absolute yaw, then wait. Not
  ``MAV_FRAME_BODY_OFFSET_NED`` with its relative yaw: ArduSub's
  ``ModeGuided::guided_set_yaw_state`` picks the turn's direction as if that yaw were
  absolute, so a relative turn can go the wrong way. Sent once: sent again, a target
  restarts ArduSub's planner. A vehicle that stops short of it (stalled) is *settled*.

Before the first step the bridge waits for the pose (a position takes ArduSub's EKF
20-45 s), then arms and dives (or rises) to the start depth, since a fresh vehicle
floats at the surface, above the shallowest depth allowed. A vehicle with no position
(no DVL, ``reckon``) is flown on timed sticks instead, and comes still in heading and
depth after each.

Both modes read the pose from ``LOCAL_POSITION_NED`` and ``ATTITUDE`` (requested at
``telemetry_hz`` with ``MAV_CMD_SET_MESSAGE_INTERVAL``, with the depth's messages below):
ALT_HOLD itself needs only the depth sensor, and a vehicle flown on its own sensors
(`ArduSubMotion` with ``reckon``) that reports no position is placed by dead reckoning
from its depth, its heading and the commanded motion (`cavenav.vehicle.dead_reckoning`),
with the uncertainty that implies; in a simulated cave (``cavenav fly --sim``) the
observation is rendered where the vehicle is, so a reported position is required. The
depth then comes from ``SCALED_PRESSURE2`` (a BlueROV2's Bar30, the pressure less
``surface_pressure_hpa`` over ``water_density_kg_m3`` times g) or, without it, from
``VFR_HUD``'s altitude (ArduSub's ``get_alt_msl``: minus the depth, but 0 until the
autopilot has an EKF origin, so a reading of exactly 0 is not taken for one); the source
chosen at the start is kept for the flight.

Only standard MAVLink messages and ArduSub's documented behaviour are relied on
(https://ardupilot.org/sub/docs/modes.html, .../parameters.html: ``SYSID_MYGCS``,
``FS_PILOT_INPUT``, ``FS_PILOT_TIMEOUT``): the bridge is a ground station (system id 255
by default), sends its heartbeat at 1 Hz and neutral sticks whenever no segment runs (in
both modes, so that ArduSub's pilot-input failsafe stays quiet while a pilot thinks, and
fires when the bridge dies: ArduSub then sets neutral controls and, with
``FS_PILOT_INPUT = 2``, disarms).

Safety, in this module: no segment while the vehicle's heartbeat is older than
``heartbeat_timeout_s`` (2.5 s), while it is disarmed or in another mode than ours, nor
one longer than ``segment_cap_s``; none once a second vehicle, or on ``udpin`` a second
peer, has been heard on the link (the bridge locks onto the first submarine's ids and
address, and sets neutral sticks the moment it hears another); depth targets
(``LOCAL_POSITION_NED``'s down) are clamped to ``[min_depth_m, max_depth_m]``; neutral
sticks (manual) or a hold at the current pose (guided) on any exception and on Ctrl-C;
arming only after the operator confirms (a flag waives it in simulation), and at the end
disarming only a vehicle the bridge armed; every message sent and received goes to the
command log as JSON lines. The forward-clearance rule is the safety shield's
(`cavenav.sim.wrappers.SafetyShield`), which `cavenav fly` puts in front of the pilot.
"""

from __future__ import annotations

import importlib.util
import json
import math
import os
import re
import stat
import threading
import time
import tomllib
from collections.abc import Callable
from contextlib import suppress
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from cavenav.core.errors import ConfigError, DependencyError, VehicleError, invalid_field
from cavenav.core.types import Action, Pose
from cavenav.motion.actions import format_action
from cavenav.motion.kinematics import Drift, wrap_angle
from cavenav.vehicle.control import (
    ControlSettings,
    Ending,
    Goal,
    Measured,
    MoveReport,
    Settling,
    goal_of,
    manual_sticks,
    off_target,
    on_target,
)
from cavenav.vehicle.dead_reckoning import DeadReckoning
from cavenav.vehicle.frames import NedFrame, NedPose, body_offset, body_to_ned

__all__ = [
    "ArduSubMotion",
    "BridgeConfig",
    "CommandRefused",
    "Segment",
    "check_address",
    "check_device",
    "describe",
    "load_bridge_config",
    "plan",
    "target_fields",
]

ALT_HOLD, GUIDED = 2, 4  # ArduSub's custom mode numbers (ArduSub/mode.h)
NEUTRAL = {"x": 0, "y": 0, "z": 500, "r": 0}  # MANUAL_CONTROL: z is 0..1000, 500 neutral
FRAME_LOCAL_NED = 1  # MAV_FRAME_LOCAL_NED: from the EKF origin, as LOCAL_POSITION_NED
FRAME_LOCAL_OFFSET_NED = 7  # MAV_FRAME_LOCAL_OFFSET_NED: NED offset from the vehicle
# SET_POSITION_TARGET_LOCAL_NED type_mask: use x, y, z and yaw; ignore velocity (8, 16,
# 32), acceleration (64, 128, 256) and yaw rate (2048).
POSITION_AND_YAW = 8 | 16 | 32 | 64 | 128 | 256 | 2048
# What a vehicle sends about itself: with a submarine's HEARTBEAT, what the bridge reads the
# pose from. Heard from a second source, it means a second vehicle on the link.
POSE_TELEMETRY = ("LOCAL_POSITION_NED", "ATTITUDE")
# Where a vehicle with no position says its depth, the preferred first.
DEPTH_SOURCES = ("SCALED_PRESSURE2", "VFR_HUD")
GRAVITY = 9.80665  # m/s², standard
CONTROL_FIELDS = tuple(ControlSettings.__dataclass_fields__)
MODE_RETRY_S = 1.0  # a refused mode is asked for again this often
GUIDED_RESENDS = 2  # a guided target sent again this often after the planner stalls
START_MARGIN_M = 0.5  # with no start depth given, this far below the shallowest allowed
START_CAP_S = 20.0  # going to the start depth may take 3 times the time expected and this

# pymavlink's network addresses, "SCHEME:HOST:PORT", and whether each listens (a listening
# one may take port 0, a port the system picks). Log files, websockets, multicast and Unix
# sockets are pymavlink forms too, but no link to one vehicle.
NETWORK_SCHEMES = {
    "udpin": True, "udp": True, "tcpin": True, "udpout": False, "udpbcast": False, "tcp": False,
}  # fmt: skip
ADDRESS_FORMS = (
    "udpin:HOST:PORT (listen, where BlueOS forwards), udpout:HOST:PORT, udp:HOST:PORT, "
    "udpbcast:HOST:PORT, tcp:HOST:PORT, tcpin:HOST:PORT, or a serial device (/dev/ttyACM0 "
    "or COM3, with its baud rate: /dev/ttyACM0,115200)"
)
_HOST = re.compile(r"[A-Za-z0-9_.-]+")  # a host name or an IPv4 address, not resolved here
# A serial device as pymavlink opens one: an absolute path (no ':', which it would read as a
# UDP address) or a Windows port, then ",BAUD" at most once.
_SERIAL = re.compile(r"(?P<device>/[^,:]+|(?i:COM)[1-9][0-9]*)(?:,(?P<baud>[0-9]+))?")


def check_address(address: str) -> str:
    """``address`` unchanged if it has the form of a link to one vehicle pymavlink opens.

    Only the form: a settings file naming /dev/ttyACM0 or COM3 loads on any machine, and
    `check_device` looks for the device when the link opens. Checked before anything is
    written, so that a typo is bad input (exit status 2) instead of pymavlink's guess: a
    string it does not know is opened as a serial port.

    Raises:
        ValueError: the address, what is wrong with it and the forms accepted.
    """
    scheme, colon, rest = address.partition(":")
    if colon and scheme in NETWORK_SCHEMES:
        host, colon, port = rest.partition(":")
        lowest = 0 if NETWORK_SCHEMES[scheme] else 1
        if not colon or not _HOST.fullmatch(host):
            raise ValueError(f"{address!r}: give {scheme}:HOST:PORT, e.g. {scheme}:127.0.0.1:14550")
        if not (port.isascii() and port.isdigit()) or not lowest <= int(port) <= 65535:
            raise ValueError(f"{address!r}: the port must be a number from {lowest} to 65535")
        return address
    serial = _SERIAL.fullmatch(address)
    if serial is None:
        raise ValueError(f"{address!r} is no MAVLink address: give {ADDRESS_FORMS}")
    if serial["baud"] is not None and int(serial["baud"]) == 0:
        raise ValueError(f"{address!r}: the baud rate must be a positive whole number")
    return address


def check_device(address: str) -> None:
    """For a serial ``address`` (see `check_address`), that its device is on this machine
    and pyserial is installed; a network address passes. Called when the link opens.

    Raises:
        VehicleError: no such device, or a file that is no device (exit status 3, as for a
            vehicle that does not answer: the cable, not the settings, is the likely cause).
        DependencyError: pyserial is missing, with the command that installs it.
    """
    serial = _SERIAL.fullmatch(address)
    if serial is None:
        return
    device = serial["device"]
    if os.name != "nt":  # a COM port is no file: there pyserial says whether it is there
        try:
            is_device = stat.S_ISCHR(os.stat(device).st_mode)
        except (OSError, ValueError):  # no such file, or a name no file can have
            is_device = None
        if is_device is None:
            raise VehicleError(
                f"cannot open MAVLink address {address!r}: {device} is not on this machine "
                "(is the vehicle plugged in?)"
            )
        if not is_device:
            raise VehicleError(f"cannot open MAVLink address {address!r}: {device} is no device")
    if importlib.util.find_spec("serial") is None:
        raise DependencyError(f"{address!r}: a serial device needs pyserial: pip install pyserial")


class BridgeConfig(BaseModel):
    """How the bridge talks to the vehicle; a TOML file of these keys overrides them.

    Rates are what the vehicle does at ``stick_limit``: calibrate them on yours (hold a
    stick until the speed is steady, measure). The defaults, and the closed loop's gains,
    were measured and tuned on ArduSub 4.5.7's SITL, which `cavenav fake-sub`'s defaults
    imitate.
    """

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    connect: str = Field(
        "udpin:0.0.0.0:14550", description="MAVLink address (BlueOS forwards here)"
    )
    mode: Literal["manual", "guided"] = "manual"
    system_id: int = Field(255, ge=1, le=255, description="our system id; ArduSub's SYSID_MYGCS")
    component_id: int = Field(190, ge=0, le=255, description="MAV_COMP_ID_MISSIONPLANNER")
    target_system: int = Field(0, ge=0, le=255, description="0: the first submarine heard")
    # Every duration and rate has a sane range: a typo of 1e308 would wait forever, and
    # sticks repeated less than once a second would trip ArduSub's pilot-input failsafe.
    heartbeat_timeout_s: float = Field(2.5, gt=0, le=60)
    connect_timeout_s: float = Field(30.0, gt=0, le=600)
    ack_timeout_s: float = Field(3.0, gt=0, le=60)
    telemetry_hz: float = Field(10.0, ge=1, le=50, description="ATTITUDE and position rate")
    control_hz: float = Field(10.0, ge=1, le=50)
    stick_limit: int = Field(400, ge=50, le=1000, description="strongest stick, of 1000")
    # Measured on ArduSub 4.5.7's SITL (JS_GAIN 0.5): stick 400 holds 0.386 m/s ahead,
    # 0.37 m/s sideways and turns 24.5 deg/s.
    forward_mps: float = Field(0.38, gt=0, le=10, description="forward/back speed at stick_limit")
    lateral_mps: float = Field(0.37, gt=0, le=10, description="sideways speed at stick_limit")
    vertical_mps: float = Field(
        0.5, gt=0, le=10, description="reckoned moves: climb with the throttle stick_limit/2 "
        "beyond its dead band"
    )  # fmt: skip
    yaw_dps: float = Field(24.5, gt=0, le=720, description="turn rate at stick_limit, deg/s")
    settle_s: float = Field(
        0.5, ge=0, le=10, description="reckoned moves: neutral sticks after a segment, "
        "then until still"
    )  # fmt: skip
    # The closed-loop manual moves (`cavenav.vehicle.control`), tuned against the SITL.
    cruise_mps: float = Field(0.3, gt=0, le=5, description="manual: the fastest a move flies")
    approach_gain: float = Field(
        0.8, gt=0, le=10, description="manual: speed wanted per metre still to go, 1/s"
    )
    velocity_gain: float = Field(
        600.0, ge=0, le=10000, description="manual: stick per m/s of speed missing"
    )
    yaw_gain: float = Field(12.0, gt=0, le=1000, description="manual: yaw stick per degree")
    stick_dead_band: int = Field(
        100, ge=0, le=500, description="manual: x, y and r sticks nearer 0 do nothing"
    )
    throttle_dead_band: int = Field(
        125, ge=0, le=499, description="manual: throttle sticks nearer 500 hold the depth"
    )
    climb_gain: float = Field(
        300.0, gt=0, le=10000, description="manual: throttle beyond its dead band per m/s"
    )
    still_mps: float = Field(0.05, gt=0, le=1, description="still: slower than this")
    still_climb_mps: float = Field(0.2, gt=0, le=2, description="still: climbing slower")
    still_dps: float = Field(2.0, gt=0, le=90, description="still: turning slower, deg/s")
    still_for_s: float = Field(0.5, ge=0, le=10, description="still: for this long")
    guided_mps: float = Field(
        0.5, gt=0, le=10, description="guided: the vehicle's speed (WPNAV_SPEED)"
    )
    guided_yaw_dps: float = Field(45.0, gt=0, le=720, description="guided: the vehicle's turn rate")
    guided_start_s: float = Field(
        1.5, ge=0, le=30, description="guided: how long ArduSub's planner takes to set off"
    )
    position_tolerance_m: float = Field(
        0.1, gt=0, le=5, description="a move is reached within this, horizontally"
    )
    depth_tolerance_m: float = Field(0.1, gt=0, le=5, description="... and this, vertically")
    yaw_tolerance_deg: float = Field(1.5, gt=0, le=45, description="... and this in heading")
    segment_cap_s: float = Field(30.0, gt=0, le=300, description="no segment lasts longer")
    reckoning_distance_error: float = Field(
        0.1, ge=0, le=1, description="dead reckoning: the speed calibration's error, a fraction"
    )
    reckoning_heading_error_deg: float = Field(
        3.0, ge=0, le=45, description="dead reckoning: the compass's error, degrees"
    )
    surface_pressure_hpa: float = Field(
        1013.25, ge=500, le=1100, description="dead reckoning: the air's pressure at the water"
    )
    water_density_kg_m3: float = Field(
        1000.0, ge=950, le=1100, description="dead reckoning: fresh 1000, sea 1025"
    )
    position_timeout_s: float = Field(
        90.0, gt=0, le=900, description="wait this long for a position before arming"
    )
    start_depth_m: float | None = Field(
        None, ge=0, description="dive (or rise) here before the first step; None: the "
        "shallowest allowed or deeper (fly --sim: where the cave's top has room above)"
    )  # fmt: skip
    min_depth_m: float = Field(0.3, description="no target shallower (autopilot depth)")
    max_depth_m: float = Field(100.0, description="no target deeper")
    disarm_at_end: bool = True

    @field_validator("connect")
    @classmethod
    def _one_vehicle_address(cls, address: str) -> str:
        return check_address(address)

    @property
    def control(self) -> ControlSettings:
        """The closed loop's settings (`cavenav.vehicle.control`)."""
        return ControlSettings(**{name: getattr(self, name) for name in CONTROL_FIELDS})


def load_bridge_config(path: str | Path | None = None, **overrides: Any) -> BridgeConfig:
    """The defaults, then the file at ``path`` (TOML, keys of `BridgeConfig`), then
    ``overrides`` (command-line flags; None leaves a value alone).

    Raises:
        ConfigError: unreadable TOML, an unknown key or an invalid value, by name.
    """
    raw: dict[str, Any] = {}
    where = "bridge settings"
    if path is not None:
        where = str(path)
        try:
            raw = tomllib.loads(Path(path).read_text())
        except FileNotFoundError:
            raise ConfigError(f"bridge config not found: {path}") from None
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
            raise ConfigError(f"{path}: not valid TOML ({exc})") from None
        except OSError as exc:  # a folder, unreadable
            raise ConfigError(f"bridge config {path}: {exc.strerror or exc}") from None
    raw.update({k: v for k, v in overrides.items() if v is not None})
    try:
        config = BridgeConfig.model_validate(raw)
    except ValidationError as exc:
        raise invalid_field(exc, where) from None
    if config.min_depth_m >= config.max_depth_m:
        raise ConfigError(f"{where}: min_depth_m must be below max_depth_m")
    return config


# ---------------------------------------------------------------------------- planning


@dataclass(frozen=True)
class Segment:
    """One phase of an action: the turn, or the translation.

    Attributes:
        kind: "turn" or "move".
        sticks: manual: MANUAL_CONTROL's x, y, z, r held for ``duration_s``.
        target: guided: SET_POSITION_TARGET_LOCAL_NED's fields (body offset frame).
        duration_s: manual: how long the sticks are held; guided: the time expected at
            the vehicle's guided speed and turn rate.
    """

    kind: Literal["turn", "move"]
    duration_s: float
    sticks: dict[str, int] | None = None
    target: dict[str, float] | None = None


def plan(action: Action, config: BridgeConfig) -> list[Segment]:
    """The segments that carry out ``action`` in ``config.mode``: a turn, then a move.

    Manual sticks are scaled so that every axis of the move ends together, which keeps
    the translation a straight line, as in the kinematics.

    Raises:
        VehicleError: a segment would last longer than ``segment_cap_s``.
    """
    forward, right, down, yaw = body_offset(action)
    limit = config.stick_limit
    segments = []
    if yaw and config.mode == "manual":
        turn = {**NEUTRAL, "r": round(math.copysign(limit, yaw))}  # r > 0: clockwise
        segments.append(Segment("turn", abs(action.yaw_deg) / config.yaw_dps, sticks=turn))
    elif yaw:
        duration = abs(action.yaw_deg) / config.guided_yaw_dps
        segments.append(Segment("turn", duration, target=_offset(0.0, 0.0, 0.0, yaw)))
    times = (
        abs(forward) / config.forward_mps,
        abs(right) / config.lateral_mps,
        abs(down) / config.vertical_mps,
    )
    duration = max(times)
    if duration > 0:
        if config.mode == "manual":
            share = [t / duration for t in times]
            move = {
                "x": round(math.copysign(limit * share[0], forward)),
                "y": round(math.copysign(limit * share[1], right)),
                "z": 500
                - round(math.copysign(config.throttle_dead_band + limit / 2 * share[2], down))
                if down
                else 500,
                "r": 0,
            }
            segments.append(Segment("move", duration, sticks=move))
        else:
            duration = math.hypot(forward, right, down) / config.guided_mps
            segments.append(Segment("move", duration, target=_offset(forward, right, down, 0.0)))
    for segment in segments:
        if segment.duration_s > config.segment_cap_s:
            raise VehicleError(
                f"'{format_action(action)}' needs a {segment.kind} of {segment.duration_s:.1f} s, "
                f"beyond the cap of {config.segment_cap_s:g} s (segment_cap_s)"
            )
    return segments


def _offset(forward: float, right: float, down: float, turn: float) -> dict[str, float]:
    return {"forward": forward, "right": right, "down": down, "turn": turn}


def target_fields(offset: dict[str, float], at: NedPose) -> dict[str, Any]:
    """SET_POSITION_TARGET_LOCAL_NED's fields for a body ``offset`` (forward, right,
    down metres; turn radians clockwise) from the pose ``at``: the offset turned by its
    heading, in MAV_FRAME_LOCAL_OFFSET_NED, and the absolute yaw to end at."""
    north, east = body_to_ned(offset["forward"], offset["right"], at.yaw)
    return {
        "coordinate_frame": FRAME_LOCAL_OFFSET_NED,
        "type_mask": POSITION_AND_YAW,
        "x": north,
        "y": east,
        "z": offset["down"],
        "yaw": wrap_angle(at.yaw + offset["turn"]),
    }


def describe(segments: list[Segment], config: BridgeConfig) -> list[str]:
    """The MAVLink commands ``segments`` send, one line each (for ``--dry-run``)."""
    lines = []
    for s in segments:
        if s.sticks is not None:
            sticks = " ".join(f"{k}={v}" for k, v in s.sticks.items())
            lines.append(
                f"{s.kind}: MANUAL_CONTROL at {config.control_hz:g} Hz from the measured pose "
                f"(at first {sticks}; about {s.duration_s:.2f} s), until within "
                f"{config.position_tolerance_m:g} m, {config.depth_tolerance_m:g} m in depth "
                f"and {config.yaw_tolerance_deg:g} deg of the step's goal and still "
                f"(under {config.still_mps:g} m/s and {config.still_dps:g} deg/s for "
                f"{config.still_for_s:g} s); without a position, {s.duration_s:.2f} s of "
                f"those sticks, then neutral"
            )
        else:
            assert s.target is not None
            t = s.target
            lines.append(
                f"{s.kind}: SET_POSITION_TARGET_LOCAL_NED frame=MAV_FRAME_LOCAL_NED "
                f"type_mask={POSITION_AND_YAW}: the step's start + forward={t['forward']:g} "
                f"right={t['right']:g} down={t['down']:g} m turned by the heading, yaw = "
                f"heading {t['turn']:+.4f} rad (absolute), then wait until within "
                f"{config.position_tolerance_m:g} m and {config.yaw_tolerance_deg:g} deg and "
                f"still (about {s.duration_s:.2f} s at the guided speed and turn rate)"
            )
    return lines or ["hold: no command (neutral sticks continue)"]


# ---------------------------------------------------------------------------- the link


class CommandRefused(VehicleError):
    """The vehicle answered a command with anything but MAV_RESULT_ACCEPTED."""


@dataclass
class _Telemetry:
    """What the vehicle last said, with the monotonic time it arrived."""

    heartbeat_at: float = -math.inf
    armed: bool = False
    mode: int | None = None
    system: int | None = None  # the vehicle flown, locked onto at its first heartbeat
    component: int | None = None
    peer: tuple[str, int] | None = None  # its address, where the link can tell (udpin)
    position: tuple[float, float, float] | None = None
    velocity: tuple[float, float, float] = (0.0, 0.0, 0.0)
    position_at: float = -math.inf
    yaw: float | None = None
    yaw_rate: float = 0.0
    climb: float = 0.0  # VFR_HUD's, m/s up
    attitude_at: float = -math.inf
    # Depths measured apart from a position, by source: (metres, arrival time).
    depths: dict[str, tuple[float, float]] = field(default_factory=dict)
    acks: dict[int, int] = field(default_factory=dict)
    failure: BaseException | None = None  # what stopped the link thread
    refused: str | None = None  # why the link refuses to fly: a second vehicle or peer


class _CommandLog:
    """Every message sent and received, one JSON object per line, flushed as written."""

    def __init__(self, path: Path | None):
        self._file = open(path, "a", encoding="utf-8") if path else None  # noqa: SIM115
        self._lock = threading.Lock()

    def write(self, direction: str, message: dict[str, Any]) -> None:
        if self._file is None:
            return
        line = json.dumps({"t": round(time.time(), 4), "dir": direction, **message}, default=str)
        with self._lock:
            self._file.write(line + "\n")
            self._file.flush()

    def close(self) -> None:
        if self._file is not None:
            with self._lock:
                self._file.close()
                self._file = None


class ArduSubLink:
    """A ground station's connection to one ArduSub vehicle.

    One background thread reads every message, keeps the latest telemetry, sends our
    heartbeat at 1 Hz and repeats the current sticks at ``control_hz``.

    The link locks onto one vehicle at its first heartbeat: its system and component id
    and, listening on UDP, its address. A second vehicle heard afterwards (another id's
    telemetry) would interleave its pose with ours, and over ``udpin`` pymavlink sends our
    commands to every address it has heard (a second peer, whatever it is): the link then
    sets neutral sticks at once, holds them, and refuses to go on (`check_alive`,
    `wait_for`).

    Threads: the link thread receives and repeats the heartbeat and sticks; the caller's
    thread sends commands. Every send and every receive happens under ``_send_lock``:
    pymavlink's ``udpin`` receive adds to the set of addresses its send iterates over.
    Locks are taken in the order ``_seen``, ``_sticks_lock``, ``_send_lock``.
    """

    def __init__(self, config: BridgeConfig, log_path: Path | None = None):
        try:
            from pymavlink import mavutil
        except ImportError as exc:  # a core dependency; a broken install says so
            raise DependencyError(f"pymavlink is missing ({exc}): pip install -e .") from None
        self.config = config
        self._mavlink = mavutil.mavlink
        check_device(config.connect)
        try:
            self._conn = mavutil.mavlink_connection(
                config.connect,
                source_system=config.system_id,
                source_component=config.component_id,
            )
        except Exception as exc:  # pymavlink raises bare OSError/ValueError here
            raise VehicleError(f"cannot open MAVLink address {config.connect!r}: {exc}") from None
        try:  # the log only once the address is open: a refused one leaves no file
            self.log = _CommandLog(log_path)
        except BaseException:
            self._conn.close()
            raise
        self.telemetry = _Telemetry()
        self._sticks = dict(NEUTRAL)
        self._send_lock = threading.Lock()
        self._sticks_lock = threading.Lock()  # the sticks read and sent as one
        self._seen = threading.Condition()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, name="mavlink-link", daemon=True)
        self._thread.start()

    @property
    def local_address(self) -> tuple[str, int] | None:
        """Where the link listens (``udpin``, ``udp``, ``tcpin``; port 0 asks the system
        for a free one), or None for a link that does not listen."""
        scheme = self.config.connect.partition(":")[0]
        if not NETWORK_SCHEMES.get(scheme):
            return None
        listening = self._conn.listen if scheme == "tcpin" else self._conn.port
        host, port = listening.getsockname()[:2]
        return host, port

    # ---------------------------------------------------------------- io
    def _send(self, name: str, **fields: Any) -> None:
        with self._send_lock:
            getattr(self._conn.mav, f"{name.lower()}_send")(**fields)
        self.log.write("sent", {"mavpackettype": name, **fields})

    def _serve(self) -> None:
        try:
            self._exchange()
        except BaseException as exc:  # a full disk under the log, a pymavlink surprise
            self.telemetry.failure = exc
            with self._seen:
                self._seen.notify_all()

    def _exchange(self) -> None:
        next_heartbeat = next_sticks = 0.0
        while not self._stop.is_set():
            now = time.monotonic()
            if now >= next_heartbeat and self.telemetry.system is not None:
                self._send(
                    "HEARTBEAT",
                    type=self._mavlink.MAV_TYPE_GCS,
                    autopilot=self._mavlink.MAV_AUTOPILOT_INVALID,
                    base_mode=0,
                    custom_mode=0,
                    system_status=self._mavlink.MAV_STATE_ACTIVE,
                )
                next_heartbeat = now + 1.0
            if now >= next_sticks and self.telemetry.system is not None:
                self.set_sticks()
                next_sticks = now + 1.0 / self.config.control_hz
            try:
                with self._send_lock:  # recv adds to the peers a send iterates over
                    message = self._conn.recv_msg()
                if message is None:
                    self._conn.select(0.02)  # wait for the next datagram, lock released
            except OSError:  # udpin before a peer spoke, or a closed socket
                message = None
            if message is not None and message.get_type() != "BAD_DATA":
                self._receive(message)

    def _receive(self, message: Any) -> None:
        kind = message.get_type()
        source = (message.get_srcSystem(), message.get_srcComponent())
        self.log.write("received", {"sys": source[0], **message.to_dict()})
        t, now = self.telemetry, time.monotonic()
        submarine = kind == "HEARTBEAT" and message.type == self._mavlink.MAV_TYPE_SUBMARINE
        with self._seen:
            if t.refused is not None:
                return
            if t.system is None:
                if not submarine or self.config.target_system not in (0, source[0]):
                    return
                t.system, t.component = source
            if source != (t.system, t.component):
                ours = source[0] == t.system  # the same id, another component
                if (ours and (submarine or kind in POSE_TELEMETRY)) or (
                    submarine and self.config.target_system == 0
                ):
                    hint = "" if ours else " (target_system chooses one)"
                    self._refuse(
                        f"two vehicles on {self.config.connect}: system {source[0]} component "
                        f"{source[1]} sends {kind} besides {self._flown()}{hint}: refusing to "
                        "fly with two on one link"
                    )
                return  # a ground station, a camera; another vehicle, with a target_system
            if not self._one_peer():
                return
            if submarine:
                t.heartbeat_at = now
                t.armed = bool(message.base_mode & self._mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
                t.mode = message.custom_mode
            elif kind == "LOCAL_POSITION_NED":
                t.position, t.position_at = (message.x, message.y, message.z), now
                t.velocity = (message.vx, message.vy, message.vz)
            elif kind == "ATTITUDE":
                t.yaw, t.yaw_rate, t.attitude_at = message.yaw, message.yawspeed, now
            elif kind == "VFR_HUD":
                t.climb = message.climb  # the barometer's, with or without a position
                if message.alt != 0.0:  # 0: no EKF origin yet
                    t.depths["VFR_HUD"] = (-message.alt, now)
            elif kind == "SCALED_PRESSURE2":
                pascals = 100.0 * (message.press_abs - self.config.surface_pressure_hpa)
                t.depths[kind] = (pascals / (self.config.water_density_kg_m3 * GRAVITY), now)
            elif kind == "COMMAND_ACK":
                t.acks[message.command] = message.result
            self._seen.notify_all()

    def _one_peer(self) -> bool:
        """Whether one address only has spoken; else the link refuses to fly on.

        Listening on UDP, pymavlink keeps every address that sent a datagram (``clients``)
        and sends our commands to all of them: a second peer, a vehicle or a ground
        station, would get them too. Other links have one peer by construction.
        """
        peers = getattr(self._conn, "clients", None)
        if not getattr(self._conn, "udp_server", False) or not peers:
            return True
        t = self.telemetry
        if len(peers) == 1:
            (t.peer,) = peers
            return True
        heard = sorted(f"{host}:{port}" for host, port in peers if (host, port) != t.peer)
        if t.peer is None:
            heard_text = f"{' and '.join(heard)} spoke before the first heartbeat"
        else:
            heard_text = f"{', '.join(heard)} speaks besides {self._flown()}"
        self._refuse(
            f"a second peer on {self.config.connect}: {heard_text}: listening, the bridge "
            "sends every command to each address heard; refusing to fly with two peers"
        )
        return False

    def _flown(self) -> str:
        t = self.telemetry
        where = f" at {t.peer[0]}:{t.peer[1]}" if t.peer else ""
        return f"system {t.system} component {t.component}{where}, the vehicle flown"

    def _refuse(self, why: str) -> None:
        """Refuse to fly on, saying ``why``, and set neutral sticks at once (called by the
        link thread under ``_seen``): sticks held for a segment must not be repeated to
        the vehicle, nor to a second one, until the main thread next looks."""
        self.telemetry.refused = why  # first: a set_sticks from now on holds neutral
        self.set_sticks(NEUTRAL)
        self._seen.notify_all()

    def set_sticks(self, sticks: dict[str, int] | None = None) -> None:
        """Hold ``sticks`` from now on and send them at once (None: send again the sticks
        held, as the link does at ``control_hz``); under one lock, so an older set is never
        sent after a newer one. Once the link has refused to fly on, the sticks stay
        neutral."""
        with self._sticks_lock:
            if self.telemetry.refused is not None:
                self._sticks = dict(NEUTRAL)
            elif sticks is not None:
                self._sticks = dict(sticks)
            if self.telemetry.system is not None:
                self._send(
                    "MANUAL_CONTROL", target=self.telemetry.system, buttons=0, **self._sticks
                )

    def wait_for(self, what: str, ready: Callable[[_Telemetry], bool], timeout_s: float) -> None:
        """Block until ``ready(telemetry)``; a VehicleError naming ``what`` after the timeout."""
        deadline = time.monotonic() + timeout_s
        with self._seen:
            while not ready(self.telemetry):
                self._check_link()
                left = deadline - time.monotonic()
                if left <= 0:
                    raise VehicleError(f"{what}: nothing after {timeout_s:g} s")
                self._seen.wait(min(left, 0.1))

    def _check_link(self) -> None:
        """A VehicleError if the link thread has stopped or refused to fly on."""
        if self.telemetry.refused is not None:
            raise VehicleError(self.telemetry.refused)
        failure = self.telemetry.failure
        if failure is not None:
            raise VehicleError(f"the MAVLink link stopped: {type(failure).__name__}: {failure}")

    def check_alive(self, mode: int) -> None:
        """Refuse to go on when the vehicle's last heartbeat is older than allowed, or it
        is no longer armed in ``mode`` (a failsafe, another ground station)."""
        self._check_link()
        t = self.telemetry
        age = time.monotonic() - t.heartbeat_at
        if age > self.config.heartbeat_timeout_s:
            raise VehicleError(
                f"the vehicle's last heartbeat is {age:.1f} s old (over "
                f"{self.config.heartbeat_timeout_s:g} s): refusing to move"
            )
        if not t.armed or t.mode != mode:
            state = "armed" if t.armed else "disarmed"
            raise VehicleError(
                f"the vehicle is {state} in mode {t.mode}, not armed in mode {mode} "
                "(a failsafe or another ground station): refusing to move"
            )

    # ---------------------------------------------------------------- commands
    def command(self, name: str, *params: float) -> None:
        """COMMAND_LONG ``name`` (a MAV_CMD_ name) and wait for its accepted COMMAND_ACK."""
        number = getattr(self._mavlink, name)
        if self.telemetry.system is None:
            raise VehicleError(f"{name}: no vehicle has been heard")
        self.telemetry.acks.pop(number, None)
        padded = [*params, *[0.0] * (7 - len(params))]
        self._send(
            "COMMAND_LONG",
            target_system=self.telemetry.system,
            target_component=self.telemetry.component,
            command=number,
            confirmation=0,
            **{f"param{i + 1}": float(p) for i, p in enumerate(padded)},
        )
        self.wait_for(
            f"{name} not acknowledged", lambda t: number in t.acks, self.config.ack_timeout_s
        )
        result = self.telemetry.acks[number]
        if result != self._mavlink.MAV_RESULT_ACCEPTED:
            entry = self._mavlink.enums["MAV_RESULT"].get(result)
            meaning = entry.name if entry else f"result {result}"
            raise CommandRefused(f"the vehicle refused {name}: {meaning}")

    def set_mode(self, mode: int) -> None:
        flag = self._mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        self.command("MAV_CMD_DO_SET_MODE", flag, mode)
        self.wait_for(
            f"mode {mode} not reported", lambda t: t.mode == mode, self.config.ack_timeout_s
        )

    def set_armed(self, armed: bool) -> None:
        self.command("MAV_CMD_COMPONENT_ARM_DISARM", 1.0 if armed else 0.0)
        self.wait_for(
            "the arming state not reported", lambda t: t.armed == armed, self.config.ack_timeout_s
        )

    def request_telemetry(self) -> None:
        """Ask for the pose's and the depth's messages at ``telemetry_hz`` (a vehicle
        streams what its SRn_ parameters or another ground station asked for otherwise)."""
        interval_us = 1e6 / self.config.telemetry_hz
        for message in ("ATTITUDE", "LOCAL_POSITION_NED", *DEPTH_SOURCES):
            number = getattr(self._mavlink, f"MAVLINK_MSG_ID_{message}")
            try:
                self.command("MAV_CMD_SET_MESSAGE_INTERVAL", number, interval_us)
            except VehicleError as refused:  # the stream rates it has may do
                self.log.write("note", {"telemetry_request": message, "refused": str(refused)})

    def send_target(self, target: dict[str, float]) -> None:
        if self.telemetry.system is None:
            return
        self._send(
            "SET_POSITION_TARGET_LOCAL_NED",
            time_boot_ms=0,
            target_system=self.telemetry.system,
            target_component=self.telemetry.component,
            vx=0.0, vy=0.0, vz=0.0, afx=0.0, afy=0.0, afz=0.0, yaw_rate=0.0,
            **target,
        )  # fmt: skip

    def pose(self) -> NedPose:
        """The latest position and heading the vehicle reported."""
        t = self.telemetry
        if t.position is None or t.yaw is None:
            raise VehicleError("the vehicle has reported no LOCAL_POSITION_NED and ATTITUDE yet")
        return NedPose(*t.position, yaw=t.yaw)

    def measured(self, depth_source: str | None = None) -> Measured:
        """The latest reported state with its rates; a vehicle with no position
        (``depth_source`` given) is placed at north = east = 0 at that depth."""
        t = self.telemetry
        if depth_source is not None:
            if t.yaw is None:
                raise VehicleError("the vehicle has reported no ATTITUDE yet")
            depth = self.depth(depth_source)
            return Measured(0.0, 0.0, depth, t.yaw, v_down=-t.climb, yaw_rate=t.yaw_rate)
        pose = self.pose()
        return Measured(pose.north, pose.east, pose.down, pose.yaw, *t.velocity, t.yaw_rate)

    def send_goal(self, goal: Goal) -> None:
        """GUIDED: a position target at ``goal`` (MAV_FRAME_LOCAL_NED, absolute yaw)."""
        self.send_target(
            {
                "coordinate_frame": FRAME_LOCAL_NED,
                "type_mask": POSITION_AND_YAW,
                "x": goal.north,
                "y": goal.east,
                "z": goal.down,
                "yaw": goal.yaw,
            }
        )

    def depth(self, source: str | None = None) -> float:
        """The latest depth from ``source`` (one of `DEPTH_SOURCES`); None: the reported
        position's."""
        t = self.telemetry
        if source is None:
            if t.position is None:
                raise VehicleError("the vehicle has reported no LOCAL_POSITION_NED yet")
            return t.position[2]
        if source not in t.depths:
            raise VehicleError(f"the vehicle has reported no depth in {source}")
        return t.depths[source][0]

    def close(self) -> None:
        """Neutral sticks, then stop the thread and close the socket and the log."""
        try:
            with suppress(VehicleError, OSError):
                self.set_sticks(NEUTRAL)
        finally:
            self._stop.set()
            self._thread.join(timeout=2.0)
            self._conn.close()
            self.log.close()


# ---------------------------------------------------------------------------- the motion


class ArduSubMotion:
    """The `cavenav.motion.kinematics.Motion` of a real (or simulated) ArduSub vehicle.

    `start` connects, sets the mode, arms after the operator's confirmation and pairs
    the reported pose with the scenario's start (`NedFrame`); `move` flies one action
    and returns the pose the autopilot reports afterwards, in the world frame.

    With ``reckon``, a vehicle that reports no position (no DVL) is flown in manual mode
    on dead reckoning: `position` says which, and `position_sigma_m` how uncertain.
    """

    def __init__(
        self,
        config: BridgeConfig,
        log_path: Path | None = None,
        confirm: Callable[[str], bool] | None = None,
        reckon: bool = False,
    ):
        """
        Args:
            log_path: the command log (JSON lines), e.g. RUN_DIR/mavlink.jsonl.
            confirm: asked "arm the vehicle?" before arming; None waives it (simulation).
            reckon: without a reported position, reckon one (manual mode only); False
                requires LOCAL_POSITION_NED (a simulated cave renders where it says).
        """
        self.config = config
        self._log_path = log_path
        self._confirm = confirm
        self._reckon = reckon
        self._link: ArduSubLink | None = None
        self._ready = False  # connected: the mode set, armed, a pose reported
        self._frame: NedFrame | None = None
        self._armed_here = False  # disarm at the end only a vehicle the bridge armed
        self._reckoning: DeadReckoning | None = None  # None: the position is reported
        self._depth_source: str | None = None  # where a reckoning vehicle's depth comes from
        self.flown = Action()  # the last move's action, as cut at the depth limits
        self.last_move: MoveReport | None = None  # how the last move went
        self._goal: Goal | None = None  # where the last move was to end
        self.start_report: dict[str, Any] | None = None  # how the start depth was reached

    @property
    def position(self) -> str:
        """ "reckoned" when the vehicle is placed by dead reckoning, else "reported"."""
        return "reported" if self._reckoning is None else "reckoned"

    @property
    def depth_source(self) -> str | None:
        """Where a reckoning vehicle's depth comes from (`DEPTH_SOURCES`); None: the
        reported position."""
        return self._depth_source

    @property
    def position_sigma_m(self) -> float | None:
        """The reckoned position's horizontal uncertainty (1 sigma); None when reported."""
        return None if self._reckoning is None else self._reckoning.sigma_m

    def listen(self) -> tuple[str, int] | None:
        """Open the link now, without waiting for the vehicle, and return where it listens
        (`ArduSubLink.local_address`): with ``udpin:HOST:0``, the port the system chose."""
        return self._open().local_address

    def start(self, pose: Pose) -> Pose:
        link = self._connect()
        self._frame = NedFrame(self._ned_pose(link), pose)
        return pose

    def _ned_pose(self, link: ArduSubLink) -> NedPose:
        """The reported pose, or the reckoned one at the measured depth and heading."""
        reckoned = self._reckoning
        if reckoned is None:
            return link.pose()
        assert link.telemetry.yaw is not None
        depth = link.depth(self._depth_source)
        return NedPose(reckoned.north, reckoned.east, depth, link.telemetry.yaw)

    def _open(self) -> ArduSubLink:
        if self._link is None:
            self._link = ArduSubLink(self.config, self._log_path)
        return self._link

    def _connect(self) -> ArduSubLink:
        """Connect, wait for the pose (before arming: a position can take the autopilot's
        EKF 20-45 s), set the mode, arm after the operator's confirmation, and take the
        vehicle to its start depth."""
        link = self._open()
        if self._ready:
            return link
        config = self.config
        link.wait_for(
            f"no heartbeat from a submarine on {config.connect}",
            lambda t: t.system is not None,
            config.connect_timeout_s,
        )
        link.request_telemetry()
        self._find_position(link)
        self._enter_mode(link)
        if not link.telemetry.armed:
            if self._confirm is not None and not self._confirm("arm the vehicle?"):
                raise VehicleError("the operator declined to arm the vehicle")
            link.set_armed(True)
            self._armed_here = True
        try:
            self._go_to_start_depth(link)
        except BaseException:
            self._stop_moving(link)
            raise
        self._ready = True
        return link

    def _enter_mode(self, link: ArduSubLink) -> None:
        """Set our mode, asking again each second while the vehicle refuses it, until
        ``position_timeout_s``: ArduSub refuses GUIDED until its EKF trusts the position,
        which on the SITL came seconds after the first LOCAL_POSITION_NED."""
        deadline = time.monotonic() + self.config.position_timeout_s
        while link.telemetry.mode != self._mode:
            try:
                link.set_mode(self._mode)
            except CommandRefused as refused:
                if time.monotonic() + MODE_RETRY_S > deadline:
                    raise
                link.log.write("note", {"mode": self._mode, "refused": str(refused)})
                time.sleep(MODE_RETRY_S)

    def _go_to_start_depth(self, link: ArduSubLink) -> None:
        """Dive (or rise) to ``start_depth_m`` and come still there, holding the position
        and heading; without one, to the shallowest depth the limits allow if the
        vehicle floats above it (a fresh vehicle floats at 0.15-0.2 m)."""
        config = self.config
        began, now = time.monotonic(), link.measured(self._depth_source)
        wanted = config.start_depth_m
        if wanted is None:
            wanted = max(now.down, config.min_depth_m + START_MARGIN_M)
        wanted = min(max(wanted, config.min_depth_m), config.max_depth_m)
        goal = self._goal = Goal(now.north, now.east, wanted, now.yaw)
        expected = abs(wanted - now.down) / self._speed
        ended = self._fly_to(link, goal, expected, cap_s=3 * expected + START_CAP_S)
        reached = link.measured(self._depth_source).down
        self.start_report = {
            "from_depth_m": round(now.down, 3),
            "start_depth_m": round(wanted, 3),
            "depth_m": round(reached, 3),
            "ended": ended,
            "seconds": round(time.monotonic() - began, 2),
        }
        link.log.write("note", {"start": self.start_report})
        if ended == "timeout":
            raise VehicleError(
                f"the vehicle did not reach its start depth {wanted:.2f} m in time: it is at "
                f"{reached:.2f} m"
            )

    @property
    def _speed(self) -> float:
        """How fast a move flies: the closed loop's cruise, or the guided speed."""
        return self.config.cruise_mps if self.config.mode == "manual" else self.config.guided_mps

    def _find_position(self, link: ArduSubLink) -> None:
        """Wait for the pose telemetry; without a reported position (and ``reckon``, in
        manual mode) start dead reckoning from here."""
        config = self.config
        if not self._reckon or config.mode == "guided":
            link.wait_for(
                "no LOCAL_POSITION_NED and ATTITUDE (the pose needs a position estimate, "
                "e.g. a DVL" + (")" if not self._reckon else "; manual mode reckons one)"),
                lambda t: t.position is not None and t.yaw is not None,
                config.position_timeout_s,
            )
            return
        link.wait_for(
            "no ATTITUDE with a depth (SCALED_PRESSURE2, or VFR_HUD's altitude, which ArduSub "
            "sends as 0 until it has an EKF origin): dead reckoning needs the heading and the "
            "depth",
            lambda t: t.yaw is not None and (bool(t.depths) or t.position is not None),
            config.connect_timeout_s,
        )
        with suppress(VehicleError):  # a position, or the Bar30, a few periods later
            link.wait_for(
                "LOCAL_POSITION_NED",
                lambda t: t.position is not None or DEPTH_SOURCES[0] in t.depths,
                3.0 / config.telemetry_hz + 0.5,
            )
        if link.telemetry.position is None:
            self._reckoning = DeadReckoning(
                config.reckoning_distance_error, config.reckoning_heading_error_deg
            )
            self._depth_source = next(s for s in DEPTH_SOURCES if s in link.telemetry.depths)
            link.log.write(
                "note", {"position": "reckoned", "depth": self._depth_source,
                         "why": "no LOCAL_POSITION_NED"},
            )  # fmt: skip

    @property
    def _mode(self) -> int:
        return ALT_HOLD if self.config.mode == "manual" else GUIDED

    def move(self, pose: Pose, action: Action) -> Pose:
        link, frame = self._link, self._frame
        if link is None or frame is None:
            raise VehicleError("the vehicle is not started: call start() first")
        asked, began, start = action, time.monotonic(), self._step_start(link)
        action = self.flown = self._within_depth_limits(link, action, start.down)
        try:
            if self._reckoning is None:
                ended, off_m, off_deg = self._fly_action(link, action, start)
            else:
                self._fly_reckoned(link, action)
                ended, off_m, off_deg = "settled", math.nan, math.nan  # unmeasured
        except BaseException:
            self._stop_moving(link)
            raise
        self.last_move = MoveReport(
            format_action(asked), format_action(action), ended,
            round(off_m, 4), round(off_deg, 3), round(time.monotonic() - began, 2),
        )  # fmt: skip
        if ended != "reached":
            link.log.write("note", {"move": self.last_move.to_dict()})
        return frame.to_world(self._ned_pose(link))

    def _step_start(self, link: ArduSubLink) -> Goal | Measured:
        """Where a step is reckoned from: the last step's goal, when the vehicle is within
        the tolerances of it (so that the shortfalls they allow do not add up), else the
        measured pose."""
        measured, last = link.measured(self._depth_source), self._goal
        return (
            last
            if last is not None and on_target(last, measured, self.config.control)
            else measured
        )

    def _fly_action(
        self, link: ArduSubLink, action: Action, start: Goal | Measured
    ) -> tuple[Ending, float, float]:
        """Fly ``action`` from ``start`` on the measured pose: the turn, then the
        translation, each aimed at one goal (`goal_of`); how it ended and how far off the
        goal the vehicle came still."""
        config = self.config
        forward, right, down, turn = body_offset(action)
        goal = self._goal = goal_of(start, forward, right, down, turn)
        facing = replace(goal, north=start.north, east=start.east, down=start.down)
        segments = plan(action, config)  # refuses a segment over segment_cap_s
        ended = self._fly_to(link, goal, 0.0) if not segments else "reached"  # a hold
        for number, segment in enumerate(segments):
            aim = goal if segment.kind == "move" else facing
            ended = self._fly_to(link, aim, segment.duration_s, number == len(segments) - 1)
        horizontal, vertical, degrees = off_target(goal, link.measured())
        return ended, math.hypot(horizontal, vertical), degrees

    def _fly_to(
        self, link: ArduSubLink, goal: Goal, expected_s: float, final: bool = True,
        cap_s: float | None = None,
    ) -> Ending:  # fmt: skip
        """Steer to ``goal`` until it is reached (and, when ``final``, the vehicle is
        still for ``still_for_s``): "reached"; a guided vehicle that stalls short of it
        after its planner had time is sent the target again, twice at most, then it has
        "settled"; neither within the cap is "timeout"."""
        config, guided = self.config, self.config.mode == "guided"
        control, began = config.control, time.monotonic()
        cap = cap_s if cap_s is not None else min(config.segment_cap_s, 3 * expected_s + 5.0)
        give_up_after = began + expected_s + (config.guided_start_s if guided else 0.0)
        settling, resends = Settling(control, config.still_for_s), GUIDED_RESENDS
        if guided:
            link.send_goal(goal)  # once a try: a target sent again restarts the planner
        while True:
            link.check_alive(self._mode)
            now, clock = link.measured(self._depth_source), time.monotonic()
            steady, stalled = settling.update(goal, now, clock)
            if on_target(goal, now, control) and (steady or not final):
                ended: Ending = "reached"
            elif guided and stalled and clock >= give_up_after and not resends:
                ended = "settled"
            elif clock - began >= cap:
                ended = "timeout"
            else:
                if not guided:
                    link.set_sticks(manual_sticks(goal, now, control))
                elif stalled and clock >= give_up_after:  # the planner stopped short: again
                    link.send_goal(goal)
                    settling, resends = Settling(control, config.still_for_s), resends - 1
                    give_up_after = clock + config.guided_start_s
                time.sleep(1.0 / config.control_hz)
                continue
            if not guided:
                link.set_sticks(NEUTRAL)
            return ended

    def _fly_reckoned(self, link: ArduSubLink, action: Action) -> None:
        """A vehicle with no position: timed sticks (`plan`), then dead reckoning."""
        for segment in plan(action, self.config):
            link.check_alive(self._mode)
            self._hold_sticks(link, segment)
        ended = time.monotonic()
        source = self._depth_source
        assert source is not None and self._reckoning is not None
        link.wait_for(
            f"no ATTITUDE and {source} after the action",
            lambda t: min(t.attitude_at, t.depths[source][1]) >= ended,
            self.config.heartbeat_timeout_s,
        )
        assert link.telemetry.yaw is not None
        self._reckoning = self._reckoning.moved(action.forward, action.right, link.telemetry.yaw)

    def drift(self, pose: Pose, action: Action, reached: Pose) -> Drift:
        """Against the whole ``action``, even where the depth limits cut it short."""
        return Drift.of(pose, action, reached)

    def _within_depth_limits(self, link: ArduSubLink, action: Action, depth: float) -> Action:
        """``action`` from ``depth`` with its vertical part cut so that the depth stays
        within limits: cut, never lengthened or reversed (a vehicle already beyond a limit
        holds its depth), so that it flies no vertical motion the shield did not judge."""
        lowest, highest = self.config.max_depth_m, self.config.min_depth_m
        if action.up > 0:  # rising: at most to the shallowest depth allowed
            target = depth - min(action.up, max(depth - highest, 0.0))
        else:
            target = depth - max(action.up, -max(lowest - depth, 0.0))
        if abs(target - (depth - action.up)) < 1e-9:
            return action
        limited = replace(action, up=round(depth - target, 2))
        link.log.write("note", {"depth_limit": True, "asked": action.up, "flown": limited.up})
        return limited

    def _hold_sticks(self, link: ArduSubLink, segment: Segment) -> None:
        assert segment.sticks is not None
        ends = time.monotonic() + segment.duration_s
        link.set_sticks(segment.sticks)
        while (left := ends - time.monotonic()) > 0:
            time.sleep(min(left, 0.05))
            link.check_alive(self._mode)
        link.set_sticks(NEUTRAL)
        time.sleep(self.config.settle_s)
        self._come_still(link)

    def _come_still(self, link: ArduSubLink) -> None:
        """Wait until a reckoned vehicle has stopped turning and climbing, as it reports
        (its horizontal speed it cannot tell), at most ``segment_cap_s``."""
        config = self.config
        settling, began = Settling(config.control, config.still_for_s), time.monotonic()
        while time.monotonic() - began < config.segment_cap_s:
            link.check_alive(self._mode)
            now = link.measured(self._depth_source)
            if settling.update(Goal(now.north, now.east, now.down, now.yaw), now, time.monotonic())[
                0
            ]:
                return
            time.sleep(1.0 / config.control_hz)

    def _stop_moving(self, link: ArduSubLink) -> None:
        """Neutral sticks, or in guided mode a target where the vehicle is now."""
        with suppress(VehicleError, OSError):
            link.set_sticks(NEUTRAL)
            if self.config.mode == "guided" and link.telemetry.position is not None:
                link.send_target(target_fields(_offset(0.0, 0.0, 0.0, 0.0), link.pose()))

    def close(self) -> None:
        """Neutral sticks, disarm (``disarm_at_end``), close the link; safe to repeat."""
        link, self._link, self._ready, self._goal = self._link, None, False, None
        if link is None:
            return
        try:
            self._stop_moving(link)
            if self.config.disarm_at_end and self._armed_here:
                with suppress(VehicleError, OSError):
                    link.set_armed(False)
        finally:
            link.close()
