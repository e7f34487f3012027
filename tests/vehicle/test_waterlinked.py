"""A Water Linked DVL A50, read over its TCP JSON API from a fake DVL on loopback that
streams the documented json_v3 reports and answers the documented commands."""

from __future__ import annotations

import itertools
import json
import socket
import time
from collections.abc import Callable, Iterator

import numpy as np
import pytest

from cavenav.core.errors import ConfigError, VehicleError
from cavenav.vehicle.waterlinked import (
    DvlAddress,
    DvlPosition,
    DvlVelocity,
    FakeDvl,
    WaterLinkedDvl,
)

STEP_S = 0.125  # the fake's clock: one report every 1/8 s of the DVL's own time


def velocity(time_s: float, valid: bool = True, vx: float = 0.5) -> DvlVelocity:
    return DvlVelocity(
        time_s=time_s,
        velocity=np.array([vx, -0.25, 0.0625]),
        valid=valid,
        fom=0.002,
        altitude_m=1.5,
        beam_distances_m=np.array([1.6, 1.625, 1.5, 1.75]),
        beam_valid=np.array([True, True, valid, True]),
        covariance=np.diag([4e-6, 4e-6, 1e-6]),
        beam_velocities=np.array([0.25, -0.125, 0.5, 0.0]),
        rssi_dbm=np.array([-30.5, -31.0, -27.25, -28.0]),
        nsd_dbm=np.array([-88.5, -89.5, -97.0, -88.25]),
    )


def measurements(make: Callable[[float], DvlVelocity]) -> Callable[[], DvlVelocity]:
    """``measure`` for the fake: ``make(t)`` at t = 1.7e9, then every STEP_S."""
    times: Iterator[int] = itertools.count()
    return lambda: make(1.7e9 + next(times) * STEP_S)


def test_the_client_reads_the_velocity_the_fake_measured_field_for_field() -> None:
    make = measurements(velocity)
    with FakeDvl(make, rate_hz=50.0) as dvl_unit, WaterLinkedDvl.connect(dvl_unit.address) as dvl:
        got = dvl.next_velocity()
        assert dvl.latest() is got
    assert (got.time_s - 1.7e9) % STEP_S == 0  # microseconds carry these times exactly
    assert got == velocity(got.time_s)


def test_an_invalid_velocity_passes_through_marked_invalid() -> None:
    make = measurements(lambda t: velocity(t, valid=False))
    with FakeDvl(make, rate_hz=50.0) as dvl_unit, WaterLinkedDvl.connect(dvl_unit.address) as dvl:
        got = dvl.next_velocity()
    assert not got.valid and got.beam_valid.tolist() == [True, True, False, True]
    assert got == velocity(got.time_s, valid=False)


def test_a_report_is_the_documented_json_v3_report() -> None:
    report = velocity(1.7e9).to_report(time_ms=125.0, sent_s=1.7e9 + 0.19)
    documented = {  # docs/dvl/dvl-json-protocol.md, "Velocity-and-transducer report"
        "time", "vx", "vy", "vz", "fom", "covariance", "altitude", "transducers",
        "velocity_valid", "status", "format", "type", "time_of_validity",
        "time_of_transmission",
    }  # fmt: skip
    assert set(report) == documented
    assert set(report["transducers"][2]) == {
        "id", "velocity", "distance", "rssi", "nsd", "beam_valid",
    }  # fmt: skip
    assert report["type"] == "velocity" and report["format"].startswith("json_v3")
    assert report["time_of_validity"] == 1_700_000_000_000_000  # Unix microseconds
    assert report["time_of_transmission"] == 1_700_000_000_190_000
    assert DvlVelocity.from_report(json.loads(json.dumps(report))) == velocity(1.7e9)


def wait_for(condition: Callable[[], object], dvl: WaterLinkedDvl, what: str) -> None:
    """Read velocity reports until ``condition()`` holds (2 s at most)."""
    deadline = time.monotonic() + 2.0
    while not condition():
        assert time.monotonic() < deadline, what
        dvl.next_velocity()


def test_the_fake_dead_reckons_and_the_reset_is_answered() -> None:
    moving = True  # then the DVL loses its lock, so that nothing moves while it resets
    make = measurements(lambda t: velocity(t, valid=moving, vx=1.0))
    with FakeDvl(make, rate_hz=50.0) as dvl_unit, WaterLinkedDvl.connect(dvl_unit.address) as dvl:

        def reckoned() -> np.ndarray | None:
            position = dvl.latest_position()
            return None if position is None else position.position

        wait_for(lambda: (p := reckoned()) is not None and p[0] >= 0.5, dvl, "no progress")
        moving = False
        wait_for(lambda: not dvl.next_velocity().valid, dvl, "the lock was never lost")
        position = reckoned()
        assert position is not None
        # 1 m/s forward, -0.25 m/s right, 0.0625 m/s down, for whole steps of 1/8 s
        assert position[0] % STEP_S == 0
        assert position.tolist() == [position[0], -0.25 * position[0], 0.0625 * position[0]]
        dvl.reset_dead_reckoning()
        wait_for(lambda: np.all(reckoned() == 0.0), dvl, "the reset did not show")
        assert dvl.get_config()["range_mode"] == "auto"
        assert dvl_unit.commands == ["reset_dead_reckoning", "get_config"]


def test_an_invalid_velocity_is_not_reckoned() -> None:
    make = measurements(lambda t: velocity(t, valid=False))
    with FakeDvl(make, rate_hz=100.0) as dvl_unit, WaterLinkedDvl.connect(dvl_unit.address) as dvl:
        for _ in range(3):
            dvl.next_velocity()
        assert dvl_unit.dead_reckoning().position.tolist() == [0.0, 0.0, 0.0]


def test_a_command_the_dvl_refuses_is_a_vehicle_error_with_its_reason() -> None:
    with (
        FakeDvl(measurements(velocity)) as dvl_unit,
        WaterLinkedDvl.connect(dvl_unit.address) as dvl,
    ):
        with pytest.raises(VehicleError, match="set_config failed: parameters .*: give some of"):
            dvl.command("set_config", {"warp_drive": True})
        dvl.command("set_config", {"speed_of_sound": 1480})
        assert dvl.get_config()["speed_of_sound"] == 1480


def test_a_position_report_reads_back() -> None:
    position = DvlPosition(49056.809, np.array([12.5, 64.5, 1.75]), 0.002, 0.5, -0.25, 90.0)
    report = position.to_report()
    assert set(report) == {
        "ts", "x", "y", "z", "std", "roll", "pitch", "yaw", "type", "status", "format",
    }  # fmt: skip
    assert DvlPosition.from_report(report) == position


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"vx": "fast"}, "field 'vx' is 'fast', not a number"),
        ({"altitude": None}, "field 'altitude' is None, not a number"),
        ({"velocity_valid": 1}, "field 'velocity_valid' is 1, not true or false"),
        ({"covariance": [[1.0, 0.0]]}, "field 'covariance' is .*, not a 3x3 list"),
        ({"transducers": []}, "field 'transducers' is \\[\\], not a list of 4"),
        ({"time_of_validity": True}, "field 'time_of_validity' is True"),
        ({"type": "velocity_water"}, "field 'type' is 'velocity_water', not 'velocity'"),
    ],
)
def test_a_malformed_report_is_a_vehicle_error_in_one_line(change: dict, message: str) -> None:
    report = velocity(1.7e9).to_report() | change
    with pytest.raises(VehicleError, match=f"^DVL velocity report: {message}") as refused:
        DvlVelocity.from_report(report)
    assert "\n" not in str(refused.value)


@pytest.mark.parametrize("number", [0, 4, True, 3.0, None])
def test_a_transducer_without_its_own_id_is_malformed(number: object) -> None:
    report = velocity(1.7e9).to_report()
    report["transducers"][3]["id"] = number
    with pytest.raises(VehicleError, match="^DVL velocity report: transducer .*no id 0-3"):
        DvlVelocity.from_report(report)


def test_a_malformed_report_on_the_wire_is_raised_once_and_the_stream_goes_on() -> None:
    with FakeDvl(measurements(velocity), rate_hz=50.0) as dvl_unit:
        dvl = WaterLinkedDvl.connect(dvl_unit.address)
        dvl_unit.send_line(json.dumps(velocity(1.7e9).to_report() | {"vx": "fast"}))
        with pytest.raises(
            VehicleError, match=f"^DVL {dvl_unit.address}: velocity report: field 'vx'"
        ):
            for _ in range(50):  # it surfaces at the next call after it came
                dvl.next_velocity()
        dvl_unit.send_line("velocity 0.5 0.25")
        with pytest.raises(VehicleError, match="a report that is no JSON: b'velocity 0.5"):
            for _ in range(50):
                dvl.next_velocity()
        assert dvl.next_velocity().valid  # the stream goes on
        dvl.close()


def test_a_dvl_that_closes_the_connection_is_a_vehicle_error() -> None:
    with FakeDvl(measurements(velocity), rate_hz=50.0) as dvl_unit:
        dvl = WaterLinkedDvl.connect(dvl_unit.address)
    with pytest.raises(VehicleError, match="the DVL closed the connection$"):
        for _ in range(50):
            dvl.next_velocity()
    with pytest.raises(VehicleError, match="closed the connection"):
        dvl.latest()
    dvl.close()


def test_connection_refused_is_a_vehicle_error_in_one_line() -> None:
    closed = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    closed.bind(("127.0.0.1", 0))
    port = closed.getsockname()[1]
    closed.close()
    with pytest.raises(VehicleError, match=f"^DVL tcp:127.0.0.1:{port}: Connection refused$"):
        WaterLinkedDvl.connect(f"tcp:127.0.0.1:{port}")


def test_a_silent_dvl_is_a_vehicle_error_in_its_own_time() -> None:
    silent = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    silent.bind(("127.0.0.1", 0))
    silent.listen()  # accepts connections, never says a word
    port = silent.getsockname()[1]
    started = time.monotonic()
    try:
        with pytest.raises(
            VehicleError, match=f"^DVL tcp:127.0.0.1:{port}: no report within 0.3 s$"
        ):
            WaterLinkedDvl.connect(f"tcp:127.0.0.1:{port}", timeout_s=0.3)
    finally:
        silent.close()
    assert time.monotonic() - started < 1.5


def test_a_command_not_answered_is_a_vehicle_error() -> None:
    with FakeDvl(measurements(velocity), rate_hz=50.0) as dvl_unit:
        dvl = WaterLinkedDvl.connect(dvl_unit.address)
        dvl_unit._answer = lambda message: {"type": "nothing"}  # type: ignore[method-assign]
        with pytest.raises(VehicleError, match="no response to reset_dead_reckoning in 0.2 s$"):
            dvl.reset_dead_reckoning(timeout_s=0.2)
        dvl.close()


@pytest.mark.parametrize(
    ("text", "address"),
    [
        ("tcp:192.168.194.95", DvlAddress("192.168.194.95", 16171)),
        ("tcp:192.168.2.95:16171", DvlAddress("192.168.2.95", 16171)),
        ("tcp:localhost:9000", DvlAddress("localhost", 9000)),
    ],
)
def test_addresses_are_read_with_the_dvls_port_by_default(text: str, address: DvlAddress) -> None:
    assert DvlAddress.parse(text) == address
    assert str(address).startswith("tcp:")


@pytest.mark.parametrize(
    "text", ["192.168.194.95", "udp:192.168.194.95:16171", "tcp:", "tcp:host:port", "tcp:h:0"]
)
def test_a_malformed_address_is_refused_in_one_line(text: str) -> None:
    with pytest.raises(ConfigError, match=r"^DVL address .*: give tcp:HOST\[:PORT\]"):
        WaterLinkedDvl.connect(text)


def test_a_velocity_of_the_wrong_shape_is_refused_where_it_is_made() -> None:
    with pytest.raises(ValueError, match=r"shape \(3,\) is needed, not \(2,\)"):
        DvlVelocity(0.0, np.zeros(2), True, 0.0, 1.0, np.ones(4), np.ones(4, bool))
    with pytest.raises(ValueError, match="DvlVelocity.beam_distances_m"):
        DvlVelocity(0.0, np.zeros(3), True, 0.0, 1.0, np.full(4, np.nan), np.ones(4, bool))
