"""The fake ArduSub autopilot, flown by a bare pymavlink ground station over UDP.

Each test starts a fake sub that sends to a free local port, where a ground station listens
with ``udpin`` (as a GCS behind BlueOS does), and checks one thing ArduSub documents: what
its HEARTBEAT says, how it acknowledges commands, how the sticks, the pilot-input failsafe
and GUIDED targets move it. Speeds, rates and timeouts are checked against the velocities
it reports and the time it reports (``time_boot_ms``), not the test's clock, so that a
loaded machine does not fail them: the test's clock only bounds how long a test waits.
"""

from __future__ import annotations

import itertools
import math
import re
import socket
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import pytest
from pymavlink import mavutil

from cavenav.core.errors import ConfigError
from cavenav.vehicle.fake_sub import (
    ALT_HOLD,
    GUIDED,
    MANUAL,
    NEUTRAL_STICKS,
    STABILIZE,
    FakeSub,
    FakeSubConfig,
    FakeSubState,
    serve,
)
from cavenav.vehicle.frames import body_to_ned
from tests.conftest import cavenav

MAV = mavutil.mavlink
GCS_ID = 255
ARMED = MAV.MAV_MODE_FLAG_SAFETY_ARMED
FAST = {
    "max_speed_mps": 4.0,
    "max_vertical_mps": 2.0,
    "max_yaw_rate_dps": 360.0,
    "guided_speed_mps": 4.0,
    "guided_yaw_rate_dps": 360.0,
    "pilot_timeout_s": 0.6,
    "telemetry_hz": 20.0,
    "start_ned": (0.0, 0.0, 5.0),  # the depths below are reckoned from 5 m
}
# The tests of what the fake sub does with each message fly it kinematic: velocities and
# turn rates reached at once, no dead bands, no buoyancy, GUIDED setting off at once. What
# it learned from ArduSub's SITL (inertia, coasting, the dead bands, buoyancy, the late
# position) has its own tests below, at the defaults.
KINEMATIC = {
    "inertia": False,
    "stick_dead_band": 0,
    "throttle_dead_band": 0,
    "buoyant_rise_mps": 0.0,
    "guided_delay_s": 0.0,
    "guided_approach_per_s": 1e6,
}
FAST |= KINEMATIC
# type_mask: fly to a position (velocity, acceleration and yaw rate ignored), with or
# without the yaw.
POSITION_AND_YAW = 0b1001_1111_1000
POSITION_ONLY = 0b1101_1111_1000


def angle_between_deg(a: float, b: float) -> float:
    return abs((a - b + 180.0) % 360.0 - 180.0)


def velocity(message: Any) -> tuple[float, float, float]:
    return message.vx, message.vy, message.vz


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
        self, kind: str, timeout: float = 3.0, where: Callable[[Any], bool] = lambda m: True
    ) -> Any:
        """The next message of ``kind`` that satisfies ``where``, or None by the deadline."""
        deadline = time.monotonic() + timeout
        while (left := deadline - time.monotonic()) > 0.0:
            message = self.gcs.recv_match(type=kind, blocking=True, timeout=left)
            if message is not None and where(message):
                return message
        return None

    def gather(self, enough: Callable[[list[Any]], bool], timeout: float = 10.0) -> list[Any]:
        """Every message that arrives, in order, until ``enough`` holds of them; fails if
        it does not within ``timeout`` (a generous wait, not a claim about speed)."""
        messages: list[Any] = []
        deadline = time.monotonic() + timeout
        while not enough(messages):
            left = deadline - time.monotonic()
            assert left > 0.0, f"not enough after {timeout} s: {len(messages)} messages"
            message = self.gcs.recv_match(blocking=True, timeout=left)
            if message is not None and message.get_type() != "BAD_DATA":
                messages.append(message)
        return messages

    def stream_for(self, kind: str, ms: int) -> list[Any]:
        """Every message that arrives until messages of ``kind`` span ``ms`` milliseconds
        of the fake sub's own clock (``time_boot_ms``), from the first one after now."""

        def spanned(messages: list[Any]) -> bool:
            times = [m.time_boot_ms for m in messages if m.get_type() == kind]
            return bool(times) and times[-1] - times[0] >= ms

        return self.gather(spanned)

    def command(self, command: int, *params: float, text: str | None = None) -> Any:
        """Send a COMMAND_LONG and return its COMMAND_ACK, after the STATUSTEXT ``text``
        (ArduSub sends the warning before the acknowledgement) if there is one."""
        padded = [*params, *[0.0] * (7 - len(params))]
        self.gcs.mav.command_long_send(self.system_id, 1, command, 0, *padded)
        return self._ack(command, text)

    def set_mode(self, mode: int, text: str | None = None) -> Any:
        """Send a SET_MODE message and return its COMMAND_ACK (command = message id 11)."""
        self.gcs.mav.set_mode_send(self.system_id, MAV.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, mode)
        return self._ack(MAV.MAVLINK_MSG_ID_SET_MODE, text)

    def _ack(self, command: int, text: str | None) -> Any:
        if text is not None:
            assert self.receive("STATUSTEXT", where=lambda m: m.text == text), f"no {text!r}"
        ack = self.receive("COMMAND_ACK", where=lambda m: m.command == command)
        assert ack is not None, f"no COMMAND_ACK for command {command}"
        return ack

    def heartbeat(self, where: Callable[[Any], bool]) -> Any:
        """The next HEARTBEAT (1 Hz) that satisfies ``where``; fails if none comes."""
        heartbeat = self.receive("HEARTBEAT", where=where)
        assert heartbeat is not None, "no such HEARTBEAT"
        return heartbeat

    def arm(self) -> None:
        ack = self.command(MAV.MAV_CMD_COMPONENT_ARM_DISARM, 1)
        assert ack.result == MAV.MAV_RESULT_ACCEPTED

    def sticks(self, x: int = 0, y: int = 0, z: int = 500, r: int = 0, target: int = 0) -> None:
        self.gcs.mav.manual_control_send(target or self.system_id, x, y, z, r, 0)

    def hold_sticks_until(self, kind: str, where: Callable[[Any], bool], **sticks: int) -> Any:
        """Send the sticks at 20 Hz, as a bridge would, until a message of ``kind`` that
        satisfies ``where`` comes; then neutral sticks. Fails if none comes in 5 s."""
        deadline = time.monotonic() + 5.0
        message = None
        while message is None and time.monotonic() < deadline:
            self.sticks(**sticks)
            message = self.receive(kind, timeout=0.05, where=where)
        self.sticks()
        assert message is not None, f"no {kind} as expected while holding {sticks}"
        wait_until(self.sub, lambda s: s.sticks == NEUTRAL_STICKS)
        return message

    def target(self, frame: int, mask: int, x: float, y: float, z: float, yaw: float = 0.0):
        self.gcs.mav.set_position_target_local_ned_send(
            0, self.system_id, 1, frame, mask, x, y, z, x, y, z, 0, 0, 0, yaw, 0.0
        )


def wait_until(
    sub: FakeSub, condition: Callable[[FakeSubState], bool], timeout: float = 5.0
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


def at(state: FakeSubState, north: float, east: float, down: float, yaw_deg: float) -> bool:
    """``state`` is at the pose (to float32 precision, as MAVLink carries targets)."""
    close = math.dist((state.north, state.east, state.down), (north, east, down)) < 1e-5
    return close and angle_between_deg(state.yaw_deg, yaw_deg) < 1e-4


@pytest.fixture
def launch() -> Iterator[Callable[..., Link]]:
    """Start fake subs (FAST, plus overrides) each with its own ground station; all are
    stopped afterwards, so no thread outlives its test."""
    links: list[Link] = []

    def start(**overrides: Any) -> Link:
        gcs = mavutil.mavlink_connection(  # on a port the system picks, read back
            "udpin:127.0.0.1:0", source_system=GCS_ID, source_component=190
        )
        port = gcs.port.getsockname()[1]
        sub = FakeSub(FakeSubConfig(address=f"udpout:127.0.0.1:{port}", **{**FAST, **overrides}))
        links.append(Link(gcs, sub, None))
        sub.start()
        heartbeat = gcs.wait_heartbeat(timeout=3.0)
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
    assert not first.base_mode & (ARMED | MAV.MAV_MODE_FLAG_GUIDED_ENABLED)
    assert first.system_status == MAV.MAV_STATE_STANDBY

    link.arm()
    assert link.set_mode(GUIDED).result == MAV.MAV_RESULT_ACCEPTED
    armed = link.heartbeat(lambda m: m.base_mode & ARMED)
    assert armed.system_status == MAV.MAV_STATE_ACTIVE
    assert armed.custom_mode == GUIDED
    assert armed.base_mode & MAV.MAV_MODE_FLAG_GUIDED_ENABLED


def test_arming_and_disarming_are_acknowledged_and_take_effect(launch) -> None:
    link = launch(pilot_failsafe="off")
    assert link.command(MAV.MAV_CMD_COMPONENT_ARM_DISARM, 1).result == MAV.MAV_RESULT_ACCEPTED
    assert link.sub.state().armed
    assert link.command(MAV.MAV_CMD_COMPONENT_ARM_DISARM, 0).result == MAV.MAV_RESULT_ACCEPTED
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
    assert link.heartbeat(lambda m: m.custom_mode == STABILIZE)

    flag = MAV.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    for unknown in (5, 16):  # no mode 5; POSHOLD (16) is not emulated
        text = f"No such mode {unknown}"
        ack = link.command(MAV.MAV_CMD_DO_SET_MODE, flag, unknown, text=text)
        assert ack.result == MAV.MAV_RESULT_FAILED
    assert link.command(MAV.MAV_CMD_DO_SET_MODE, 0, MANUAL).result == MAV.MAV_RESULT_DENIED
    assert link.sub.state().mode == STABILIZE


def test_without_a_position_estimate_there_is_no_guided_and_no_local_position(launch) -> None:
    link = launch(position_estimate=False, pilot_failsafe="off")
    text = "Mode change failed: GUIDED requires position"
    assert link.set_mode(GUIDED, text=text).result == MAV.MAV_RESULT_FAILED
    assert link.sub.state().mode == MANUAL

    # Half a second of its own clock (10 ATTITUDE at 20 Hz), and no position among them.
    seen = {m.get_type() for m in link.stream_for("ATTITUDE", 500)}
    assert "LOCAL_POSITION_NED" not in seen


def test_telemetry_reports_the_pose_at_the_requested_rates(launch) -> None:
    link = launch(start_ned=(1.0, -2.0, 3.0), start_yaw_deg=-90.0, pilot_failsafe="off")
    position = link.receive("LOCAL_POSITION_NED")
    assert (position.x, position.y, position.z) == pytest.approx((1.0, -2.0, 3.0))
    assert velocity(position) == (0.0, 0.0, 0.0)
    assert link.receive("ATTITUDE").yaw == pytest.approx(-math.pi / 2)

    # LOCAL_POSITION_NED asked faster than the physics goes out at every physics step:
    # its time_boot_ms marks each step of the fake's own clock.
    interval = MAV.MAV_CMD_SET_MESSAGE_INTERVAL
    ack = link.command(interval, MAV.MAVLINK_MSG_ID_LOCAL_POSITION_NED, 1_000)
    assert ack.result == MAV.MAV_RESULT_ACCEPTED
    assert_streamed_every(link, "ATTITUDE", 50)  # 20 Hz by default
    ack = link.command(interval, MAV.MAVLINK_MSG_ID_ATTITUDE, 250_000)  # 4 Hz
    assert ack.result == MAV.MAV_RESULT_ACCEPTED
    assert_streamed_every(link, "ATTITUDE", 250)

    ack = link.command(interval, MAV.MAVLINK_MSG_ID_LOCAL_POSITION_NED, -1)  # stop it
    assert ack.result == MAV.MAV_RESULT_ACCEPTED
    # What arrives after the acknowledgement was sent after it: 0.5 s of ATTITUDE, no position.
    seen = {m.get_type() for m in link.stream_for("ATTITUDE", 500)}
    assert "LOCAL_POSITION_NED" not in seen


def assert_streamed_every(link: Link, kind: str, period_ms: int, count: int = 6) -> None:
    """``count`` messages of ``kind`` went out every ``period_ms`` of the fake sub's clock,
    as ArduSub streams them: never sooner than the interval, and at the first physics step
    on which one is due (told by LOCAL_POSITION_NED, which goes out at every step).

    One sent late by a late step is followed by the next on time, less than a period after
    it, so "never sooner" is over the whole run: n messages span more than n - 2 periods.
    Times are whole milliseconds, hence 1 ms of slack.
    """
    messages = link.gather(lambda got: sum(m.get_type() == kind for m in got) >= count)
    sent = [m.time_boot_ms for m in messages if m.get_type() == kind]
    steps = [m.time_boot_ms for m in messages if m.get_type() == "LOCAL_POSITION_NED"]
    assert sent[-1] - sent[0] >= (count - 2) * period_ms - 1, f"too soon: {sent}"
    for before, after in itertools.pairwise(sent):
        skipped = [t for t in steps if before + period_ms + 1 < t < after]
        assert not skipped, f"{kind} due at {before + period_ms} ms, sent at {after} ms"


def test_the_sticks_fly_along_the_heading_at_their_speeds(launch) -> None:
    link = launch()
    link.sticks()
    link.arm()

    # Half forward stick: 2 m/s north, reported and integrated over the fake's own time.
    moving: list[Any] = []

    def moved_for_300_ms(message: Any) -> bool:
        if message.vx > 0.0:
            moving.append(message)
        return bool(moving) and message.time_boot_ms >= moving[0].time_boot_ms + 300

    later = link.hold_sticks_until("LOCAL_POSITION_NED", moved_for_300_ms, x=500)
    first = moving[0]
    assert all(velocity(m) == pytest.approx((2.0, 0.0, 0.0)) for m in moving)
    elapsed = (later.time_boot_ms - first.time_boot_ms) / 1000.0
    assert (later.x - first.x) / elapsed == pytest.approx(2.0, rel=0.02)
    assert (later.y, later.z) == pytest.approx((first.y, first.z))

    # Half yaw stick: 180 deg/s clockwise, toward east.
    turning = link.hold_sticks_until("ATTITUDE", lambda m: m.yawspeed > 0.0, r=500)
    assert turning.yawspeed == pytest.approx(math.pi)
    link.hold_sticks_until("ATTITUDE", lambda m: m.yaw > math.radians(60.0), r=500)
    heading = link.sub.state().yaw_deg
    assert 60.0 < heading < 180.0

    # Forward and right now go along and across the heading, throttle up goes up.
    across = link.hold_sticks_until(
        "LOCAL_POSITION_NED", lambda m: m.vx != 0.0 or m.vy != 0.0, x=500, y=250, z=750
    )
    expected = body_to_ned(2.0, 1.0, math.radians(heading))
    assert velocity(across) == pytest.approx((*expected, -1.0), abs=1e-5)


def test_sticks_from_another_system_or_aimed_elsewhere_are_ignored(launch) -> None:
    link = launch(pilot_failsafe="off")
    link.gcs.mav.srcSystem = 200  # not SYSID_MYGCS
    link.sticks(x=1000)
    link.gcs.mav.srcSystem = GCS_ID
    link.sticks(x=1000, target=link.system_id + 1)
    link.arm()  # acknowledged after the sticks above were handled
    assert link.sub.state().sticks == NEUTRAL_STICKS

    link.sticks(y=-250)
    assert wait_until(link.sub, lambda s: s.sticks == (0, -250, 500, 0))


def test_lost_pilot_input_neutralises_the_sticks_and_disarms_once(launch) -> None:
    link = launch(pilot_failsafe="disarm")
    link.sticks()
    link.arm()
    every_step = link.command(
        MAV.MAV_CMD_SET_MESSAGE_INTERVAL, MAV.MAVLINK_MSG_ID_LOCAL_POSITION_NED, 1_000
    )
    assert every_step.result == MAV.MAV_RESULT_ACCEPTED
    still = link.receive("LOCAL_POSITION_NED")  # measured before the last input was sent
    link.sticks(x=300)  # the last pilot input: 1.2 m/s forward, then nothing

    def stopped_after_moving(messages: list[Any]) -> bool:
        track = [m.vx for m in messages if m.get_type() == "LOCAL_POSITION_NED"]
        moved = next((i for i, vx in enumerate(track) if vx > 0.0), len(track))
        return 0.0 in track[moved:]

    messages = link.gather(stopped_after_moving)
    track = [m for m in messages if m.get_type() == "LOCAL_POSITION_NED"]
    moving = [m for m in track if m.vx > 0.0]
    assert all(velocity(m) == pytest.approx((1.2, 0.0, 0.0)) for m in moving)
    stopped = next(m for m in track if m.time_boot_ms > moving[0].time_boot_ms and m.vx == 0.0)
    # FS_PILOT_TIMEOUT (0.6 s) on the fake sub's clock: the sticks stayed in effect until
    # 600 ms after the input came (which was after `still`, and before the first step
    # moving on them), and no longer.
    assert stopped.time_boot_ms - still.time_boot_ms >= 600
    assert moving[-1].time_boot_ms <= moving[0].time_boot_ms + 600 + 1
    assert velocity(stopped) == (0.0, 0.0, 0.0)
    text = next(m for m in messages if m.get_type() == "STATUSTEXT")
    assert (text.text, text.severity) == ("Lost manual control", MAV.MAV_SEVERITY_CRITICAL)
    state = link.sub.state()
    assert (state.armed, state.sticks, state.failsafe) == (False, NEUTRAL_STICKS, True)

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
    # ArduSub reports CRITICAL in any failsafe.
    heartbeat = link.heartbeat(lambda m: m.system_status == MAV.MAV_STATE_CRITICAL)
    assert heartbeat.base_mode & ARMED


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
    wait_until(link.sub, lambda s: at(s, -1.0, 2.0, 5.5, 180.0))


def test_a_local_offset_target_takes_an_absolute_yaw(launch) -> None:
    link = launch(start_yaw_deg=90.0, pilot_failsafe="off")
    assert link.set_mode(GUIDED).result == MAV.MAV_RESULT_ACCEPTED
    link.arm()
    # The offset is north, east, down whatever the heading; the yaw is the heading to end at.
    link.target(MAV.MAV_FRAME_LOCAL_OFFSET_NED, POSITION_AND_YAW, 1.0, -0.5, -1.0, -math.pi / 4)
    wait_until(link.sub, lambda s: at(s, 1.0, -0.5, 4.0, -45.0))


def test_a_local_target_without_a_yaw_keeps_the_heading_and_counts_only_in_guided(
    launch,
) -> None:
    link = launch(start_yaw_deg=30.0, pilot_failsafe="off")
    link.arm()
    link.target(MAV.MAV_FRAME_LOCAL_NED, POSITION_ONLY, 1.0, -1.0, 4.0)  # in MANUAL: ignored
    assert link.set_mode(GUIDED).result == MAV.MAV_RESULT_ACCEPTED  # handled after the target
    assert holds_throughout(link.sub, lambda s: at(s, 0.0, 0.0, 5.0, 30.0), 0.2)

    link.target(MAV.MAV_FRAME_LOCAL_NED, POSITION_ONLY, 1.0, -1.0, 4.0, yaw=2.0)
    wait_until(link.sub, lambda s: at(s, 1.0, -1.0, 4.0, 30.0))


def test_a_target_sent_while_disarmed_is_dropped(launch) -> None:
    link = launch(pilot_failsafe="off")
    assert link.set_mode(GUIDED).result == MAV.MAV_RESULT_ACCEPTED
    link.target(MAV.MAV_FRAME_LOCAL_OFFSET_NED, POSITION_ONLY, 1.0, 0.0, 0.0)
    # ArduSub resets its waypoint controller while disarmed: the target is forgotten.
    link.arm()
    assert holds_throughout(link.sub, lambda s: at(s, 0.0, 0.0, 5.0, 0.0), 0.3)


def test_a_current_drifts_the_vehicle_unless_a_controller_holds_against_it(launch) -> None:
    link = launch(current_ned_mps=(1.0, 0.5, 0.4), pilot_failsafe="off")
    # Each LOCAL_POSITION_NED after an acknowledgement was measured in the new state.
    drifting = link.receive("LOCAL_POSITION_NED", where=lambda m: m.time_boot_ms >= 100)
    assert velocity(drifting) == pytest.approx((1.0, 0.5, 0.4))  # disarmed, it drifts

    assert link.set_mode(ALT_HOLD).result == MAV.MAV_RESULT_ACCEPTED
    link.arm()
    alt_hold = link.receive("LOCAL_POSITION_NED")
    assert velocity(alt_hold) == pytest.approx((1.0, 0.5, 0.0))  # ALT_HOLD holds the depth

    assert link.set_mode(MANUAL).result == MAV.MAV_RESULT_ACCEPTED
    assert velocity(link.receive("LOCAL_POSITION_NED")) == pytest.approx((1.0, 0.5, 0.4))

    assert link.set_mode(GUIDED).result == MAV.MAV_RESULT_ACCEPTED
    assert velocity(link.receive("LOCAL_POSITION_NED")) == (0.0, 0.0, 0.0)
    held = link.sub.state()
    assert holds_throughout(link.sub, lambda s: s == held, 0.2)


def test_noise_misses_a_guided_target_by_a_bounded_amount_repeatable_by_seed(launch) -> None:
    links = [launch(noise=0.1, seed=3, pilot_failsafe="off") for _ in range(2)]
    for link in links:
        link.set_mode(GUIDED)
        link.arm()
        link.target(MAV.MAV_FRAME_BODY_OFFSET_NED, POSITION_ONLY, 2.0, 0.0, 0.0)
    for link in links:  # moved, then stopped: the goal is reached
        stopped = link.receive(
            "LOCAL_POSITION_NED", where=lambda m: m.x > 1.0 and velocity(m) == (0.0, 0.0, 0.0)
        )
        assert stopped is not None
    ends = [link.sub.state() for link in links]
    misses = [(s.north - 2.0, s.east, s.down - 5.0) for s in ends]
    assert misses[0] == pytest.approx(misses[1], abs=1e-9)
    assert 1e-4 < math.dist(misses[0], (0.0, 0.0, 0.0)) < 5 * 0.1 * 2.0 * math.sqrt(3)


def test_stop_ends_the_thread_and_the_telemetry(launch) -> None:
    link = launch()
    link.sub.stop()  # joins the thread (waiting 2 s at most)
    assert not [t for t in threading.enumerate() if t.name == "fake-sub"]
    link.sub.stop()  # again: nothing happens
    while link.gcs.recv_match(blocking=False) is not None:  # what was sent before the stop
        pass
    assert link.gcs.recv_match(blocking=True, timeout=0.3) is None


def test_a_paused_heartbeat_leaves_the_telemetry_running(launch) -> None:
    link = launch(pilot_failsafe="off")
    link.sub.pause_heartbeat(True)
    while link.gcs.recv_match(blocking=False) is not None:  # what was sent before the pause
        pass
    # 1.2 s of the fake sub's clock: at 1 Hz a HEARTBEAT would have gone out.
    kinds = {m.get_type() for m in link.stream_for("ATTITUDE", 1_200)}
    assert "HEARTBEAT" not in kinds
    link.sub.pause_heartbeat(False)
    assert link.receive("HEARTBEAT") is not None


def test_serve_reports_the_state_until_stopped() -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as ground:  # held: no one else's
        ground.bind(("127.0.0.1", 0))
        config = FakeSubConfig(address=f"udpout:127.0.0.1:{ground.getsockname()[1]}", **FAST)
        stop, states = threading.Event(), []
        server = threading.Thread(target=serve, args=(config, stop, states.append, 0.05))
        server.start()
        try:
            deadline = time.monotonic() + 3.0
            while len(states) < 2 and time.monotonic() < deadline:
                time.sleep(0.01)
        finally:
            stop.set()
            server.join(timeout=3.0)
    assert not server.is_alive()
    assert len(states) >= 2 and states[0].mode == MANUAL and not states[0].armed


@pytest.mark.parametrize(
    ("bad", "name"),
    [
        ({"max_speed_mps": 0.0}, "max_speed_mps"),
        ({"guided_yaw_rate_dps": -1.0}, "guided_yaw_rate_dps"),
        ({"physics_hz": math.inf}, "physics_hz"),
        ({"noise": -0.1}, "noise"),
        ({"noise": math.nan}, "noise"),
        ({"pilot_failsafe": "surface"}, "pilot_failsafe"),
        ({"current_ned_mps": (0.0, 0.0)}, "current_ned_mps"),
        ({"start_ned": (0.0, math.nan, 5.0)}, "start_ned"),
        ({"system_id": 0}, "system_id"),
        ({"gcs_system_id": 256}, "gcs_system_id"),
        ({"address": " "}, "address"),
        ({"address": "bogus"}, "address"),  # pymavlink would open it as a serial port
        ({"address": "udpout:127.0.0.1:x"}, "address"),
        ({"speed": 1.0}, "speed"),
    ],
)
def test_a_bad_config_value_is_a_config_error_naming_the_field(
    bad: dict[str, Any], name: str
) -> None:
    with pytest.raises(ConfigError, match=f"'{name}"):
        FakeSubConfig(**bad)


def test_fake_sub_refuses_a_malformed_address_in_one_line() -> None:
    """Not a traceback from pymavlink opening 'bogus' as a serial port."""
    result = cavenav("fake-sub", "--connect", "bogus")
    assert result.returncode == 2
    (line,) = result.stderr.strip().splitlines()
    assert re.match("error: fake sub settings: field 'address': .*'bogus'", line)


def test_fake_sub_help_states_the_defaults_the_config_holds() -> None:
    """The command passes only the flags given; its help repeats the config's defaults."""
    shown = " ".join(cavenav("fake-sub", "--help", env={"COLUMNS": "400"}).stdout.split())
    defaults = FakeSubConfig()
    for flag, default in [
        ("--connect", defaults.address),
        ("--noise", f"{defaults.noise:g}"),
        ("--depth", f"{defaults.start_ned[2]:g}"),
        ("--pilot-timeout", f"{defaults.pilot_timeout_s:g}"),
        ("--seed", f"{defaults.seed}"),
    ]:
        assert re.search(rf"{flag} [^│]*\[default: \({re.escape(default)}\)\]", shown), flag


def test_a_serial_device_is_looked_for_when_the_fake_sub_starts() -> None:
    """Settings naming one load on any machine; starting without it is one line."""
    config = FakeSubConfig(address="/dev/no-such-serial-port")
    with pytest.raises(ConfigError, match="/dev/no-such-serial-port is not on this machine"):
        FakeSub(config).start()


def test_a_config_takes_vectors_as_lists() -> None:
    assert FakeSubConfig(start_ned=[1, 2, 3]).start_ned == (1.0, 2.0, 3.0)


# ---------------------------------------------------------------------------- the SITL's motion
# What ArduSub 4.5.7's SITL does (issue 46), at the fake sub's defaults (KINEMATIC undone).
SITL_MOTION = {
    name: getattr(FakeSubConfig(), name)
    for name in (*KINEMATIC, "max_speed_mps", "max_vertical_mps", "max_yaw_rate_dps")
}


def steady(link: Link, **sticks: int) -> FakeSubState:
    """Hold ``sticks`` at 10 Hz for 2.5 s (long enough to reach a steady speed); the state
    at the end, sticks still held."""
    deadline = time.monotonic() + 2.5
    while time.monotonic() < deadline:
        link.sticks(**sticks)
        time.sleep(0.1)
    return link.sub.state()


def test_stick_400_holds_the_sitls_speed_and_turn_rate(launch) -> None:
    link = launch(**SITL_MOTION, pilot_failsafe="off")
    link.arm()
    assert link.set_mode(ALT_HOLD).result == MAV.MAV_RESULT_ACCEPTED
    ahead = link.receive("LOCAL_POSITION_NED", where=lambda m: m.vx > 0.38 and m.vx < 0.40)
    assert ahead is None  # at rest yet
    steady(link, x=400)  # held on: this test turns the pilot-input failsafe off
    moving = link.receive("LOCAL_POSITION_NED", where=lambda m: abs(m.vx - 0.386) < 0.01)
    assert moving is not None and abs(moving.vy) < 1e-6
    steady(link, r=400)
    turning = link.receive("ATTITUDE", where=lambda m: abs(math.degrees(m.yawspeed) - 24.5) < 0.5)
    assert turning is not None


def test_let_go_the_vehicle_coasts_on_and_turns_on(launch) -> None:
    """Nothing brakes it in ALT_HOLD: 0.39 m/s falls to about 0.1 in the first second and
    a half and the vehicle is still moving after it, as on the SITL; a 24.5 deg/s turn
    turns on by several degrees."""
    link = launch(**SITL_MOTION, pilot_failsafe="off")
    link.arm()
    link.set_mode(ALT_HOLD)
    steady(link, x=400, r=400)
    let_go = link.sub.state()
    link.sticks()
    time.sleep(1.5)
    later = link.sub.state()
    coasted = math.dist((let_go.north, let_go.east), (later.north, later.east))
    assert 0.2 < coasted < 0.5
    assert link.receive("LOCAL_POSITION_NED").vx > 0.02  # still moving
    assert 3.0 < angle_between_deg(later.yaw_deg, let_go.yaw_deg) < 15.0


@pytest.mark.parametrize("sticks", [{"x": 90}, {"y": -90}, {"r": 90}, {"z": 620}, {"z": 380}])
def test_small_sticks_are_swallowed_by_the_dead_bands(launch, sticks: dict[str, int]) -> None:
    link = launch(**SITL_MOTION, pilot_failsafe="off")
    link.arm()
    link.set_mode(ALT_HOLD)
    before = link.sub.state()
    after = steady(link, **sticks)
    moved = math.dist((before.north, before.east), (after.north, after.east))
    assert moved < 0.01 and abs(after.down - before.down) < 0.01
    assert angle_between_deg(before.yaw_deg, after.yaw_deg) < 0.1


def test_disarmed_it_rises_to_float_at_the_surface(launch) -> None:
    link = launch(**SITL_MOTION, start_ned=(0.0, 0.0, 0.3), pilot_failsafe="off")
    rising = link.receive("LOCAL_POSITION_NED", where=lambda m: m.vz < -0.035)
    assert rising is not None and rising.vz == pytest.approx(-0.04, abs=0.005)
    wait_until(link.sub, lambda s: s.down <= 0.17)
    assert holds_throughout(link.sub, lambda s: s.down == pytest.approx(0.17, abs=1e-6), 0.5)


def test_the_position_comes_late_and_guided_waits_for_it(launch) -> None:
    link = launch(position_after_s=1.0, pilot_failsafe="off")
    assert link.receive("LOCAL_POSITION_NED", timeout=0.5) is None
    refused = link.set_mode(GUIDED, text="Mode change failed: GUIDED requires position")
    assert refused.result == MAV.MAV_RESULT_FAILED
    assert link.receive("LOCAL_POSITION_NED", timeout=2.0) is not None
    assert link.set_mode(GUIDED).result == MAV.MAV_RESULT_ACCEPTED


def test_guided_sets_off_late_and_slows_into_its_target(launch) -> None:
    faster = {"guided_speed_mps": 2.0, "guided_delay_s": 0.5, "pilot_failsafe": "off"}
    link = launch(**SITL_MOTION | faster)
    link.arm()
    link.set_mode(GUIDED)
    sent = time.monotonic()
    link.target(MAV.MAV_FRAME_LOCAL_OFFSET_NED, POSITION_ONLY, 1.0, 0.0, 0.0)
    state = wait_until(link.sub, lambda s: s.north > 0.01)
    assert time.monotonic() - sent > 0.45
    state = wait_until(link.sub, lambda s: s.north > 0.9)
    assert link.receive("LOCAL_POSITION_NED").vx < 0.2  # slowing, 0.1 m short
    wait_until(link.sub, lambda s: s.north == pytest.approx(1.0, abs=1e-6), timeout=10.0)
    assert state.armed
