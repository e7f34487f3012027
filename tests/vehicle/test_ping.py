"""A BlueROV2's own echo sounders, read with Blue Robotics' library from a Ping1D that
answers on loopback in the ping protocol's own messages."""

from __future__ import annotations

import math
import socket

import pytest

from cavenav.core.errors import ConfigError, VehicleError
from cavenav.vehicle.ping import (
    DISTANCE_SIMPLE,
    GENERAL_INFO,
    PROTOCOL_VERSION,
    FakePing1D,
    PingAddress,
    PingSounder,
    PingSounders,
)


def test_both_sounders_give_d_top_and_d_bottom_in_metres() -> None:
    with FakePing1D(lambda: 2.5) as ceiling, FakePing1D(lambda: 1.25) as floor:
        sounders = PingSounders.connect(up=ceiling.address, down=floor.address)
        try:
            assert sounders.read() == (2.5, 1.25)
        finally:
            sounders.close()
        # Connected as the library connects: its version and information, then a range.
        assert ceiling.requests == [PROTOCOL_VERSION, GENERAL_INFO, DISTANCE_SIMPLE]


def test_a_reading_the_device_is_not_confident_of_is_unknown() -> None:
    ranges = iter([3.0, math.nan])
    with FakePing1D(lambda: next(ranges)) as device:
        sounder = PingSounder(PingAddress.parse(device.address), min_confidence=50)
        assert sounder.read_m() == 3.0
        assert math.isnan(sounder.read_m())  # confidence 0
        sounder.close()
    with FakePing1D(lambda: 3.0, confidence=40) as doubtful:
        sounder = PingSounder(PingAddress.parse(doubtful.address), min_confidence=50)
        assert math.isnan(sounder.read_m())
        sounder.close()


def test_a_sounder_not_fitted_reads_unknown() -> None:
    with FakePing1D(lambda: 1.5) as floor:
        sounders = PingSounders.connect(up=None, down=floor.address)
        d_top, d_bottom = sounders.read()
        sounders.close()
    assert math.isnan(d_top) and d_bottom == 1.5


def test_nothing_answering_at_the_address_is_a_vehicle_error() -> None:
    silent = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    silent.bind(("127.0.0.1", 0))  # a port that receives and never answers
    port = silent.getsockname()[1]
    try:
        with pytest.raises(VehicleError, match=f"udp:127.0.0.1:{port}: no answer"):
            PingSounder(PingAddress(kind="udp", where="127.0.0.1", number=port))
    finally:
        silent.close()


def test_nothing_listening_at_the_address_is_a_vehicle_error() -> None:
    closed = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    closed.bind(("127.0.0.1", 0))
    port = closed.getsockname()[1]
    closed.close()  # the port refuses: ConnectionRefusedError, raised from inside brping
    with pytest.raises(VehicleError, match=f"^sounder udp:127.0.0.1:{port}: Connection refused$"):
        PingSounder(PingAddress(kind="udp", where="127.0.0.1", number=port))


def test_a_failed_second_sounder_closes_the_first_again() -> None:
    silent = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    silent.bind(("127.0.0.1", 0))
    with FakePing1D(lambda: 2.0) as ceiling:
        opened: list[PingSounder] = []
        real_init = PingSounder.__init__

        def remember(self: PingSounder, *args: object, **kwargs: object) -> None:
            real_init(self, *args, **kwargs)  # type: ignore[arg-type]
            opened.append(self)

        with pytest.MonkeyPatch.context() as patch:
            patch.setattr(PingSounder, "__init__", remember)
            with pytest.raises(VehicleError, match="no answer"):
                PingSounders.connect(ceiling.address, f"udp:127.0.0.1:{silent.getsockname()[1]}")
        (up,) = opened
        assert up.device.iodev.fileno() == -1  # closed
    silent.close()


@pytest.mark.parametrize(
    ("text", "address"),
    [
        ("udp:192.168.2.2:9090", PingAddress("udp", "192.168.2.2", 9090)),
        ("serial:/dev/ttyUSB0", PingAddress("serial", "/dev/ttyUSB0", 115200)),
        ("serial:/dev/ttyUSB0:9600", PingAddress("serial", "/dev/ttyUSB0", 9600)),
    ],
)
def test_addresses_are_read_as_blueos_gives_them(text: str, address: PingAddress) -> None:
    assert PingAddress.parse(text) == address


@pytest.mark.parametrize("text", ["192.168.2.2:9090", "udp:host", "udp:host:port", "serial:"])
def test_a_malformed_address_is_refused_in_one_line(text: str) -> None:
    with pytest.raises(ConfigError, match="give udp:HOST:PORT or serial:DEVICE"):
        PingAddress.parse(text)
