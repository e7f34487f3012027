"""The fake ArduSub autopilot, flown by a bare pymavlink ground station over UDP.

Each test starts a fake sub that sends to a free local port, where a ground station listens
with ``udpin`` (as a GCS behind BlueOS does), and checks one thing ArduSub documents: what
its HEARTBEAT says, how it acknowledges commands, how the sticks, the pilot-input failsafe
and GUIDED targets move it. Rates are fast so that each test takes about a second.
"""

from __future__ import annotations

import math
import socket
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import pytest
from pymavlink import mavutil

from cavenav.errors import ConfigError
from cavenav.vehicle.fake_sub import (
    ALT_HOLD,
    GUIDED,
    MANUAL,
    NEUTRAL_STICKS,
    POSHOLD,
    STABILIZE,
    FakeSub,
    FakeSubConfig,
    FakeSubState,
    serve,
)

MAV = mavutil.mavlink
GCS_ID = 255
FAST = {
    "max_speed_mps": 4.0,
    "max_vertical_mps": 2.0,
    "max_yaw_rate_dps": 360.0,
    "guided_speed_mps": 4.0,
    "guided_yaw_rate_dps": 360.0,
    "pilot_timeout_s": 0.6,
    "telemetry_hz": 20.0,
}
# type_mask: fly to a position (velocity, acceleration and yaw rate ignored), with or
# without the yaw; or fly a velocity.
POSITION_AND_YAW = 0b1001_1111_1000
POSITION_ONLY = 0b1101_1111_1000
VELOCITY_ONLY = 0b1101_1100_0111


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def angle_between_deg(a: float, b: float) -> float:
    return abs((a - b + 180.0) % 360.0 - 180.0)


@dataclass(frozen=True)
class Link:
    """A started fake sub and the ground station that talks to it."""

    gcs: Any
    sub: FakeSub
    first_heartbeat: Any

    @property
    def system_id(self) -> int:
        return self.sub.config.system_id

    def receive(
        self, kind: str, timeout: float = 2.0, where: Callable[[Any], bool] = lambda m: True
    ) -> Any:
        """The next message of ``kind`` that satisfies ``where``, or None by the deadline."""
        deadline = time.monotonic() + timeout
        while (left := deadline - time.monotonic()) > 0.0:
            message = self.gcs.recv_match(type=kind, blocking=True, timeout=left)
            if message is not None and where(message):
                return message
        return None

    def command(self, command: int, *params: float) -> Any:
        """Send a COMMAND_LONG and return its COMMAND_ACK."""
        padded = [*params, *[0.0] * (7 - len(params))]
        self.gcs.mav.command_long_send(self.system_id, 1, command, 0, *padded)
        ack = self.receive("COMMAND_ACK", where=lambda m: m.command == command)
        assert ack is not None, f"no COMMAND_ACK for command {command}"
        return ack

    def set_mode(self, mode: int) -> Any:
        """Send a SET_MODE message and return its COMMAND_ACK (command = message id 11)."""
        self.gcs.mav.set_mode_send(self.system_id, MAV.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, mode)
        ack = self.receive("COMMAND_ACK", where=lambda m: m.command == MAV.MAVLINK_MSG_ID_SET_MODE)
        assert ack is not None, "no COMMAND_ACK for SET_MODE"
        return ack

    def heartbeat_now(self) -> Any:
        """Ask for a HEARTBEAT (MAV_CMD_REQUEST_MESSAGE) instead of waiting up to a second,
        and return the first that comes; the COMMAND_ACK follows it."""
        request = MAV.MAV_CMD_REQUEST_MESSAGE
        self.gcs.mav.command_long_send(self.system_id, 1, request, 0, 0, 0, 0, 0, 0, 0, 0)
        heartbeat = self.receive("HEARTBEAT")
        ack = self.receive("COMMAND_ACK", where=lambda m: m.command == request)
        assert ack is not None and ack.result == MAV.MAV_RESULT_ACCEPTED
        return heartbeat

    def arm(self) -> None:
        ack = self.command(MAV.MAV_CMD_COMPONENT_ARM_DISARM, 1)
        assert ack.result == MAV.MAV_RESULT_ACCEPTED

    def sticks(self, x: int = 0, y: int = 0, z: int = 500, r: int = 0, target: int = 0) -> None:
        self.gcs.mav.manual_control_send(target or self.system_id, x, y, z, r, 0)

    def hold_sticks(
        self, seconds: float, x: int = 0, y: int = 0, z: int = 500, r: int = 0
    ) -> float:
        """Send the sticks at 20 Hz for ``seconds``, then neutral, as a bridge would; returns
        how long they were in effect."""
        start = time.monotonic()
        while time.monotonic() - start < seconds:
            self.sticks(x, y, z, r)
            time.sleep(0.05)
        self.sticks()
        held = time.monotonic() - start
        wait_until(self.sub, lambda s: s.sticks == NEUTRAL_STICKS)
        return held

    def target(self, frame: int, mask: int, x: float, y: float, z: float, yaw: float = 0.0):
        self.gcs.mav.set_position_target_local_ned_send(
            0, self.system_id, 1, frame, mask, x, y, z, x, y, z, 0, 0, 0, yaw, 0.0
        )


def wait_until(
    sub: FakeSub, condition: Callable[[FakeSubState], bool], timeout: float = 2.0
) -> FakeSubState:
    """Poll the fake sub's state until ``condition`` holds; fail with the last state."""
    deadline = time.monotonic() + timeout
    while True:
        state = sub.state()
        if condition(state):
            return state
        assert time.monotonic() < deadline, f"condition never held; last state {state}"
        time.sleep(0.01)


def holds_throughout(sub: FakeSub, condition: Callable[[FakeSubState], bool], seconds: float):
    """True if ``condition`` holds at every poll for ``seconds``."""
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        if not condition(sub.state()):
            return False
        time.sleep(0.01)
    return True


@pytest.fixture
def launch() -> Iterator[Callable[..., Link]]:
    """Start fake subs (FAST, plus overrides) each with its own ground station; all are
    stopped afterwards, so no thread outlives its test."""
    links: list[Link] = []

    def start(**overrides: Any) -> Link:
        port = free_udp_port()
        gcs = mavutil.mavlink_connection(
            f"udpin:127.0.0.1:{port}", source_system=GCS_ID, source_component=190
        )
        sub = FakeSub(FakeSubConfig(address=f"udpout:127.0.0.1:{port}", **{**FAST, **overrides}))
        links.append(Link(gcs, sub, None))
        sub.start()
        heartbeat = gcs.wait_heartbeat(timeout=2.0)
        assert heartbeat is not None, "the fake sub sent no HEARTBEAT"
        return Link(gcs, sub, heartbeat)

    yield start
    for link in links:
        link.sub.stop()
        link.gcs.close()


def test_the_heartbeat_shows_a_submarine_its_mode_and_whether_it_is_armed(launch) -> None:
    link = launch(system_id=7, pilot_failsafe="off")
    first = link.first_heartbeat
    assert (first.get_srcSystem(), first.get_srcComponent()) == (7, 1)
    assert first.type == MAV.MAV_TYPE_SUBMARINE
    assert first.autopilot == MAV.MAV_AUTOPILOT_ARDUPILOTMEGA
    assert first.custom_mode == MANUAL  # ArduSub boots in MANUAL
    assert first.base_mode & MAV.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    assert not first.base_mode & MAV.MAV_MODE_FLAG_SAFETY_ARMED
    assert first.system_status == MAV.MAV_STATE_STANDBY

    link.arm()
    armed = link.heartbeat_now()
    assert armed.base_mode & MAV.MAV_MODE_FLAG_SAFETY_ARMED
    assert armed.system_status == MAV.MAV_STATE_ACTIVE


def test_arming_and_disarming_are_acknowledged_and_take_effect(launch) -> None:
    link = launch(pilot_failsafe="off")
    assert link.command(MAV.MAV_CMD_COMPONENT_ARM_DISARM, 1).result == MAV.MAV_RESULT_ACCEPTED
    assert link.sub.state().armed

    link.gcs.mav.command_int_send(
        link.system_id, 1, 0, MAV.MAV_CMD_COMPONENT_ARM_DISARM, 0, 0, 0, 0, 0, 0, 0, 0, 0
    )
    ack = link.receive("COMMAND_ACK", where=lambda m: m.command == MAV.MAV_CMD_COMPONENT_ARM_DISARM)
    assert ack.result == MAV.MAV_RESULT_ACCEPTED
    assert not link.sub.state().armed

    # ArduPilot accepts a disarm when already disarmed, and knows only 0 and 1.
    assert link.command(MAV.MAV_CMD_COMPONENT_ARM_DISARM, 0).result == MAV.MAV_RESULT_ACCEPTED
    assert link.command(MAV.MAV_CMD_COMPONENT_ARM_DISARM, 2).result == MAV.MAV_RESULT_UNSUPPORTED
    assert not link.sub.state().armed


def test_the_mode_changes_by_set_mode_and_by_do_set_mode(launch) -> None:
    link = launch(pilot_failsafe="off")
    assert link.set_mode(ALT_HOLD).result == MAV.MAV_RESULT_ACCEPTED
    assert (link.sub.state().mode, link.sub.state().mode_name) == (ALT_HOLD, "ALT_HOLD")

    link.gcs.set_mode("STABILIZE")  # pymavlink sends MAV_CMD_DO_SET_MODE
    ack = link.receive("COMMAND_ACK", where=lambda m: m.command == MAV.MAV_CMD_DO_SET_MODE)
    assert ack.result == MAV.MAV_RESULT_ACCEPTED
    assert link.sub.state().mode_name == "STABILIZE"
    assert link.heartbeat_now().custom_mode == STABILIZE

    flag = MAV.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    link.gcs.mav.command_long_send(
        link.system_id, 1, MAV.MAV_CMD_DO_SET_MODE, 0, flag, 5, 0, 0, 0, 0, 0
    )
    assert link.receive("STATUSTEXT", where=lambda m: m.text == "No such mode 5") is not None
    ack = link.receive("COMMAND_ACK", where=lambda m: m.command == MAV.MAV_CMD_DO_SET_MODE)
    assert ack.result == MAV.MAV_RESULT_FAILED
    assert link.command(MAV.MAV_CMD_DO_SET_MODE, 0, MANUAL).result == MAV.MAV_RESULT_DENIED
    assert link.sub.state().mode == STABILIZE


def test_without_a_position_estimate_there_is_no_guided_and_no_local_position(launch) -> None:
    link = launch(position_estimate=False, pilot_failsafe="off")
    assert link.set_mode(GUIDED).result == MAV.MAV_RESULT_FAILED
    flag = MAV.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    assert link.command(MAV.MAV_CMD_DO_SET_MODE, flag, POSHOLD).result == MAV.MAV_RESULT_FAILED
    assert link.sub.state().mode == MANUAL

    seen = set()
    deadline = time.monotonic() + 0.5
    while (left := deadline - time.monotonic()) > 0.0:
        message = link.gcs.recv_match(blocking=True, timeout=left)
        if message is not None:
            seen.add(message.get_type())
    assert "ATTITUDE" in seen
    assert "LOCAL_POSITION_NED" not in seen


def test_telemetry_reports_the_pose_at_the_telemetry_rate(launch) -> None:
    link = launch(start_ned=(1.0, -2.0, 3.0), start_yaw_deg=-90.0, pilot_failsafe="off")
    position = link.receive("LOCAL_POSITION_NED")
    assert (position.x, position.y, position.z) == pytest.approx((1.0, -2.0, 3.0))
    assert (position.vx, position.vy, position.vz) == (0.0, 0.0, 0.0)
    assert link.receive("ATTITUDE").yaw == pytest.approx(-math.pi / 2)

    count = 0
    deadline = time.monotonic() + 0.5
    while link.receive("ATTITUDE", timeout=deadline - time.monotonic()) is not None:
        count += 1
    assert 6 <= count <= 14  # 20 Hz for 0.5 s


def test_the_forward_stick_flies_along_the_heading(launch) -> None:
    link = launch()
    link.sticks()
    link.arm()
    start = link.sub.state()

    held = link.hold_sticks(0.5, x=500)  # half stick: 2 m/s
    ahead = link.sub.state()
    assert ahead.north - start.north == pytest.approx(2.0 * held, rel=0.15)
    assert ahead.east == pytest.approx(start.east, abs=0.02)
    assert ahead.down == start.down

    link.hold_sticks(0.5, r=500)  # half yaw stick: 180 deg/s clockwise, toward east
    turned = link.sub.state()
    assert 60.0 < turned.yaw_deg < 120.0

    held = link.hold_sticks(0.5, x=500)
    after = link.sub.state()
    north, east = after.north - turned.north, after.east - turned.east
    assert math.hypot(north, east) == pytest.approx(2.0 * held, rel=0.15)
    assert angle_between_deg(math.degrees(math.atan2(east, north)), after.yaw_deg) < 1.0
    assert east > 0.9 * math.hypot(north, east)


def test_sticks_from_another_system_or_aimed_elsewhere_are_ignored(launch) -> None:
    link = launch(pilot_failsafe="off")
    link.arm()
    link.gcs.mav.srcSystem = 200  # not SYSID_MYGCS
    for _ in range(5):
        link.sticks(x=1000)
    link.gcs.mav.srcSystem = GCS_ID
    for _ in range(5):
        link.sticks(x=1000, target=link.system_id + 1)
    link.sticks(y=-250)  # the one that counts, and arrives after the others

    state = wait_until(link.sub, lambda s: s.manual_controls > 0)
    assert state.manual_controls == 1
    assert state.sticks == (0, -250, 500, 0)
    assert state.north == pytest.approx(0.0, abs=0.05)


def test_lost_pilot_input_neutralises_the_sticks_and_disarms_once(launch) -> None:
    link = launch(pilot_failsafe="disarm")
    link.sticks(x=300)
    last_input = time.monotonic()
    link.arm()
    assert link.sub.state().sticks == (300, 0, 500, 0)

    state = wait_until(link.sub, lambda s: not s.armed)
    assert time.monotonic() - last_input >= 0.55  # FS_PILOT_TIMEOUT 0.6 s, less one tick
    assert state.sticks == NEUTRAL_STICKS
    assert state.failsafe
    text = link.receive("STATUSTEXT", where=lambda m: m.text == "Lost manual control")
    assert text is not None and text.severity == MAV.MAV_SEVERITY_CRITICAL

    link.arm()  # the failsafe acts once per loss: re-armed, it stays armed
    assert holds_throughout(link.sub, lambda s: s.armed, 0.3)
    link.sticks()
    assert not wait_until(link.sub, lambda s: not s.failsafe).failsafe


def test_a_warning_failsafe_only_neutralises_the_sticks(launch) -> None:
    link = launch(pilot_failsafe="warn")
    link.sticks(x=300)
    link.arm()

    state = wait_until(link.sub, lambda s: s.failsafe)
    assert state.armed
    assert state.sticks == NEUTRAL_STICKS
    heartbeat = link.heartbeat_now()
    assert heartbeat.system_status == MAV.MAV_STATE_CRITICAL  # as ArduSub in any failsafe
    assert heartbeat.base_mode & MAV.MAV_MODE_FLAG_SAFETY_ARMED


def test_with_the_failsafe_off_the_last_sticks_stay_in_effect(launch) -> None:
    link = launch(pilot_failsafe="off")
    link.sticks(x=300, r=-100)
    link.arm()
    assert holds_throughout(link.sub, lambda s: s.sticks == (300, 0, 500, -100), 0.8)
    assert link.sub.state().armed


def test_a_body_offset_target_with_a_relative_yaw_is_reached_in_body_axes(launch) -> None:
    link = launch(start_yaw_deg=90.0, pilot_failsafe="off")  # heading east
    assert link.set_mode(GUIDED).result == MAV.MAV_RESULT_ACCEPTED
    link.arm()
    # 2 m forward (east), 1 m right (south), 0.5 m down, and a quarter turn clockwise.
    link.target(MAV.MAV_FRAME_BODY_OFFSET_NED, POSITION_AND_YAW, 2.0, 1.0, 0.5, math.pi / 2)

    pending = wait_until(link.sub, lambda s: s.guided_target is not None)
    assert pending.guided_target == pytest.approx((-1.0, 2.0, 5.5, -180.0))
    assert pending.position_targets == 1
    reached = wait_until(link.sub, lambda s: s.guided_target is None)
    assert (reached.north, reached.east, reached.down) == pytest.approx((-1.0, 2.0, 5.5))
    assert angle_between_deg(reached.yaw_deg, 180.0) < 1e-4  # MAVLink's yaw is a float32


def test_a_target_without_a_yaw_keeps_the_heading_and_counts_only_in_guided(launch) -> None:
    link = launch(start_yaw_deg=30.0, pilot_failsafe="off")
    link.arm()
    link.target(MAV.MAV_FRAME_LOCAL_NED, POSITION_ONLY, 1.0, -1.0, 4.0)  # in MANUAL: ignored
    assert link.set_mode(GUIDED).result == MAV.MAV_RESULT_ACCEPTED  # handled after the target
    assert link.sub.state().position_targets == 0

    link.target(MAV.MAV_FRAME_LOCAL_NED, POSITION_ONLY, 1.0, -1.0, 4.0, yaw=2.0)
    wait_until(link.sub, lambda s: s.position_targets == 1)
    reached = wait_until(link.sub, lambda s: s.guided_target is None)
    assert (reached.north, reached.east, reached.down) == pytest.approx((1.0, -1.0, 4.0))
    assert reached.yaw_deg == pytest.approx(30.0)


def test_a_target_sent_while_disarmed_is_dropped(launch) -> None:
    link = launch(pilot_failsafe="off")
    assert link.set_mode(GUIDED).result == MAV.MAV_RESULT_ACCEPTED
    link.target(MAV.MAV_FRAME_LOCAL_OFFSET_NED, POSITION_ONLY, 1.0, 0.0, 0.0)
    # ArduSub resets its waypoint controller while disarmed: the target is forgotten.
    dropped = wait_until(link.sub, lambda s: s.position_targets == 1 and s.guided_target is None)
    link.arm()
    assert holds_throughout(link.sub, lambda s: s.north == dropped.north == 0.0, 0.2)


def test_a_body_velocity_target_flies_along_the_heading(launch) -> None:
    link = launch(start_yaw_deg=90.0, pilot_failsafe="off")
    link.set_mode(GUIDED)
    link.arm()
    link.gcs.mav.set_position_target_local_ned_send(
        0,
        link.system_id,
        1,
        MAV.MAV_FRAME_BODY_NED,
        VELOCITY_ONLY,
        0,
        0,
        0,
        2.0,
        0,
        0,
        0,
        0,
        0,
        0,
        0,
    )
    moved = wait_until(link.sub, lambda s: s.east > 0.4)
    assert moved.north == pytest.approx(0.0, abs=1e-9)
    assert moved.guided_target is None  # a velocity has no target to reach


def test_a_current_drifts_the_vehicle_unless_a_controller_holds_against_it(launch) -> None:
    link = launch(current_ned_mps=(1.0, 0.5, 0.4), pilot_failsafe="off")
    assert link.set_mode(ALT_HOLD).result == MAV.MAV_RESULT_ACCEPTED
    link.arm()
    before, since = link.sub.state(), time.monotonic()
    time.sleep(0.4)
    after, elapsed = link.sub.state(), time.monotonic() - since
    assert after.north - before.north == pytest.approx(1.0 * elapsed, abs=0.1)
    assert after.east - before.east == pytest.approx(0.5 * elapsed, abs=0.05)
    assert after.down == before.down  # ALT_HOLD holds the depth

    assert link.set_mode(GUIDED).result == MAV.MAV_RESULT_ACCEPTED
    link.target(MAV.MAV_FRAME_LOCAL_OFFSET_NED, POSITION_ONLY, 0.5, 0.0, 0.0)
    reached = wait_until(link.sub, lambda s: s.position_targets == 1 and s.guided_target is None)
    assert holds_throughout(link.sub, lambda s: s == reached, 0.3)

    assert link.set_mode(MANUAL).result == MAV.MAV_RESULT_ACCEPTED
    deeper = wait_until(link.sub, lambda s: s.down > reached.down + 0.04)  # 0.4 m/s down
    assert deeper.north > reached.north

    assert link.set_mode(POSHOLD).result == MAV.MAV_RESULT_ACCEPTED
    held = link.sub.state()
    assert holds_throughout(link.sub, lambda s: s == held, 0.2)


def test_noise_misses_a_guided_target_by_a_bounded_amount_repeatable_by_seed(launch) -> None:
    links = [launch(noise=0.1, seed=3, pilot_failsafe="off") for _ in range(2)]
    for link in links:
        link.set_mode(GUIDED)
        link.arm()
        link.target(MAV.MAV_FRAME_BODY_OFFSET_NED, POSITION_ONLY, 2.0, 0.0, 0.0)
    ends = [
        wait_until(link.sub, lambda s: s.position_targets == 1 and s.guided_target is None)
        for link in links
    ]
    misses = [(s.north - 2.0, s.east, s.down - 5.0) for s in ends]
    assert misses[0] == pytest.approx(misses[1], abs=1e-9)
    assert 1e-4 < math.dist(misses[0], (0.0, 0.0, 0.0)) < 5 * 0.1 * 2.0 * math.sqrt(3)


def test_stop_returns_promptly_and_leaves_no_thread(launch) -> None:
    link = launch()
    started = time.monotonic()
    link.sub.stop()
    assert time.monotonic() - started < 0.5
    assert not [t for t in threading.enumerate() if t.name == "fake-sub"]
    link.sub.stop()  # again: nothing happens


def test_a_paused_heartbeat_leaves_the_telemetry_running(launch) -> None:
    link = launch(pilot_failsafe="off")
    link.sub.pause_heartbeat(True)
    while link.gcs.recv_match(blocking=False) is not None:  # what was sent before the pause
        pass
    kinds = set()
    deadline = time.monotonic() + 1.2
    while (left := deadline - time.monotonic()) > 0.0:
        message = link.gcs.recv_match(blocking=True, timeout=left)
        if message is not None:
            kinds.add(message.get_type())
    assert "ATTITUDE" in kinds
    assert "HEARTBEAT" not in kinds
    link.sub.pause_heartbeat(False)
    assert link.receive("HEARTBEAT", timeout=1.2) is not None


def test_serve_reports_the_state_until_stopped() -> None:
    config = FakeSubConfig(address=f"udpout:127.0.0.1:{free_udp_port()}", **FAST)
    stop, states = threading.Event(), []
    server = threading.Thread(target=serve, args=(config, stop, states.append, 0.05))
    server.start()
    try:
        deadline = time.monotonic() + 2.0
        while len(states) < 2 and time.monotonic() < deadline:
            time.sleep(0.01)
    finally:
        stop.set()
        server.join(timeout=1.0)
    assert not server.is_alive()
    assert len(states) >= 2 and states[0].mode == MANUAL and not states[0].armed


@pytest.mark.parametrize(
    "bad",
    [
        {"max_speed_mps": 0.0},
        {"guided_yaw_rate_dps": -1.0},
        {"physics_hz": math.inf},
        {"noise": -0.1},
        {"noise": math.nan},
        {"pilot_failsafe": "surface"},
        {"current_ned_mps": (0.0, 0.0)},
        {"start_ned": (0.0, math.nan, 5.0)},
        {"system_id": 0},
        {"gcs_system_id": 256},
        {"address": ""},
    ],
)
def test_a_bad_config_value_is_a_config_error(bad: dict[str, Any]) -> None:
    with pytest.raises(ConfigError):
        FakeSubConfig(**bad)


def test_a_config_takes_vectors_as_lists() -> None:
    assert FakeSubConfig(start_ned=[1, 2, 3]).start_ned == (1.0, 2.0, 3.0)
