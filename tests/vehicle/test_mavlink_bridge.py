"""The MAVLink bridge to ArduSub: frames, plans, settings, and flights through a simulated
autopilot on 127.0.0.1 (`cavenav.vehicle`)."""

from __future__ import annotations

import json
import math
import queue
import re
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from pymavlink import mavutil

from cavenav.cli.vehicle import _room_above
from cavenav.core.errors import CavenavError, ConfigError, VehicleError
from cavenav.core.types import Action, Pose
from cavenav.episode.loop import run_episode
from cavenav.episode.run_folder import read_jsonl
from cavenav.episode.settings import EpisodeConfig
from cavenav.motion.actions import parse_action
from cavenav.motion.kinematics import apply, wrap_angle
from cavenav.pilots.geometric import GeometricPilot
from cavenav.vehicle.fake_sub import FakeSub, FakeSubConfig
from cavenav.vehicle.frames import NedFrame, NedPose, body_offset
from cavenav.vehicle.mavlink import (
    ArduSubLink,
    ArduSubMotion,
    BridgeConfig,
    describe,
    load_bridge_config,
    plan,
    target_fields,
)
from cavenav.world.scenarios import load_scenario
from tests.conftest import cavenav, takes_ctrl_c, write_room
from tests.evaluation.test_report import ScriptedPilot, corridor

MAV = mavutil.mavlink
angles = st.floats(-math.pi, math.pi - 1e-9)
metres = st.floats(-50, 50)


def close_poses(a: Pose, b: Pose, tol: float = 1e-6) -> bool:
    turn = (a.psi - b.psi + math.pi) % (2 * math.pi) - math.pi
    return math.dist(a.position, b.position) < tol and abs(turn) < tol


# ---------------------------------------------------------------------------- frames


def test_with_no_turn_north_is_minus_y_east_is_minus_x_and_down_is_minus_z() -> None:
    frame = NedFrame(NedPose(0, 0, 0, 0), Pose(0, 0, 0, 0))
    assert close_poses(frame.to_world(NedPose(1, 0, 0, 0)), Pose(0, -1, 0, 0))
    assert close_poses(frame.to_world(NedPose(0, 1, 0, 0)), Pose(-1, 0, 0, 0))
    assert close_poses(frame.to_world(NedPose(0, 0, 1, 0)), Pose(0, 0, -1, 0))
    # a right turn: ArduSub's yaw grows clockwise, cavenav's psi counter-clockwise
    assert close_poses(frame.to_world(NedPose(0, 0, 0, math.pi / 2)), Pose(0, 0, 0, -math.pi / 2))


def test_the_start_the_autopilot_reports_is_the_scenarios_start() -> None:
    start = Pose(3.0, -7.0, -2.0, psi=0.4)
    reported = NedPose(12.0, 5.0, 30.0, yaw=2.0)
    frame = NedFrame(reported, start)
    assert close_poses(frame.to_world(reported), start)


@given(angles, angles, metres, metres, metres, st.floats(-3, 3), st.floats(-3, 3))
def test_a_body_move_reported_by_the_autopilot_is_the_same_move_in_the_world(
    yaw: float, psi: float, n: float, e: float, d: float, forward: float, right: float
) -> None:
    """The pairing turns the autopilot's axes so that its forward is the vehicle's."""
    start = Pose(1.0, 2.0, -5.0, psi)
    frame = NedFrame(NedPose(n, e, d, yaw), start)
    moved = NedPose(
        n + forward * math.cos(yaw) - right * math.sin(yaw),
        e + forward * math.sin(yaw) + right * math.cos(yaw),
        d - 0.5,
        yaw,
    )
    expected = apply(start, Action(forward=forward, right=right, up=0.5))
    assert close_poses(frame.to_world(moved), expected, 1e-6)


@given(angles, angles, metres, metres, metres, angles)
def test_world_to_ned_and_back_is_the_identity(
    yaw: float, psi: float, x: float, y: float, z: float, heading: float
) -> None:
    frame = NedFrame(NedPose(4.0, -3.0, 20.0, yaw), Pose(0.5, 0.5, -1.0, psi))
    pose = Pose(x, y, z, heading)
    assert close_poses(frame.to_world(frame.to_ned(pose)), pose, 1e-6)


def test_an_action_in_ardusubs_body_offset_frame_flips_vertical_and_yaw() -> None:
    forward, right, down, yaw = body_offset(
        parse_action("forward 0.5 m, strafe left 0.2 m, ascend 0.3 m, turn left 15 deg")
    )
    assert (forward, right, down) == (0.5, -0.2, -0.3)
    assert yaw == pytest.approx(-math.radians(15))


# ---------------------------------------------------------------------------- plans


def test_manual_turns_first_then_moves_in_a_straight_line() -> None:
    config = BridgeConfig(stick_limit=400, forward_mps=0.4, lateral_mps=0.2, yaw_dps=30)
    turn, move = plan(parse_action("forward 1 m, strafe right 0.2 m, turn left 15 deg"), config)
    assert turn.kind == "turn" and turn.sticks == {"x": 0, "y": 0, "z": 500, "r": -400}
    assert turn.duration_s == pytest.approx(0.5)
    assert move.kind == "move" and move.duration_s == pytest.approx(2.5)  # 1 m at 0.4 m/s
    # the lateral 0.2 m takes 1 s at full stick: 40 % of it over 2.5 s ends together
    assert move.sticks == {"x": 400, "y": 160, "z": 500, "r": 0}


def test_manual_vertical_sticks_are_around_500_up_above_beyond_the_throttle_dead_band() -> None:
    """A reckoned move's throttle leaves ALT_HOLD's dead band (125 around 500: within it
    the depth is held, so a smaller stick would climb nothing, as it did on the SITL)."""
    config = BridgeConfig(stick_limit=400, vertical_mps=0.2, throttle_dead_band=125)
    (up,) = plan(parse_action("ascend 0.4 m"), config)
    (down,) = plan(parse_action("descend 0.4 m"), config)
    assert up.sticks["z"] == 500 + 125 + 200 and down.sticks["z"] == 500 - 125 - 200
    assert up.duration_s == pytest.approx(2.0)


def test_guided_turns_then_moves_holding_the_heading() -> None:
    turn, move = plan(parse_action("back 0.5 m, turn right 90 deg"), BridgeConfig(mode="guided"))
    assert turn.target == {"forward": 0, "right": 0, "down": 0, "turn": pytest.approx(math.pi / 2)}
    assert move.target == {"forward": -0.5, "right": 0, "down": 0, "turn": 0}


def test_guided_targets_are_offsets_turned_by_the_heading_with_an_absolute_yaw() -> None:
    """Not a relative yaw in MAV_FRAME_BODY_OFFSET_NED: ArduSub can turn that the wrong way."""
    heading_east = NedPose(3.0, 4.0, 20.0, yaw=math.pi / 2)
    forward = target_fields({"forward": 1.0, "right": 0.5, "down": -0.2, "turn": 0.0}, heading_east)
    assert forward["coordinate_frame"] == 7  # MAV_FRAME_LOCAL_OFFSET_NED
    assert (forward["x"], forward["y"], forward["z"]) == pytest.approx((-0.5, 1.0, -0.2))
    assert forward["yaw"] == pytest.approx(math.pi / 2)
    left = target_fields({"forward": 0, "right": 0, "down": 0, "turn": -math.pi / 4}, heading_east)
    assert left["yaw"] == pytest.approx(math.pi / 4)


def test_hold_plans_nothing_and_says_so() -> None:
    assert plan(Action(), BridgeConfig()) == []
    assert "no command" in describe([], BridgeConfig())[0]


def test_a_segment_beyond_the_cap_is_refused_before_anything_moves() -> None:
    with pytest.raises(VehicleError, match="segment_cap_s"):
        plan(parse_action("turn left 180 deg"), BridgeConfig(yaw_dps=10, segment_cap_s=5))


def test_dry_run_lines_name_the_messages() -> None:
    config = BridgeConfig()
    lines = describe(plan(parse_action("forward 0.5 m, turn left 15 deg"), config), config)
    assert lines[0].startswith("turn: MANUAL_CONTROL at 10 Hz from the measured pose")
    assert "(at first x=0 y=0 z=500 r=-400;" in lines[0] and "and still" in lines[0]
    assert "(at first x=400 y=0 z=500 r=0;" in lines[1]
    guided = BridgeConfig(mode="guided")
    (line,) = describe(plan(parse_action("forward 0.5 m"), guided), guided)
    assert "SET_POSITION_TARGET_LOCAL_NED frame=MAV_FRAME_LOCAL_NED " in line


# ---------------------------------------------------------------------------- settings


def test_a_settings_file_overrides_the_defaults_and_flags_override_the_file(tmp_path) -> None:
    path = tmp_path / "bridge.toml"
    path.write_text('mode = "guided"\nforward_mps = 0.8\n')
    config = load_bridge_config(path, connect="udpin:127.0.0.1:15000", mode=None)
    assert (config.mode, config.forward_mps, config.connect) == (
        "guided",
        0.8,
        "udpin:127.0.0.1:15000",
    )


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("forward_mps = -1\n", "field 'forward_mps'"),
        ("forward_mps = nan\n", "field 'forward_mps'"),
        ("speed = 1\n", "field 'speed'"),
        ('mode = "auto"\n', "field 'mode'"),
        ("min_depth_m = 5\nmax_depth_m = 2\n", "min_depth_m must be below max_depth_m"),
        ("mode = \n", "not valid TOML"),
        # durations and rates within sane ranges: 1e308 s would wait forever
        ("connect_timeout_s = 1e308\n", "field 'connect_timeout_s'"),
        ("ack_timeout_s = 1e9\n", "field 'ack_timeout_s'"),
        ("heartbeat_timeout_s = 3600\n", "field 'heartbeat_timeout_s'"),
        ("segment_cap_s = 1e12\n", "field 'segment_cap_s'"),
        ("control_hz = 0.001\n", "field 'control_hz'"),  # the failsafe would fire
        ("telemetry_hz = 1e-300\n", "field 'telemetry_hz'"),
        ("yaw_dps = 1e308\n", "field 'yaw_dps'"),
        ("settle_s = 1e308\n", "field 'settle_s'"),
        ('connect = "bogus"\n', "field 'connect'"),
    ],
)
def test_bad_settings_are_one_line_naming_the_field(tmp_path, text: str, message: str) -> None:
    path = tmp_path / "bridge.toml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=message):
        load_bridge_config(path)


def test_a_config_that_is_a_folder_is_one_line(tmp_path) -> None:
    with pytest.raises(ConfigError, match=f"^bridge config {tmp_path}: Is a directory$"):
        load_bridge_config(tmp_path)  # it was an IsADirectoryError's traceback


@pytest.mark.parametrize(
    "address",
    [
        "udpin:0.0.0.0:14550",
        "udpin:127.0.0.1:0",  # listening: a port the system picks
        "udpout:192.168.2.2:14550",
        "udp:blueos.local:14550",
        "udpbcast:192.168.2.255:14550",
        "tcp:127.0.0.1:5760",
        "tcpin:0.0.0.0:5760",
    ],
)
def test_pymavlinks_network_addresses_are_accepted(address: str) -> None:
    assert load_bridge_config(connect=address).connect == address


@pytest.mark.parametrize(
    ("address", "problem"),
    [
        ("bogus", "'bogus' is no MAVLink address: give udpin:HOST:PORT"),
        ("", "'' is no MAVLink address"),
        ("udpin:127.0.0.1", "give udpin:HOST:PORT"),
        ("udpin::14550", "give udpin:HOST:PORT"),
        ("udpin:127.0.0.1:99999", "the port must be a number from 0 to 65535"),
        ("udpout:127.0.0.1:0", "the port must be a number from 1 to 65535"),
        ("tcp:host:port", "the port must be a number"),
        ("flight.tlog", "is no MAVLink address"),  # a log file is no vehicle
        ("ttyACM0", "is no MAVLink address"),  # pymavlink would look for it in the cwd
        ("/dev/serial/by-path/pci-0000:00:14.0-usb-0:1", "is no MAVLink address"),  # UDP to it
        ("/dev/ttyACM0,0", "the baud rate must be a positive whole number"),
        ("/dev/ttyACM0,fast", "is no MAVLink address"),
        ("COM0", "is no MAVLink address"),
    ],
)
def test_a_malformed_address_is_a_settings_error_naming_it(address: str, problem: str) -> None:
    with pytest.raises(ConfigError, match=f"field 'connect': .*{re.escape(problem)}"):
        load_bridge_config(connect=address)


@pytest.mark.parametrize(
    "address", ["/dev/ttyACM0", "/dev/serial/by-id/usb-ArduPilot,115200", "COM3", "com12,57600"]
)
def test_a_serial_device_loads_on_a_machine_without_it(address: str) -> None:
    """The settings travel between machines; the device is looked for when connecting."""
    assert load_bridge_config(connect=address).connect == address


def test_a_serial_device_that_is_not_there_is_a_vehicle_fault_when_connecting(
    tmp_path: Path,
) -> None:
    with pytest.raises(
        VehicleError, match="/dev/no-such-serial-port is not on this machine"
    ) as missing:
        ArduSubMotion(load_bridge_config(connect="/dev/no-such-serial-port")).listen()
    assert missing.value.exit_status == 3  # as a vehicle that does not answer
    (plain_file := tmp_path / "ttyACM0").write_text("")
    with pytest.raises(VehicleError, match="ttyACM0 is no device"):
        ArduSubLink(load_bridge_config(connect=str(plain_file)))


# ---------------------------------------------------------------------------- flights
# The simulated autopilot moves as ArduSub's SITL does (inertia, coasting, dead bands, the
# turn's lag, a planner slow to set off), SPEEDUP times faster, and the bridge's closed
# loop is tuned to match: the same motion in a fifth of the time.
SPEEDUP = 5.0


def sped_up_sub(k: float = SPEEDUP) -> dict[str, object]:
    """`FakeSubConfig`'s defaults (the SITL's motion) run ``k`` times faster."""
    defaults = FakeSubConfig()
    faster = ("max_speed_mps", "max_vertical_mps", "max_yaw_rate_dps", "drag_per_s",
              "buoyant_rise_mps", "guided_speed_mps", "guided_yaw_rate_dps",
              "guided_approach_per_s", "depth_hold_per_s")  # fmt: skip
    sooner = ("yaw_lag_s", "climb_lag_s", "guided_delay_s", "position_after_s")
    return {name: getattr(defaults, name) * k for name in faster} | {
        name: getattr(defaults, name) / k for name in sooner
    }


def sped_up_bridge(k: float = SPEEDUP) -> dict[str, object]:
    """`BridgeConfig`'s defaults (tuned on the SITL) for a vehicle ``k`` times faster."""
    defaults = BridgeConfig()
    faster = ("forward_mps", "lateral_mps", "vertical_mps", "yaw_dps", "cruise_mps",
              "approach_gain", "still_mps", "still_climb_mps", "still_dps", "guided_mps",
              "guided_yaw_dps")  # fmt: skip
    sooner = ("velocity_gain", "climb_gain", "still_for_s", "guided_start_s", "settle_s")
    return {name: getattr(defaults, name) * k for name in faster} | {
        name: getattr(defaults, name) / k for name in sooner
    }


FAST_SUB = sped_up_sub() | {
    "start_ned": (10.0, -4.0, 30.0),
    "start_yaw_deg": 70.0,
    "telemetry_hz": 50.0,
    "physics_hz": 100.0,
}
FAST_BRIDGE = sped_up_bridge() | {
    "telemetry_hz": 50.0,
    "control_hz": 50.0,
    "connect_timeout_s": 10.0,
}


@contextmanager
def autopilot(port: int, **settings: object) -> Iterator[FakeSub]:
    sub = FakeSub(FakeSubConfig(address=f"udpout:127.0.0.1:{port}", **{**FAST_SUB, **settings}))
    with sub:
        yield sub


def bridge(port: int, **settings: object) -> BridgeConfig:
    return BridgeConfig(connect=f"udpin:127.0.0.1:{port}", **{**FAST_BRIDGE, **settings})


# The bridge listens on a port the system picks (udpin:127.0.0.1:0), read back before the
# autopilot starts: no port is probed free and then raced for.


def listening(motion: ArduSubMotion) -> int:
    address = motion.listen()
    assert address is not None
    return address[1]


@contextmanager
def flying(port: int = 0, log: Path | None = None, **settings: object) -> Iterator[ArduSubMotion]:
    """A bridge to the autopilot on ``port`` (its command log at ``log``), closed whatever
    the test does."""
    motion = ArduSubMotion(bridge(port, **settings), log)
    try:
        yield motion
    finally:
        motion.close()


@contextmanager
def flown(sub: dict[str, object] | None = None, **settings: object) -> Iterator[
    tuple[ArduSubMotion, FakeSub]
]:  # fmt: skip
    """A bridge (``settings``) and an autopilot (``sub``) sending to the port it listens on;
    the bridge is closed first, while the autopilot still answers its disarm."""
    with flying(**settings) as motion, autopilot(listening(motion), **(sub or {})) as vehicle:
        try:
            yield motion, vehicle
        finally:
            motion.close()


def fly_s4(tmp_path: Path, mode: str, **sub_settings: object) -> tuple[dict, list[dict]]:
    (tmp_path / "run").mkdir()
    motion = ArduSubMotion(bridge(0, mode=mode), tmp_path / "run" / "mavlink.jsonl")
    config = EpisodeConfig(save_frames=False, plots=False, shield=True)
    try:
        with autopilot(listening(motion), **sub_settings):
            result = run_episode(load_scenario("S4", 0), GeometricPilot(), config,
                                 tmp_path / "run", motion=motion)  # fmt: skip
    finally:
        motion.close()
    return result.summary, result.steps


@pytest.mark.slow
def test_the_geometric_pilot_flies_s4_through_mavlink_in_manual_mode_with_noise(
    tmp_path: Path,
) -> None:
    summary, steps = fly_s4(tmp_path, "manual", noise=0.05, seed=3)
    assert summary["termination"] == "exit" and summary["collisions"] == 0
    assert 0 < summary["mean_drift_m"] < 0.2  # noise and timing: never exactly the command
    log = read_jsonl(tmp_path / "run" / "mavlink.jsonl")
    sent = {r["mavpackettype"] for r in log if r["dir"] == "sent"}
    assert {"HEARTBEAT", "MANUAL_CONTROL", "COMMAND_LONG"} <= sent
    assert any(r["dir"] == "received" and r["mavpackettype"] == "LOCAL_POSITION_NED" for r in log)
    assert all("drift_m" in s and "commanded_pose" in s for s in steps)


@pytest.mark.slow
def test_the_geometric_pilot_flies_s4_through_mavlink_in_guided_mode(tmp_path: Path) -> None:
    summary, _ = fly_s4(tmp_path, "guided", noise=0.02, seed=4)
    assert summary["termination"] == "exit" and summary["collisions"] == 0
    assert summary["max_drift_m"] < 0.3


# 1 m/s at the bridge's stick limit: a sleep that overshoots 50 ms costs 5 cm
GENTLE = {"stick_limit": 125, "forward_mps": 1.0, "vertical_mps": 0.5}


def test_the_bridge_arms_in_alt_hold_and_disarms_with_neutral_sticks_at_the_end() -> None:
    with flown(**GENTLE) as (motion, sub):
        start = Pose(1.0, 2.0, -3.0, 0.3)
        assert motion.start(start) == start
        state = sub.state()
        assert state.armed and state.mode_name == "ALT_HOLD"
        reached = motion.move(start, parse_action("forward 1 m"))
        # Straight ahead along the heading; how far is the sticks' time at 1 m/s, judged
        # only within half a second of the calibrated 1 s.
        unit = np.subtract(apply(start, Action(forward=1.0)).position, start.position)
        moved = np.subtract(reached.position, start.position)
        ahead = float(moved @ unit)
        assert np.linalg.norm(moved - ahead * unit) < 1e-3
        assert 0.5 < ahead < 1.5
        motion.close()
        assert wait_until(lambda: not sub.state().armed)
        assert sub.state().sticks == (0, 0, 500, 0)


def test_a_vehicle_armed_before_the_bridge_came_is_left_armed() -> None:
    with flown(disarm_at_end=False) as (first, sub):
        first.start(Pose(0, 0, 0))
        port = listening(first)
        first.close()
        with flying(port) as second:  # on the port the autopilot sends to, freed just now
            second.start(Pose(0, 0, 0))
        assert sub.state().armed


def test_no_vehicle_is_one_line_and_closing_after_it_is_clean() -> None:
    with (
        flying(connect_timeout_s=0.3) as motion,
        pytest.raises(VehicleError, match="no heartbeat from a submarine"),
    ):
        motion.start(Pose(0, 0, 0))
    motion.close()  # again: nothing left to close


def test_the_operator_is_asked_before_arming_and_a_no_leaves_it_disarmed() -> None:
    asked = []
    with flown() as (motion, sub):
        motion._confirm = lambda q: asked.append(q) or False
        with pytest.raises(VehicleError, match="declined"):
            motion.start(Pose(0, 0, 0))
        assert asked == ["arm the vehicle?"] and not sub.state().armed


def test_no_move_while_the_vehicles_heartbeat_is_stale() -> None:
    with flown(heartbeat_timeout_s=0.5) as (motion, sub):
        start = motion.start(Pose(0, 0, 0))
        sub.pause_heartbeat(True)
        time.sleep(0.6)
        before = sub.state()
        with pytest.raises(VehicleError, match="heartbeat is .* old"):
            motion.move(start, parse_action("forward 1 m"))
        after = sub.state()
        assert math.dist((before.north, before.east), (after.north, after.east)) < 0.01
        sub.pause_heartbeat(False)  # for the disarm on the way out


def test_a_heartbeat_lost_mid_segment_stops_the_segment_with_neutral_sticks() -> None:
    """Stopped short of the move, wherever the heartbeat is lost: what the vehicle flew is
    read from the autopilot, not from a clock (when it refuses is the next test's)."""
    slow = {"cruise_mps": 0.3}  # 'forward 1 m' takes more than 3 s
    with flown(heartbeat_timeout_s=1.5, **slow) as (motion, sub):
        start = motion.start(Pose(0, 0, 0))
        at_start = sub.state()

        def flown_m() -> float:
            state = sub.state()
            return math.dist((state.north, state.east), (at_start.north, at_start.east))

        def lose_the_heartbeat_once_moving() -> None:
            if wait_until(lambda: flown_m() > 0.05, 10.0):
                sub.pause_heartbeat(True)

        threading.Thread(target=lose_the_heartbeat_once_moving, daemon=True).start()
        with pytest.raises(VehicleError, match="heartbeat is .* old"):
            motion.move(start, parse_action("forward 1 m"))
        assert wait_until(lambda: sub.state().sticks == (0, 0, 500, 0))
        assert 0.05 < flown_m() < 1.0  # about 0.35 m: 1.5 s at most after the pause
        sub.pause_heartbeat(False)  # for the disarm on the way out


def test_a_move_is_refused_once_the_heartbeat_is_older_than_the_timeout() -> None:
    """The age is the link's record of when the last heartbeat came, set back here rather
    than waited for; 10 s either side of the 30 s timeout, so that no pause of the test
    tips it."""
    with one_vehicle(heartbeat_timeout_s=30.0) as (link, _, _):
        heard = link.telemetry.heartbeat_at
        link.telemetry.heartbeat_at = heard - 20.0
        link.check_alive(2)  # armed in ALT_HOLD, 20 s old: goes on
        link.telemetry.heartbeat_at = heard - 40.0
        with pytest.raises(VehicleError, match=r"heartbeat is 4\d\.\d s old \(over 30 s\)"):
            link.check_alive(2)


def test_a_vehicle_with_no_position_estimate_is_refused_before_it_is_armed() -> None:
    with flown({"position_estimate": False}, mode="guided", position_timeout_s=1.0) as (
        motion,
        sub,
    ):
        with pytest.raises(VehicleError, match="no LOCAL_POSITION_NED and ATTITUDE"):
            motion.start(Pose(0, 0, 0))
        assert not sub.state().armed and sub.state().mode_name == "MANUAL"


def at_depth(sub: FakeSub, down: float) -> bool:
    """The autopilot comes to rest at ``down``, to within the tolerance the move is flown to."""
    return wait_until(lambda: sub.state().down == pytest.approx(down, abs=0.005))


def test_guided_depth_targets_stop_at_the_depth_limits() -> None:
    """The target the autopilot flies to is cut at max_depth_m and min_depth_m; a move
    within them is not touched."""
    # GUIDED lands on its targets: tolerances this tight end each move exactly there
    limits = {"min_depth_m": 2.5, "max_depth_m": 4.0, "start_depth_m": 3.0}
    exact = {"depth_tolerance_m": 0.002, "position_tolerance_m": 0.002}
    with flown({"start_ned": (0.0, 0.0, 3.0)}, mode="guided", **limits, **exact) as (motion, sub):
        start = motion.start(Pose(0, 0, 0))  # 3 m deep
        pose = motion.move(start, parse_action("descend 0.5 m"))
        assert at_depth(sub, 3.5)
        pose = motion.move(pose, parse_action("descend 1 m"))  # to 4.5 m, asked
        assert at_depth(sub, 4.0)
        assert pose.z == pytest.approx(-1.0, abs=0.06)  # within the position tolerance
        pose = motion.move(pose, parse_action("ascend 2 m"))  # to 2 m, asked
        assert at_depth(sub, 2.5)
        assert pose.z == pytest.approx(0.5, abs=0.06)


def test_manual_ascents_and_descents_stop_at_the_depth_limits(tmp_path: Path) -> None:
    """The part of a move within the limits is flown, to within the depth tolerance, and
    the command log and the move's report say what was asked and what flown."""
    log = tmp_path / "mavlink.jsonl"
    limits = {"min_depth_m": 0.5, "max_depth_m": 1.5, "start_depth_m": 1.0}
    with flown({"start_ned": (0.0, 0.0, 1.0)}, log=log, **limits) as (motion, sub):
        pose = motion.start(Pose(0, 0, 0))  # 1 m deep
        before = 1.0  # the start depth's goal, which the next step is reckoned from
        pose = motion.move(pose, parse_action("ascend 2 m"))  # to 1 m above the surface
        assert motion.last_move is not None and motion.last_move.depth_limited
        assert (motion.last_move.asked, motion.last_move.ended) == ("ascend 2 m", "reached")
        shallowest = sub.state().down
        motion.move(pose, parse_action("descend 2 m"))  # to about 2.5 m
        deepest = sub.state().down
    assert shallowest == pytest.approx(0.5, abs=0.1) and deepest == pytest.approx(1.5, abs=0.1)
    notes = [(r["asked"], r["flown"]) for r in read_jsonl(log) if r.get("depth_limit")]
    assert notes[0] == (2.0, pytest.approx(before - 0.5, abs=0.01))
    assert notes[1] == (-2.0, pytest.approx(-1.0, abs=0.1))


# ---------------------------------------------------------------------------- one vehicle

NEUTRAL_STICKS = (0, 0, 500, 0)


def test_two_vehicles_with_one_system_id_on_the_port_are_refused_before_arming() -> None:
    with flying() as motion:
        port = listening(motion)
        with (
            autopilot(port, start_ned=(0.0, 0.0, 12.0)) as deep,
            autopilot(port, start_ned=(0.0, 0.0, 0.5)) as shallow,
        ):
            with pytest.raises(VehicleError, match=r"a second peer on udpin:127\.0\.0\.1:0: "):
                motion.start(Pose(0, 0, 0))
            motion.close()
            for sub in (deep, shallow):
                state = sub.state()
                assert not state.armed and state.sticks == NEUTRAL_STICKS


def test_a_second_vehicle_heard_mid_flight_stops_the_flight_with_neutral_sticks() -> None:
    with flying(**GENTLE) as motion:
        port = listening(motion)
        with autopilot(port) as first:
            start = motion.start(Pose(0, 0, 0))
            pose = motion.move(start, parse_action("forward 0.5 m"))
            with autopilot(port, start_ned=(0.0, 0.0, 0.5)) as second:
                with pytest.raises(VehicleError, match="speaks besides system 1 component 1 at"):
                    motion.move(pose, parse_action("forward 1 m, turn left 90 deg"))  # ~3 s
                for sub in (first, second):
                    assert wait_until(lambda sub=sub: sub.state().sticks == NEUTRAL_STICKS, 1.0)
                with pytest.raises(VehicleError, match="a second peer"):  # and it stays refused
                    motion.move(pose, parse_action("hold"))


def heartbeat(kind: int) -> Callable[[Any], None]:
    """A HEARTBEAT of type ``kind``, armed in ALT_HOLD (2)."""
    armed = MAV.MAV_MODE_FLAG_SAFETY_ARMED | MAV.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    return lambda mav: mav.heartbeat_send(
        kind, MAV.MAV_AUTOPILOT_ARDUPILOTMEGA, armed, 2, MAV.MAV_STATE_ACTIVE
    )


@pytest.mark.parametrize(
    ("system", "component", "send", "target_system", "refused"),
    [
        pytest.param(2, 1, heartbeat(MAV.MAV_TYPE_SUBMARINE), 0, True, id="another submarine"),
        pytest.param(
            1, 2, lambda mav: mav.attitude_send(0, 0, 0, 1.0, 0, 0, 0), 0, True,
            id="our system id, another component's attitude",
        ),
        pytest.param(
            1, 2, heartbeat(MAV.MAV_TYPE_SUBMARINE), 1, True, id="our system id, two autopilots"
        ),
        pytest.param(255, 190, heartbeat(MAV.MAV_TYPE_GCS), 0, False, id="a ground station"),
        pytest.param(1, 100, heartbeat(MAV.MAV_TYPE_CAMERA), 0, False, id="the vehicle's camera"),
        pytest.param(
            2, 1, heartbeat(MAV.MAV_TYPE_SUBMARINE), 1, False, id="another, not the target_system"
        ),
    ],
)  # fmt: skip
def test_the_link_locks_onto_one_vehicle_and_refuses_a_second_from_one_address(
    system: int, component: int, send: Callable[[Any], None], target_system: int, refused: bool
) -> None:
    """Through one address (a router, as BlueOS is), a second vehicle shows by its ids."""
    link = ArduSubLink(BridgeConfig(connect="udpin:127.0.0.1:0", target_system=target_system))
    vehicle = None
    try:
        port = link.local_address[1]  # type: ignore[index]
        vehicle = mavutil.mavlink_connection(
            f"udpout:127.0.0.1:{port}", source_system=1, source_component=1
        )
        heartbeat(MAV.MAV_TYPE_SUBMARINE)(vehicle.mav)
        link.wait_for("a heartbeat", lambda t: t.system is not None, 5.0)
        vehicle.mav.srcSystem, vehicle.mav.srcComponent = system, component
        send(vehicle.mav)
        vehicle.mav.srcSystem, vehicle.mav.srcComponent = 1, 1
        vehicle.mav.attitude_send(0, 0, 0, 0.5, 0, 0, 0)  # after it on the same socket
        if refused:
            with pytest.raises(VehicleError, match=f"two vehicles .*: system {system} "):
                link.wait_for("never", lambda t: False, 5.0)
        else:
            link.wait_for("the vehicle's ATTITUDE", lambda t: t.yaw == 0.5, 5.0)
            link.check_alive(2)  # armed in ALT_HOLD, as the heartbeat says
    finally:
        link.close()
        if vehicle is not None:
            vehicle.close()


@contextmanager
def one_vehicle(**settings: Any) -> Iterator[tuple[ArduSubLink, Any, int]]:
    """A link listening on a port the system picks, locked onto a vehicle (system 1,
    component ``component``, default 1) that a bare pymavlink connection plays."""
    component = settings.pop("component", 1)
    link = ArduSubLink(BridgeConfig(connect="udpin:127.0.0.1:0", **settings))
    vehicle = None
    try:
        port = link.local_address[1]  # type: ignore[index]
        vehicle = mavutil.mavlink_connection(
            f"udpout:127.0.0.1:{port}", source_system=1, source_component=component
        )
        heartbeat(MAV.MAV_TYPE_SUBMARINE)(vehicle.mav)
        link.wait_for("a heartbeat", lambda t: t.system is not None, 5.0)
        yield link, vehicle, port
    finally:
        link.close()
        if vehicle is not None:
            vehicle.close()


def received(connection: Any, kind: str, count: int, timeout_s: float = 5.0) -> list[Any]:
    """The next ``count`` messages of ``kind`` that ``connection`` receives; fails if they
    do not come within ``timeout_s`` (a generous wait, not a claim about speed)."""
    messages, deadline = [], time.monotonic() + timeout_s
    while len(messages) < count:
        left = deadline - time.monotonic()
        assert left > 0, f"{len(messages)} {kind} of {count} after {timeout_s} s"
        message = connection.recv_match(type=kind, blocking=True, timeout=left)
        if message is not None:
            messages.append(message)
    return messages


def drain(connection: Any) -> None:
    while connection.recv_match(blocking=False) is not None:
        pass


def test_a_ground_station_on_a_second_address_is_refused_as_a_second_peer() -> None:
    """Not as "two vehicles": on udpin every command would go to it too, whatever it is."""
    with one_vehicle() as (link, vehicle, port):
        station = mavutil.mavlink_connection(
            f"udpout:127.0.0.1:{port}", source_system=255, source_component=190
        )
        try:
            heartbeat(MAV.MAV_TYPE_GCS)(station.mav)
            vehicle.mav.attitude_send(0, 0, 0, 0.5, 0, 0, 0)
            with pytest.raises(VehicleError) as refused:
                link.wait_for("never", lambda t: False, 5.0)
        finally:
            station.close()
    message = str(refused.value)
    assert re.match(r"a second peer on udpin:127\.0\.0\.1:0: 127\.0\.0\.1:\d+ speaks besides "
                    r"system 1 component 1 at 127\.0\.0\.1:\d+", message)  # fmt: skip
    assert "two vehicles" not in message


def test_sticks_held_when_a_second_peer_is_heard_turn_neutral_at_once_and_stay_so() -> None:
    """The link thread repeats the sticks at control_hz: it must not repeat a segment's
    sticks to the vehicle (and, over udpin, to the second peer) until the main thread
    next looks, nor take new ones after the refusal."""
    forward = {"x": 400, "y": 0, "z": 500, "r": 0}
    with one_vehicle(control_hz=50) as (link, vehicle, port):
        link.set_sticks(forward)
        assert vehicle.recv_match(
            type="MANUAL_CONTROL", condition="MANUAL_CONTROL.x == 400", blocking=True, timeout=5.0
        )
        second = mavutil.mavlink_connection(
            f"udpout:127.0.0.1:{port}", source_system=1, source_component=1
        )
        try:
            heartbeat(MAV.MAV_TYPE_SUBMARINE)(second.mav)
            # The main thread does not look yet: the link thread alone turns them neutral,
            # and repeats only neutral ones (five at control_hz).
            assert vehicle.recv_match(
                type="MANUAL_CONTROL", condition="MANUAL_CONTROL.x == 0", blocking=True, timeout=5
            )
            sticks = received(vehicle, "MANUAL_CONTROL", 5)
            with pytest.raises(VehicleError, match="a second peer"):
                link.wait_for("never", lambda t: False, 5.0)
            link.set_sticks(forward)  # a segment that began as the refusal came
            sticks += received(vehicle, "MANUAL_CONTROL", 5)  # that one's and four repeats
        finally:
            second.close()
    assert {(m.x, m.y, m.z, m.r) for m in sticks} == {NEUTRAL_STICKS}


def test_a_peer_heard_while_a_command_is_being_sent_is_a_refusal_not_a_crash() -> None:
    """pymavlink's udpin send iterates over the addresses heard while the link thread's
    receive adds to them: never "Set changed size during iteration" from a send."""
    with one_vehicle(mode="guided", control_hz=1) as (link, vehicle, port):
        # The link's first heartbeat and sticks are out: its thread only receives for the
        # next second (control_hz=1), so it is receiving when the second peer speaks.
        assert vehicle.recv_match(type="MANUAL_CONTROL", blocking=True, timeout=5.0)
        second = mavutil.mavlink_connection(
            f"udpout:127.0.0.1:{port}", source_system=1, source_component=1
        )
        udp, caller, spoken = link._conn.port, threading.current_thread(), threading.Event()

        class PeerSpeaksMidSend:
            """The link's socket; its first send from this thread waits mid-send (0.5 s at
            most) for the second peer's heartbeat to be received."""

            def __getattr__(self, name: str) -> Any:
                return getattr(udp, name)

            def sendto(self, data: bytes, address: Any) -> int:
                if threading.current_thread() is caller and not spoken.is_set():
                    spoken.set()
                    heartbeat(MAV.MAV_TYPE_SUBMARINE)(second.mav)
                    wait_until(lambda: len(link._conn.clients) > 1, 0.5)
                return udp.sendto(data, address)

        link._conn.port = PeerSpeaksMidSend()
        try:
            link.send_target(target_fields(_HOLD, NedPose(0.0, 0.0, 5.0, 0.0)))
            assert spoken.is_set()
            with pytest.raises(VehicleError, match="a second peer"):
                link.wait_for("never", lambda t: False, 5.0)
        finally:
            link._conn.port = udp
            second.close()


_HOLD = {"forward": 0.0, "right": 0.0, "down": 0.0, "turn": 0.0}


def test_commands_and_targets_go_to_the_component_the_link_locked_onto() -> None:
    """A vehicle whose autopilot is component 2 (not MAV_COMP_ID_AUTOPILOT1) gets them."""
    with one_vehicle(component=2, ack_timeout_s=0.2) as (link, vehicle, _):
        drain(vehicle)
        with pytest.raises(VehicleError, match="not acknowledged"):
            link.command("MAV_CMD_COMPONENT_ARM_DISARM", 1.0)
        link.send_target(target_fields(_HOLD, NedPose(0.0, 0.0, 5.0, 0.0)))
        command = vehicle.recv_match(type="COMMAND_LONG", blocking=True, timeout=2.0)
        target = vehicle.recv_match(
            type="SET_POSITION_TARGET_LOCAL_NED", blocking=True, timeout=2.0
        )
    assert (command.target_system, command.target_component) == (1, 2)
    assert (target.target_system, target.target_component) == (1, 2)


def wait_until(condition: Callable[[], bool], timeout_s: float = 5.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(0.02)
    return condition()


# ---------------------------------------------------------------------------- the command


def test_fly_on_a_vehicles_own_sensors_refuses_the_geometric_pilot_without_depth(
    tmp_path: Path,
) -> None:
    result = cavenav("fly", "--pilot", "geometric", "--out", str(tmp_path / "runs"))
    assert result.returncode == 2
    (line,) = result.stderr.strip().splitlines()
    assert "steers by the depth image: give --depth-model FOLDER" in line
    assert not (tmp_path / "runs").exists()


def test_fly_on_a_vehicles_own_sensors_keeps_the_shield_without_a_depth_image(
    tmp_path: Path,
) -> None:
    result = cavenav("fly", "--pilot", "random", "--no-shield", "--out", str(tmp_path))
    assert result.returncode == 2
    (line,) = result.stderr.strip().splitlines()
    assert "--no-shield without --depth-model" in line
    assert list(tmp_path.iterdir()) == []


def test_fly_on_a_vehicles_own_sensors_refuses_a_bad_camera_address(tmp_path: Path) -> None:
    result = cavenav("fly", "--pilot", "random", "--camera", "udp:99999", "--out", str(tmp_path))
    assert result.returncode == 2
    assert result.stderr.strip().splitlines() == [
        "error: camera 'udp:99999': give udp:PORT (RTP H.264, BlueOS sends to 5600), "
        "rtsp://HOST:PORT/PATH or a URL FFmpeg opens"
    ]
    assert list(tmp_path.iterdir()) == []


def test_fly_dry_run_prints_the_commands_and_sends_nothing() -> None:
    result = cavenav(
        "fly", "--dry-run", "--mode", "guided", "--action", "forward 0.5 m, turn left 15 deg"
    )
    assert result.returncode == 0, result.stderr
    assert "turn: SET_POSITION_TARGET_LOCAL_NED" in result.stdout
    assert "move: SET_POSITION_TARGET_LOCAL_NED" in result.stdout


def test_fly_refuses_a_bad_settings_file_in_one_line(tmp_path: Path) -> None:
    settings = tmp_path / "bridge.toml"
    settings.write_text("yaw_dps = 0\n")
    result = cavenav("fly", "--config", str(settings), "--dry-run", "--action", "hold")
    assert result.returncode == 2
    (line,) = result.stderr.strip().splitlines()
    assert line.startswith(f"error: {settings}: field 'yaw_dps': ")


@pytest.mark.parametrize("address", ["bogus", ""])
def test_fly_refuses_a_malformed_address_in_one_line_before_anything_is_written(
    tmp_path: Path, address: str
) -> None:
    """Not pymavlink's "No module named 'serial'" with a vehicle's exit status 3."""
    out = tmp_path / "runs"
    result = cavenav("fly", "--sim", "S1", "--yes", "--connect", address, "--out", str(out))
    assert result.returncode == 2
    (line,) = result.stderr.strip().splitlines()
    assert re.match(f"error: bridge settings: field 'connect': .*'{address}' is no MAVLink", line)
    assert not out.exists()


@pytest.mark.slow
def test_fly_that_hears_no_vehicle_exits_3_and_leaves_no_run_folder(tmp_path: Path) -> None:
    settings = tmp_path / "bridge.toml"
    settings.write_text("connect_timeout_s = 0.3\n")
    out = tmp_path / "runs"
    result = cavenav(
        "fly", "--sim", str(write_room(tmp_path)), "--yes", "--no-frames",
        "--config", str(settings), "--connect", "udpin:127.0.0.1:0", "--out", str(out),
    )  # fmt: skip
    assert result.returncode == 3
    assert result.stderr.strip().splitlines() == [
        "error: no heartbeat from a submarine on udpin:127.0.0.1:0: nothing after 0.3 s"
    ]
    assert list(out.iterdir()) == []  # not a folder holding only mavlink.jsonl


def start_flying(tmp_path: Path) -> tuple[subprocess.Popen[str], int]:
    """`cavenav fly --sim S1` at the calibrated default rates (segments of about a second),
    listening on a port the system picks, and that port, as the command prints it."""
    process = subprocess.Popen(
        [sys.executable, "-m", "cavenav.cli", "fly", "--sim", "S1", "--yes", "--no-frames",
         "--connect", "udpin:127.0.0.1:0", "--out", str(tmp_path), "--steps", "30",
         "--start-depth", "30"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=takes_ctrl_c,
    )  # fmt: skip
    lines: queue.Queue[str] = queue.Queue()

    def read_until_listening() -> None:  # then communicate() reads the rest
        assert process.stdout is not None
        for line in process.stdout:
            lines.put(line)
            if "listening on" in line:
                return
        lines.put("")  # the command ended first

    threading.Thread(target=read_until_listening, daemon=True).start()
    while line := lines.get(timeout=120):
        if found := re.search(r"listening on 127\.0\.0\.1:(\d+)", line):
            return process, int(found[1])
    process.kill()
    raise AssertionError(f"fly printed no port: {process.communicate()}")


def calibrated_autopilot(port: int, pilot_timeout_s: float) -> FakeSub:
    """The fake sub at its defaults, which the bridge's defaults are calibrated to."""
    config = FakeSubConfig(
        address=f"udpout:127.0.0.1:{port}",
        start_ned=(0.0, 0.0, 30.0),
        pilot_timeout_s=pilot_timeout_s,
    )
    return FakeSub(config)


def mid_segment(sub: FakeSub, process: subprocess.Popen[str], out: Path) -> None:
    """Wait until the episode has begun (its summary is written: the vehicle is at its
    start depth) and the bridge holds a stick that is not neutral."""
    assert wait_until(
        lambda: (
            (any(out.glob("*/summary.json")) and sub.state().sticks != (0, 0, 500, 0))
            or process.poll() is not None
        ),
        90,
    )
    assert process.poll() is None, process.communicate()


@pytest.mark.slow
def test_killing_the_bridge_mid_segment_leaves_neutral_sticks_then_a_disarm(
    tmp_path: Path,
) -> None:
    process, port = start_flying(tmp_path)
    try:
        with calibrated_autopilot(port, pilot_timeout_s=1.0) as sub:
            mid_segment(sub, process, tmp_path)
            process.kill()  # SIGKILL: no neutral sticks from the bridge
            process.wait()
            assert sub.state().armed  # until the failsafe fires
            assert wait_until(lambda: sub.state().failsafe, 3)
            state = sub.state()
            assert state.sticks == (0, 0, 500, 0) and not state.armed
    finally:
        process.kill()


@pytest.mark.slow
def test_ctrl_c_mid_segment_sets_neutral_sticks_at_once_and_keeps_the_record(
    tmp_path: Path,
) -> None:
    process, port = start_flying(tmp_path)
    try:
        with calibrated_autopilot(port, pilot_timeout_s=5.0) as sub:
            mid_segment(sub, process, tmp_path)
            process.send_signal(signal.SIGINT)
            assert wait_until(lambda: sub.state().sticks == (0, 0, 500, 0), 1.0)
            _, stderr = process.communicate(timeout=30)
            assert process.returncode == 130, stderr
            state = sub.state()
            assert not state.armed and not state.failsafe  # disarmed by the bridge, at once
    finally:
        process.kill()
    (run_dir,) = tmp_path.iterdir()
    assert json.loads((run_dir / "summary.json").read_text())["status"] == "interrupted"
    assert read_jsonl(run_dir / "mavlink.jsonl")


# ---------------------------------------------------------------------------- the SITL's lessons
# Flown against ArduSub 4.5.7's SITL (issue 46), the bridge crashed or fell short in six
# ways; each is a test here against the fake sub, which has learned the SITL's motion
# (inertia and coasting, dead bands, buoyancy, a late position, a planner slow to start).


def test_from_the_surface_the_vehicle_dives_before_the_first_step_and_can_then_ascend() -> None:
    """1. A fresh vehicle floats at 0.17 m, above the 0.3 m limit, where every ascent
    was cut to nothing."""
    with flown({"start_ned": (0.0, 0.0, 0.17)}) as (motion, sub):
        start = motion.start(Pose(0, 0, 0))
        assert motion.start_report is not None
        assert motion.start_report["from_depth_m"] == pytest.approx(0.17, abs=0.03)
        assert motion.start_report["ended"] == "reached"
        assert sub.state().down == pytest.approx(0.3 + 0.5, abs=0.1)  # the limit and a margin
        motion.move(start, parse_action("ascend 0.3 m"))
        assert motion.last_move is not None and not motion.last_move.depth_limited
        assert sub.state().down == pytest.approx(0.5, abs=0.1)


def test_fly_sim_starts_as_deep_as_the_cave_rises_above_its_start() -> None:
    cave = load_scenario("S4", 0)
    rise = float(cave.mesh.bounds[1][2] - cave.start.z)
    assert _room_above(BridgeConfig(), cave).start_depth_m == pytest.approx(
        0.3 + rise + 0.5, abs=0.01
    )
    assert _room_above(BridgeConfig(start_depth_m=7.0), cave).start_depth_m == 7.0
    with pytest.raises(CavenavError, match="give --start-depth"):
        _room_above(BridgeConfig(max_depth_m=3.0), cave)


def test_steps_record_the_move_flown_and_the_move_asked(tmp_path: Path) -> None:
    """2. A move the depth limit cut is recorded as flown ('action'), with what was asked,
    how it ended and how far off in 'vehicle'; the summary counts the endings."""
    motion = ArduSubMotion(bridge(0, min_depth_m=29.5, start_depth_m=30.0))
    try:
        with autopilot(listening(motion)):
            pilot = ScriptedPilot(("ascend 1 m", "forward 0.5 m"))
            config = EpisodeConfig(max_steps=2, save_frames=False, plots=False)
            result = run_episode(corridor(), pilot, config, tmp_path / "run", motion=motion)
    finally:
        motion.close()
    first, second = read_jsonl(tmp_path / "run" / "steps.jsonl")
    assert parse_action(first["action"]).up == pytest.approx(0.5, abs=0.1)  # to 29.5 m
    assert first["vehicle"]["asked"] == "ascend 1 m" and first["vehicle"]["depth_limited"]
    assert second["vehicle"]["flown"] == "forward 0.5 m" == second["action"]
    assert all(s["vehicle"]["ended"] == "reached" for s in (first, second))
    assert result.summary["move_endings"] == {"reached": 2}
    assert result.summary["depth_limited_moves"] == 1
    assert result.summary["vehicle_start"]["ended"] == "reached"


@pytest.mark.parametrize(
    "text",
    ["forward 0.2 m", "strafe right 0.1 m", "turn right 5 deg", "forward 0.5 m, ascend 0.24 m"],
)
def test_manual_moves_land_where_they_were_meant_and_stay(text: str) -> None:
    """3. Timed sticks overshot on the SITL: 0.2 m gave 0.35-0.49 m (no braking), 5 deg
    gave 2 (the lag), a small ascent beside a forward move nothing (the dead band), and
    the pose was read while the vehicle still moved. Now each lands within the
    tolerances, and the vehicle is still where the move says it ended."""
    with flown() as (motion, sub):
        start = motion.start(Pose(0, 0, 0, 0.3))
        reached = motion.move(start, parse_action(text))
        meant = apply(start, parse_action(text))
        assert motion.last_move is not None and motion.last_move.ended == "reached"
        assert math.dist(reached.position, meant.position) <= 0.1 * math.sqrt(2) + 1e-6
        assert math.degrees(abs(wrap_angle(reached.psi - meant.psi))) <= 1.5 + 1e-6
        settled = sub.state()
        time.sleep(2.0 / SPEEDUP)  # two of the SITL's seconds later, it has not coasted on
        later = sub.state()
        assert math.dist((settled.north, settled.east), (later.north, later.east)) < 0.06


def test_guided_turns_are_finished_even_when_cut_short() -> None:
    """4. Declared done 2 deg short, the rest of a 5 deg turn was lost: the move after it
    held the heading it had reached. Every part of a step now aims at the step's goal."""
    with flown(mode="guided") as (motion, _):
        start = motion.start(Pose(0, 0, 0, 0.0))
        pose = start
        for _ in range(4):
            pose = motion.move(pose, parse_action("turn right 5 deg"))
        pose = motion.move(pose, parse_action("forward 0.5 m"))
        assert math.degrees(wrap_angle(start.psi - pose.psi)) == pytest.approx(20.0, abs=1.5)


def test_guided_moves_wait_for_a_planner_slow_to_set_off() -> None:
    """5. ArduSub's planner took over 0.7 s to start a move, and the stillness check
    ended the move before it began."""
    with flown({"guided_delay_s": 0.7 / SPEEDUP * 2}, mode="guided") as (motion, sub):
        start = motion.start(Pose(0, 0, 0, 0.0))
        reached = motion.move(start, parse_action("forward 1 m"))
        assert motion.last_move is not None and motion.last_move.ended == "reached"
        meant = apply(start, parse_action("forward 1 m"))
        assert math.dist(reached.position, meant.position) < 0.15


def test_the_vehicle_is_armed_only_once_it_reports_a_position(tmp_path: Path) -> None:
    """6. It was armed at once, then waited up to 30 s for a position (the SITL takes
    20-45 s), armed; and with the old 30 s wait some flights never began."""
    log = tmp_path / "mavlink.jsonl"
    late = {"position_after_s": 1.0}
    with flown(late, log=log, position_timeout_s=5.0, connect_timeout_s=0.5) as (motion, _):
        motion.start(Pose(0, 0, 0))
    records = read_jsonl(log)
    first_position = next(r["t"] for r in records if r.get("mavpackettype") == "LOCAL_POSITION_NED")
    arming = next(
        r["t"] for r in records
        if r["dir"] == "sent" and r.get("command") == MAV.MAV_CMD_COMPONENT_ARM_DISARM
    )  # fmt: skip
    assert first_position < arming


def test_a_guided_target_the_planner_stops_short_of_is_sent_again(tmp_path: Path) -> None:
    """A position controller can stall short of its target (here the fake sub misses each
    target by a fifth of the way); the bridge sends it again, then has the vehicle's
    stop recorded as settled rather than waiting for the cap."""
    log = tmp_path / "mavlink.jsonl"

    def targets_sent() -> int:
        return sum(
            r.get("mavpackettype") == "SET_POSITION_TARGET_LOCAL_NED" for r in read_jsonl(log)
        )

    missing = {"noise": 0.2, "seed": 1}
    with flown(missing, log=log, mode="guided", start_depth_m=30.0) as (motion, _):
        start = motion.start(Pose(0, 0, 0))
        before = targets_sent()
        motion.move(start, parse_action("forward 1 m"))
        report, sent = motion.last_move, targets_sent() - before
    assert report is not None and sent >= 2  # the first, and at least one again
    assert report.ended == "reached" or (report.ended == "settled" and sent == 3)


def test_guided_refused_while_the_position_is_not_yet_trusted_is_asked_for_again(
    tmp_path: Path,
) -> None:
    """On the SITL, ArduSub reported LOCAL_POSITION_NED seconds before it would enter
    GUIDED (its EKF did not trust the position yet): one flight in six failed there."""
    log = tmp_path / "mavlink.jsonl"
    late = {"position_after_s": 0.2, "guided_after_s": 1.5}
    with flown(late, log=log, mode="guided") as (motion, sub):
        motion.start(Pose(0, 0, 0))
        assert sub.state().mode_name == "GUIDED" and sub.state().armed
    assert any("refused" in r for r in read_jsonl(log) if r["dir"] == "note")
