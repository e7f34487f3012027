"""A Ping360 scanning sonar, read with Blue Robotics' library from a fake Ping360 that
answers on loopback in the ping protocol's own messages."""

from __future__ import annotations

import socket
import time

import numpy as np
import pytest

from cavenav.core.errors import ConfigError, VehicleError
from cavenav.vehicle.ping import PingAddress
from cavenav.vehicle.ping360 import (
    DEVICE_DATA,
    DEVICE_INFORMATION,
    PROTOCOL_VERSION,
    TRANSDUCER,
    FakePing360,
    Ping360Settings,
    Ping360Sonar,
    next_angle,
    transducer_timing,
)


def ramp(angle_deg: float, samples: int, range_m: float) -> np.ndarray:
    """Intensities that say where they were drawn: the angle, then counting up."""
    return ((np.arange(samples) + round(angle_deg)) % 256).astype(np.uint8)


def test_a_ping_returns_the_intensities_the_sonar_drew_byte_for_byte() -> None:
    asked: list[tuple[float, int, float]] = []

    def echo(angle_deg: float, samples: int, range_m: float) -> np.ndarray:
        asked.append((angle_deg, samples, range_m))
        return ramp(angle_deg, samples, range_m)

    with FakePing360(echo) as device:
        sonar = Ping360Sonar.connect(device.address, Ping360Settings(range_m=2.0, gain=1))
        try:
            angle, intensities = sonar.ping(100)  # 100 gradians: 90 degrees
            assert sonar.ping(450)[0] == 50  # angles wrap round the 400 gradians
        finally:
            sonar.close()
        # Connected as the library connects (version, then the head's state), checked
        # to be a Ping360, then one transducer request per ping.
        assert device.requests == [
            PROTOCOL_VERSION,
            DEVICE_DATA,
            DEVICE_INFORMATION,
            TRANSDUCER,
            TRANSDUCER,
        ]
        head = device.head
    assert angle == 100 and intensities.dtype == np.uint8
    assert intensities.tobytes() == ramp(90.0, 1200, 1.98).tobytes()
    # Ping Viewer's 2 m: 1200 samples of 88 ticks (25 ns), a pulse of 11 us; 1.98 m.
    assert (head.number_of_samples, head.sample_period, head.transmit_duration) == (1200, 88, 11)
    assert (head.gain_setting, head.transmit_frequency, head.angle) == (1, 750, 50)
    assert asked[0] == (90.0, 1200, pytest.approx(1200 * 88 * 25e-9 * 1500 / 2))


@pytest.mark.parametrize(
    ("range_m", "samples", "period", "duration"),
    [
        (0.75, 500, 80, 5),  # short: fewer samples, as the period cannot go below 80
        (2.0, 1200, 88, 11),  # Ping Viewer's defaults come out of its own formula
        (10.0, 1200, 444, 53),
        (50.0, 1200, 2222, 267),
    ],
)
def test_the_timing_is_ping_viewers(
    range_m: float, samples: int, period: int, duration: int
) -> None:
    timing = transducer_timing(range_m, 1200, 1500.0)
    assert (timing.number_of_samples, timing.sample_period_ticks) == (samples, period)
    assert timing.transmit_duration_us == duration
    # range = samples * period * 25 ns * c / 2: the longest whole period within the range
    assert timing.range_m == pytest.approx(samples * period * 25e-9 * 1500 / 2)
    assert timing.range_m <= range_m < samples * (period + 1) * 25e-9 * 1500 / 2


def test_the_pulse_is_at_least_two_and_a_half_sample_periods() -> None:
    # 200 samples over 10 m: 2667 ticks (66.7 us); 8000 * 10 / 1500 = 53 us is too short.
    timing = transducer_timing(10.0, 200, 1500.0)
    assert timing.sample_period_ticks == 2666
    assert timing.transmit_duration_us == 167  # ceil(2.5 * 66.65)


def test_the_range_the_fake_draws_at_follows_the_speed_of_sound() -> None:
    ranges: list[float] = []

    def echo(angle_deg: float, samples: int, range_m: float) -> np.ndarray:
        ranges.append(range_m)
        return np.zeros(samples, np.uint8)

    settings = Ping360Settings(range_m=10.0, speed_of_sound=1480.0)
    with FakePing360(echo, speed_of_sound=1480.0) as device:
        sonar = Ping360Sonar.connect(device.address, settings)
        sonar.ping(0)
        sonar.close()
    assert ranges == [pytest.approx(settings.timing.range_m)]
    assert 9.95 <= ranges[0] <= 10.0


def test_a_sector_is_swept_back_and_forth_and_the_sweep_goes_on_where_it_stopped() -> None:
    settings = Ping360Settings(range_m=1.0, sector_deg=9.0, step_grad=2, center_grad=200)
    with FakePing360(ramp) as device:
        sonar = Ping360Sonar.connect(device.address, settings)
        try:
            first = sonar.sweep(5)
            then = sonar.sweep(6)
        finally:
            sonar.close()
        transmitted = device.pings
    # The head starts at 0, outside the 10 gradians around 200: it goes to the centre,
    # then turns back at each edge (edges included).
    angles = [angle for angle, _ in first + then]
    assert angles == [200, 202, 204, 202, 200, 198, 196, 198, 200, 202, 204]
    assert transmitted == angles
    assert all(data.tobytes() == ramp(a * 0.9, 666, 1.0).tobytes() for a, data in first + then)


def test_a_full_circle_goes_round() -> None:
    settings = Ping360Settings(step_grad=10)
    angle, direction, seen = 390, 1, []
    for _ in range(3):
        angle, direction = next_angle(angle, direction, settings)
        seen.append(angle)
    assert seen == [0, 10, 20] and direction == 1


def test_an_echo_of_the_wrong_length_is_refused_in_one_line() -> None:
    with FakePing360(lambda angle, samples, range_m: np.zeros(10, np.uint8)) as device:
        sonar = Ping360Sonar.connect(device.address)
        with pytest.raises(VehicleError, match=r"refused the ping \(echo gave uint8 \(10,\)"):
            sonar.ping(0)
        sonar.close()


def test_nothing_answering_at_the_address_is_a_vehicle_error_soon() -> None:
    silent = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    silent.bind(("127.0.0.1", 0))  # a port that receives and never answers
    port = silent.getsockname()[1]
    started = time.monotonic()
    try:
        with pytest.raises(VehicleError, match=f"^Ping360 udp:127.0.0.1:{port}: no answer"):
            Ping360Sonar(PingAddress("udp", "127.0.0.1", port))
    finally:
        silent.close()
    assert time.monotonic() - started < 2.0  # the library's 0.5 s for the protocol version


def test_nothing_listening_at_the_address_is_a_vehicle_error() -> None:
    closed = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    closed.bind(("127.0.0.1", 0))
    port = closed.getsockname()[1]
    closed.close()
    with pytest.raises(VehicleError, match=f"^Ping360 udp:127.0.0.1:{port}: Connection refused$"):
        Ping360Sonar(PingAddress("udp", "127.0.0.1", port))


def test_a_ping_not_answered_in_time_is_a_vehicle_error_and_its_late_answer_is_passed_over() -> (
    None
):
    delays = iter([0.5])  # the first ping answers late, the others at once

    def slow(angle_deg: float, samples: int, range_m: float) -> np.ndarray:
        time.sleep(next(delays, 0.0))
        return ramp(angle_deg, samples, range_m)

    with FakePing360(slow) as device:
        sonar = Ping360Sonar(PingAddress.parse(device.address), answer_s=0.4)
        started = time.monotonic()
        with pytest.raises(VehicleError, match="no device_data at 7 gradians within 0.4 s$"):
            sonar.ping(7)
        assert time.monotonic() - started < 1.0
        angle, data = sonar.ping(8)  # the answer at 7 comes first, and is not taken
        sonar.close()
    assert angle == 8 and data[0] == round(8 * 0.9)


def test_a_renderer_that_fails_fails_the_test_that_used_it() -> None:
    def broken(angle_deg: float, samples: int, range_m: float) -> np.ndarray:
        raise RuntimeError("no cave loaded")

    with pytest.raises(RuntimeError, match="no cave loaded"), FakePing360(broken) as device:
        sonar = Ping360Sonar(PingAddress.parse(device.address), answer_s=0.2)
        with pytest.raises(VehicleError, match="no device_data"):
            sonar.ping(0)
        sonar.close()


@pytest.mark.parametrize("text", ["192.168.2.2:9092", "udp:host", "tcp:host:9092", "serial:"])
def test_a_malformed_address_is_refused_in_one_line(text: str) -> None:
    with pytest.raises(ConfigError, match=r"^Ping360 address .*: give udp:HOST:PORT \(BlueOS"):
        Ping360Sonar.connect(text)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"range_m": 0.5}, "range_m 0.5: give 0.75 to 50.0 m"),
        ({"range_m": 60}, "range_m 60: give 0.75 to 50.0 m"),
        ({"range_m": float("nan")}, "range_m nan"),
        ({"gain": 3}, "gain 3: give a whole number, 0 to 2"),
        ({"gain": 1.0}, "gain 1.0: give a whole number"),
        ({"max_samples": 1201}, "max_samples 1201: give a whole number, 200 to 1200"),
        ({"transmit_frequency_khz": 1200}, "transmit_frequency_khz 1200"),
        ({"speed_of_sound": 343.0}, "speed_of_sound 343.0: give 1000.0 to 2000.0 m/s"),
        ({"sector_deg": 400.0}, "sector_deg 400.0: give 0.9 to 360.0 degrees"),
        ({"sector_deg": 0.0}, "sector_deg 0.0"),
        ({"step_grad": 0}, "step_grad 0: give a whole number, 1 to 10 gradians"),
        ({"step_grad": True}, "step_grad True"),
        ({"center_grad": 400}, "center_grad 400"),
    ],
)
def test_settings_out_of_bounds_are_refused_in_one_line(change: dict, message: str) -> None:
    with pytest.raises(ConfigError, match=f"^Ping360 {message}") as refused:
        Ping360Settings(**change)
    assert "\n" not in str(refused.value)


def test_a_sector_is_counted_in_the_heads_gradians() -> None:
    assert Ping360Settings(sector_deg=360.0).sector_grad == 400
    assert Ping360Settings(sector_deg=90.0).sector_grad == 100
