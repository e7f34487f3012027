"""A BlueROV2's own echo sounders: Blue Robotics' Ping1D and Ping2, read with their own
library (``bluerobotics-ping``), over serial or UDP as BlueOS exposes them.

The method's two vertical ranges, d_top and d_bottom, come on a real vehicle from two
single-beam sounders, one pointing up and one down. `PingSounders` reads both: each
reading is the device's ``distance_simple`` (distance in mm and a confidence in %), and
a reading below `PingSounder.min_confidence` counts as unknown (NaN), which the prompt
says in words. `FakePing1D` answers on 127.0.0.1 with the ping protocol's own messages,
for tests and for flying the loop without a vehicle.

An address is ``udp:HOST:PORT`` (BlueOS serves a Ping1D on UDP port 9090) or
``serial:DEVICE[:BAUD]`` (115200 baud by default).
"""

from __future__ import annotations

import contextlib
import io
import math
import socket
import struct
import threading
from collections.abc import Callable
from dataclasses import dataclass
from types import TracebackType
from typing import Any, Self

import brping
from brping import definitions

from cavenav.core.errors import ConfigError, VehicleError

__all__ = ["FakePing1D", "FakePingDevice", "PingAddress", "PingSounder", "PingSounders"]

SERIAL_BAUD = 115200
HEADER = struct.Struct("<2sHHBB")  # "BR", payload length, message id, source, destination
PROTOCOL_VERSION, GENERAL_REQUEST = 5, 6  # the ping protocol's common messages
GENERAL_INFO, DISTANCE_SIMPLE = 1210, 1211  # Ping1D's


@dataclass(frozen=True)
class PingAddress:
    """Where a sounder answers: ``udp`` HOST:PORT or ``serial`` DEVICE at BAUD."""

    kind: str
    where: str
    number: int

    @classmethod
    def parse(cls, text: str) -> PingAddress:
        """``udp:HOST:PORT`` or ``serial:DEVICE[:BAUD]``.

        Raises:
            ConfigError: anything else, in one line.
        """
        kind, _, rest = text.partition(":")
        where, _, number = rest.rpartition(":") if kind == "udp" else rest.partition(":")
        try:
            if kind == "udp" and where:
                return cls(kind, where, int(number))
            if kind == "serial" and where:
                return cls(kind, where, int(number or SERIAL_BAUD))
        except ValueError:
            pass
        raise ConfigError(f"sounder address {text!r}: give udp:HOST:PORT or serial:DEVICE[:BAUD]")

    def __str__(self) -> str:
        return f"{self.kind}:{self.where}:{self.number}"


class PingSounder:
    """One Ping1D or Ping2, connected and checked (it must answer its protocol version
    and general information, as `brping.Ping1D.initialize` asks). The library waits
    0.5 s for each answer."""

    def __init__(self, address: PingAddress, min_confidence: int = 50):
        """
        Raises:
            VehicleError: the device cannot be opened or does not answer.
        """
        self.address, self.min_confidence = address, min_confidence
        device = brping.Ping1D(payload_dict=_ping1d_messages())
        try:
            with contextlib.redirect_stdout(io.StringIO()):  # it prints "Opening ..."
                if address.kind == "udp":
                    device.connect_udp(address.where, address.number)
                else:
                    device.connect_serial(address.where, address.number)
        except Exception as exc:  # brping raises bare Exceptions
            raise VehicleError(f"sounder {address}: cannot open it ({exc})") from None
        try:
            answered = device.initialize()
        except OSError as exc:  # UDP: nothing listens there (ICMP port unreachable)
            raise VehicleError(f"sounder {address}: {exc.strerror or exc}") from None
        if not answered:
            raise VehicleError(f"sounder {address}: no answer to the ping protocol")
        self.device = device

    def read_m(self) -> float:
        """The range in metres; NaN when the device is not confident enough.

        Raises:
            VehicleError: no reading came back in time.
        """
        reading = self.device.get_distance_simple()
        if reading is None:
            raise VehicleError(f"sounder {self.address}: no distance within 0.5 s")
        if reading["confidence"] < self.min_confidence:
            return math.nan
        return reading["distance"] / 1000.0

    def close(self) -> None:
        iodev = getattr(self.device, "iodev", None)
        if iodev is not None:
            iodev.close()


@dataclass
class PingSounders:
    """The two vertical sounders: up (d_top) and down (d_bottom); either may be absent."""

    up: PingSounder | None
    down: PingSounder | None

    @classmethod
    def connect(cls, up: str | None, down: str | None, min_confidence: int = 50) -> PingSounders:
        """Open the sounders at the addresses given (None: that one is not fitted).

        Raises:
            ConfigError, VehicleError: an address or a device (one opened before it is
                closed again).
        """
        above, below = (PingAddress.parse(text) if text else None for text in (up, down))
        sounders = cls(None, None)
        try:
            sounders.up = PingSounder(above, min_confidence) if above else None
            sounders.down = PingSounder(below, min_confidence) if below else None
        except VehicleError:
            sounders.close()
            raise
        return sounders

    def read(self) -> tuple[float, float]:
        """(d_top, d_bottom) in metres; NaN where unknown or not fitted."""
        return tuple(  # type: ignore[return-value]
            sounder.read_m() if sounder else math.nan for sounder in (self.up, self.down)
        )

    def close(self) -> None:
        for sounder in (self.up, self.down):
            if sounder:
                sounder.close()


def _ping1d_messages() -> dict[int, Any]:
    """The Ping1D's own message table. The library's combined table, which a device made
    without one uses, gives message 1211 to the S500's altitude (bluerobotics-ping 0.2.5),
    and a Ping1D's ``distance_simple`` then cannot be read."""
    return {**definitions.payload_dict_common, **definitions.payload_dict_ping1d}


def _message(message_id: int, **fields: int) -> bytes:
    """A Ping1D message, packed by the library's own `PingMessage`."""
    message = brping.PingMessage(message_id, payload_dict=_ping1d_messages())
    for name, value in fields.items():
        setattr(message, name, value)
    return bytes(message.pack_msg_data())


class FakePingDevice:
    """A device on 127.0.0.1 (UDP) that answers the ping protocol's messages, for tests
    and for flying the loop without a vehicle: the socket, the thread that serves it, and
    the reading of each request's id (a general request names the message it wants in its
    payload). A kind of device says what it answers with `_answer`.

    Use as a context manager; ``address`` is where it listens (``udp:127.0.0.1:PORT``),
    ``requests`` lists the message ids asked for. An exception while answering stops the
    device, and leaving the context raises it.
    """

    name = "ping device"

    def __init__(self, port: int = 0):
        """``port``: where to listen on 127.0.0.1 (0: a free port the system picks).

        Raises:
            ConfigError: the port is taken.
        """
        self.requests: list[int] = []
        self._socket = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            self._socket.bind(("127.0.0.1", port))
        except OSError as exc:
            self._socket.close()
            raise ConfigError(
                f"a fake {self.name} cannot listen on UDP port {port}: {exc}"
            ) from None
        self._socket.settimeout(0.1)
        self._stop = threading.Event()
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._serve, daemon=True)

    @property
    def address(self) -> str:
        return f"udp:127.0.0.1:{self._socket.getsockname()[1]}"

    def __enter__(self) -> Self:
        self._thread.start()
        return self

    def __exit__(
        self,
        kind: type[BaseException] | None,
        error: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self._stop.set()
        self._thread.join()
        self._socket.close()
        if self._error is not None and error is None:
            raise self._error

    def _serve(self) -> None:
        while not self._stop.is_set():
            try:
                data, client = self._socket.recvfrom(4096)
            except TimeoutError:
                continue
            try:
                reply = self._reply(data)
            except Exception as error:  # handed to the caller at the end of the context
                self._error = error
                return
            if reply:
                self._socket.sendto(reply, client)

    def _reply(self, data: bytes) -> bytes | None:
        """The answer to one message (None: none, as to anything not in the protocol)."""
        if len(data) < HEADER.size + 2 or data[:2] != b"BR":
            return None
        _, length, message_id, _, _ = HEADER.unpack_from(data)
        if message_id == GENERAL_REQUEST and length >= 2:
            (message_id,) = struct.unpack_from("<H", data, HEADER.size)
        self.requests.append(message_id)
        return self._answer(message_id, data[HEADER.size : HEADER.size + length])

    def _answer(self, message_id: int, payload: bytes) -> bytes | None:
        """The answer to the message ``message_id`` whose payload is ``payload``."""
        raise NotImplementedError


class FakePing1D(FakePingDevice):
    """A Ping1D that answers every request in the ping protocol's own messages: the
    protocol version, its general information and ``distance_simple`` with the range
    ``distance_m()`` gives (NaN: confidence 0). A Ping1D's legacy request is an empty
    message of the id it wants. See `FakePingDevice` for its use.
    """

    name = "Ping1D"

    def __init__(self, distance_m: Callable[[], float], confidence: int = 100, port: int = 0):
        """
        Raises:
            ConfigError: the port is taken.
        """
        self.distance_m, self.confidence = distance_m, confidence
        super().__init__(port)

    def _answer(self, message_id: int, payload: bytes) -> bytes | None:
        if message_id == PROTOCOL_VERSION:
            return _message(PROTOCOL_VERSION, version_major=1)
        if message_id == GENERAL_INFO:
            return _message(GENERAL_INFO, firmware_version_major=3, voltage_5=5000)
        if message_id == DISTANCE_SIMPLE:
            distance = self.distance_m()
            known = math.isfinite(distance)
            millimetres = round(distance * 1000) if known else 0
            return _message(
                DISTANCE_SIMPLE, distance=millimetres, confidence=self.confidence * known
            )
        return None
