"""A Blue Robotics Ping360 scanning imaging sonar, read with its own library
(``bluerobotics-ping``), over UDP as BlueOS serves it (port 9092) or a serial line.

The Ping360 turns a single narrow beam on a stepper head and answers one ping per
request: a ``transducer`` message (2601) names the head angle and how to sample, and the
sonar answers with ``device_data`` (2300): the same settings and the echo intensities,
one byte (0-255) per sample, nearest first. `Ping360Sonar` sends those requests, one
angle at a time (`Ping360Sonar.ping`) or sweeping a sector as Ping Viewer does
(`Ping360Sonar.sweep`). `FakePing360` answers on 127.0.0.1 in the same messages, with
intensities an injected renderer draws, for tests and for flying the loop without a
vehicle.

The protocol facts this relies on, and where they come from:

- message layouts (``brping/definitions.py`` of bluerobotics-ping 0.2.5):
  ``transducer`` = mode u8, gain_setting u8, angle u16 (gradians, 0-399),
  transmit_duration u16 (us), sample_period u16 (25 ns ticks), transmit_frequency u16
  (kHz), number_of_samples u16, transmit u8, reserved u8; ``device_data`` = the first
  seven of those, data_length u16, then the data bytes. ``brping.Ping360.initialize``
  asks for ``protocol_version`` (5) and then ``device_data`` by ``general_request`` (6);
  ``device_information`` (4) says the device type (2: Ping360). Mode 1 is the Ping360's
  operating mode (the library's field documentation; Ping Viewer sends 1).
- the range and the timing (Ping Viewer, ``src/sensor/ping360.{h,cpp}``, commit 1ed4508):
  one-way range = number_of_samples * sample_period * 25e-9 s * speed_of_sound / 2;
  ``set_range`` starts from 1200 samples and takes samples away until the sample period
  ``2 * range / (samples * c * 25e-9)``, truncated to an integer, is at least 80 ticks;
  the automatic transmit duration is ``round(8000 * range / c)`` us, at least 2.5 sample
  periods, at most ``min(500, sample_period_s * 64e6)`` and at least 5 us.
  Ping Viewer's own line for "at least 2.5 sample periods" divides seconds by 1000 (its
  comment says nanoseconds), which makes that rule a no-op; the firmware engineer's rule
  quoted there is in microseconds, as ping-viewer-next writes it
  (``utils/ping360.ts``: ``ceil(2.5 * sample_period * 25e-9 * 1e6)``), and so it is here.
- sweeping (Ping Viewer's ``legacyProfileRequest``): the head steps ``step_grad``
  gradians at a time; in a sector narrower than the circle it turns back at the edges
  (both edges included), and a head found outside the sector goes to its centre; a full
  circle goes round. A Ping360 steps 0.9 degrees (1 gradian); Ping Viewer offers 1-10.
"""

from __future__ import annotations

import contextlib
import io
import math
import struct
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import brping
import numpy as np
from brping import definitions

from cavenav.core.errors import ConfigError, VehicleError
from cavenav.vehicle.ping import HEADER, FakePingDevice, PingAddress

__all__ = [
    "FakePing360",
    "Ping360Settings",
    "Ping360Sonar",
    "Ping360Timing",
    "next_angle",
    "sonar_range_m",
    "transducer_timing",
]

UDP_PORT = 9092  # where BlueOS serves a Ping360
GRADIANS = 400  # a full turn of the head; one gradian is 0.9 degrees
TICK_S = 25e-9  # the unit of sample_period
MIN_SAMPLE_PERIOD, MAX_SAMPLE_PERIOD = 80, 40000  # ticks: 2 us to 1 ms
MIN_SAMPLES, MAX_SAMPLES = 200, 1200  # samples per ping the firmware supports
MIN_TRANSMIT_US, MAX_TRANSMIT_US = 5, 500  # the firmware clamps the pulse to these
MIN_RANGE_M, MAX_RANGE_M = 0.75, 50.0  # the sonar's specified range
PING360_MODE = 1  # "operating mode (1 for Ping360)"
PING360_DEVICE_TYPE = 2  # device_information.device_type of a Ping360
ANSWER_S = 4.0  # the protocol's advice for device_data's worst case (a long turn, 50 m)

PROTOCOL_VERSION = definitions.COMMON_PROTOCOL_VERSION
DEVICE_INFORMATION = definitions.COMMON_DEVICE_INFORMATION
NACK = definitions.COMMON_NACK
DEVICE_DATA = definitions.PING360_DEVICE_DATA
TRANSDUCER = definitions.PING360_TRANSDUCER

Ping = tuple[int, np.ndarray]  # (head angle in gradians, (n,) uint8 intensities)


def sonar_range_m(samples: int, sample_period_ticks: int, speed_of_sound: float) -> float:
    """The one-way range, metres: the sound travels there and back in samples * period."""
    return samples * sample_period_ticks * TICK_S * speed_of_sound / 2


def _sample_period(range_m: float, samples: int, speed_of_sound: float) -> int:
    """Ping Viewer's ``calculateSamplePeriod``, truncated to whole ticks. The nudge of
    1e-9 keeps an exact ratio (0.75 m over 500 samples is 80 ticks) from falling to
    79.999... and so a tick short."""
    return int(2 * range_m / (samples * speed_of_sound * TICK_S) + 1e-9)


def transducer_timing(range_m: float, max_samples: int, speed_of_sound: float) -> Ping360Timing:
    """The samples, sample period and transmit duration Ping Viewer picks for a range.

    As many samples as allowed (``max_samples``, at most 1200) for the finest range
    resolution, fewer where the sample period would fall below the firmware's 80 ticks;
    then the automatic transmit duration (see the module docstring).

    Raises:
        ConfigError: no sample period the firmware takes (80-40000 ticks) covers the range.
    """
    samples = max_samples
    period = _sample_period(range_m, samples, speed_of_sound)
    while period < MIN_SAMPLE_PERIOD and samples > MIN_SAMPLES:
        samples -= 1
        period = _sample_period(range_m, samples, speed_of_sound)
    if not MIN_SAMPLE_PERIOD <= period <= MAX_SAMPLE_PERIOD:
        raise ConfigError(
            f"Ping360 range {range_m} m over {max_samples} samples at {speed_of_sound} m/s: "
            f"a sample period of {period} ticks, where the sonar takes 80 to 40000"
        )
    period_us = period * TICK_S * 1e6
    duration = round(8000 * sonar_range_m(samples, period, speed_of_sound) / speed_of_sound)
    duration = max(math.ceil(2.5 * period_us - 1e-9), duration)
    longest = min(MAX_TRANSMIT_US, int(period_us * 64))
    duration = max(MIN_TRANSMIT_US, min(longest, duration))
    return Ping360Timing(samples, period, duration, speed_of_sound)


def _relative(angle: int) -> int:
    """An angle in gradians as an offset in [-200, 200)."""
    angle %= GRADIANS
    return angle - GRADIANS if angle >= GRADIANS // 2 else angle


def next_angle(angle_grad: int, direction: int, settings: Ping360Settings) -> tuple[int, int]:
    """Where the head pings next from ``angle_grad``, and the direction it then turns
    (+1 or -1), as Ping Viewer steps it (see the module docstring)."""
    step = direction * settings.step_grad
    if settings.sector_grad >= GRADIANS:
        return (angle_grad + step) % GRADIANS, direction
    half = settings.sector_grad // 2
    offset = _relative(angle_grad - settings.center_grad)

    def inside(steps: int) -> bool:
        return -half <= _relative(offset + steps) <= half

    if not inside(step):
        direction, step = -direction, -step
    if not inside(step):  # outside the sector altogether: to its centre
        return settings.center_grad, -direction
    return (settings.center_grad + offset + step) % GRADIANS, direction


def _message(message_id: int, **fields: Any) -> bytes:  # noqa: ANN401 - ints or bytes
    """A message of fixed length, packed by the library's own `PingMessage` (which, in
    bluerobotics-ping 0.2.5, cannot pack a NACK, nor a ``device_data`` with no data)."""
    message = brping.PingMessage(message_id, payload_dict=definitions.payload_dict_all)
    for name, value in fields.items():
        setattr(message, name, value)
    return bytes(message.pack_msg_data())


def _framed(message_id: int, payload: bytes) -> bytes:
    """A message from its payload: header, payload and the checksum (the sum of the
    bytes before it, modulo 2**16), for the messages of variable length."""
    body = HEADER.pack(b"BR", len(payload), message_id, 0, 0) + payload
    return body + struct.pack("<H", sum(body) & 0xFFFF)


def _open(device: Any, address: PingAddress) -> None:  # noqa: ANN401 - a brping device
    """Open the link and check that a Ping360 answers it.

    Raises:
        VehicleError: it cannot be opened, nothing answers, or what answers is no Ping360.
    """
    try:
        with contextlib.redirect_stdout(io.StringIO()):  # it prints "Opening ..."
            if address.kind == "udp":
                device.connect_udp(address.where, address.number)
            else:
                device.connect_serial(address.where, address.number)
    except Exception as exc:  # brping raises bare Exceptions
        raise VehicleError(f"Ping360 {address}: cannot open it ({exc})") from None
    try:
        answered = device.initialize()
        information = device.get_device_information() if answered else None
    except OSError as exc:  # UDP: nothing listens there (ICMP port unreachable)
        raise VehicleError(f"Ping360 {address}: {exc.strerror or exc}") from None
    if not answered:
        raise VehicleError(f"Ping360 {address}: no answer to the ping protocol")
    if information is None or information["device_type"] != PING360_DEVICE_TYPE:
        kind = "no device_information" if information is None else information["device_type"]
        raise VehicleError(f"Ping360 {address}: the device is no Ping360 (device type: {kind})")


@dataclass(frozen=True)
class Ping360Timing:
    """What a ``transducer`` request asks of the sonar for one range.

    Attributes:
        number_of_samples: intensities per ping.
        sample_period_ticks: the time between samples, in 25 ns ticks.
        transmit_duration_us: the length of the acoustic pulse, microseconds.
        speed_of_sound: m/s, the speed the range was computed with.
    """

    number_of_samples: int
    sample_period_ticks: int
    transmit_duration_us: int
    speed_of_sound: float

    @property
    def range_m(self) -> float:
        """The one-way range these samples cover (at most the range asked for: the
        sample period is truncated to whole ticks)."""
        return sonar_range_m(self.number_of_samples, self.sample_period_ticks, self.speed_of_sound)


@dataclass(frozen=True)
class Ping360Settings:
    """How the sonar pings and sweeps; each value is checked when made.

    Attributes:
        range_m: one-way range to sample, 0.75 to 50 m.
        gain: the receiver's analog gain: 0 low (the firmware's default), 1 normal, 2 high.
        max_samples: the most samples per ping (200-1200); short ranges get fewer (the
            sample period cannot go below 80 ticks).
        transmit_frequency_khz: 500-1000 kHz; the receiver's band makes 650-850 the
            practical part. 750 is Ping Viewer's default (the firmware boots at 740).
        speed_of_sound: m/s, for the range (Ping Viewer's default 1500; its manual
            gives about 1480 in fresh water at 20 C, 1520 in salt).
        sector_deg: the sector swept, degrees (360: all round).
        step_grad: gradians between pings (1-10; 1 gradian = 0.9 degrees).
        center_grad: the head angle the sector is centred on (Ping Viewer's angle offset:
            where the vehicle's forward is, as the sonar is mounted).
    """

    range_m: float = 10.0
    gain: int = 0
    max_samples: int = MAX_SAMPLES
    transmit_frequency_khz: int = 750
    speed_of_sound: float = 1500.0
    sector_deg: float = 360.0
    step_grad: int = 1
    center_grad: int = 0

    def __post_init__(self) -> None:
        """Raises:
        ConfigError: the first value out of bounds, in one line.
        """
        checks = [
            ("range_m", self.range_m, MIN_RANGE_M, MAX_RANGE_M, "m"),
            ("gain", self.gain, 0, 2, "(0 low, 1 normal, 2 high)"),
            ("max_samples", self.max_samples, MIN_SAMPLES, MAX_SAMPLES, "samples"),
            ("transmit_frequency_khz", self.transmit_frequency_khz, 500, 1000, "kHz"),
            ("speed_of_sound", self.speed_of_sound, 1000.0, 2000.0, "m/s"),
            ("sector_deg", self.sector_deg, 0.9, 360.0, "degrees"),
            ("step_grad", self.step_grad, 1, 10, "gradians"),
            ("center_grad", self.center_grad, 0, GRADIANS - 1, "gradians"),
        ]
        for name, value, low, high, unit in checks:
            whole = isinstance(low, int)  # a field of the protocol's integers
            number = isinstance(value, int if whole else int | float)
            if isinstance(value, bool) or not (number and low <= value <= high):
                kind = "a whole number, " if whole else ""
                raise ConfigError(f"Ping360 {name} {value!r}: give {kind}{low} to {high} {unit}")

    @property
    def sector_grad(self) -> int:
        """The sector in the head's gradians (360 degrees: 400, all round)."""
        return round(self.sector_deg * GRADIANS / 360)

    @property
    def timing(self) -> Ping360Timing:
        return transducer_timing(self.range_m, self.max_samples, self.speed_of_sound)


class Ping360Sonar:
    """One Ping360, connected and checked, and where its head last pinged.

    The head's state (its angle and the way it turns) lives here, so that successive
    `sweep` calls go on where the last one stopped. ``settings`` may be replaced between
    pings (a frozen `Ping360Settings`); the next ping uses them.
    """

    def __init__(
        self,
        address: PingAddress,
        settings: Ping360Settings | None = None,
        answer_s: float = ANSWER_S,
    ):
        """``answer_s``: how long to wait for each ping's answer (4 s by default, what
        the protocol advises for the worst case).

        Raises:
            VehicleError: the device cannot be opened, does not answer, or is no Ping360.
        """
        self.address, self.answer_s = address, answer_s
        self.settings = settings or Ping360Settings()
        self.device = brping.Ping360(payload_dict=definitions.payload_dict_ping360)
        try:
            _open(self.device, address)
        except VehicleError:
            self.close()
            raise
        self.angle_grad: int = int(getattr(self.device, "_angle", 0)) % GRADIANS
        self.direction = 1

    @classmethod
    def connect(cls, text: str, settings: Ping360Settings | None = None) -> Ping360Sonar:
        """The sonar at ``udp:HOST:PORT`` or ``serial:DEVICE[:BAUD]``.

        Raises:
            ConfigError: the address is malformed.
            VehicleError: as `Ping360Sonar`.
        """
        try:
            address = PingAddress.parse(text)
        except ConfigError:
            raise ConfigError(
                f"Ping360 address {text!r}: give udp:HOST:PORT (BlueOS serves it on "
                f"udp:192.168.2.2:{UDP_PORT}) or serial:DEVICE[:BAUD]"
            ) from None
        return cls(address, settings)

    def ping(self, angle_grad: int) -> Ping:
        """Turn the head to ``angle_grad`` (taken modulo 400), transmit, and return
        (the angle, the intensities: (n,) uint8, nearest first).

        Raises:
            VehicleError: no answer in ``answer_s``, a refusal (NACK), or an answer with
                other samples than asked.
        """
        angle, timing = angle_grad % GRADIANS, self.settings.timing
        try:
            self.device.control_transducer(
                PING360_MODE,
                self.settings.gain,
                angle,
                timing.transmit_duration_us,
                timing.sample_period_ticks,
                self.settings.transmit_frequency_khz,
                timing.number_of_samples,
                1,  # transmit
                0,  # reserved
            )
            data = self._answer(angle)
        except OSError as exc:
            raise VehicleError(f"Ping360 {self.address}: {exc.strerror or exc}") from None
        if len(data) != timing.number_of_samples:
            raise VehicleError(
                f"Ping360 {self.address}: {len(data)} samples at {angle} gradians, "
                f"asked for {timing.number_of_samples}"
            )
        self.angle_grad = angle
        return angle, np.frombuffer(bytes(data), dtype=np.uint8).copy()

    def _answer(self, angle: int) -> bytes:
        """The data of the ``device_data`` at ``angle``; an answer to an earlier request
        that came late (another angle) is passed over."""
        deadline = time.monotonic() + self.answer_s
        while (left := deadline - time.monotonic()) > 0:
            message = self.device.wait_message([DEVICE_DATA, NACK], left)
            if message is None:
                break
            if message.message_id == NACK:
                why = bytes(message.nack_message).decode("ascii", "replace").strip("\x00")
                raise VehicleError(f"Ping360 {self.address}: refused the ping ({why})")
            if message.angle == angle:
                return bytes(message.data)
        raise VehicleError(
            f"Ping360 {self.address}: no device_data at {angle} gradians within {self.answer_s:g} s"
        )

    def sweep(self, count: int) -> list[Ping]:
        """The next ``count`` pings of the sector, going on from where the head is.

        Raises:
            VehicleError: as `ping`.
        """
        pings = []
        for _ in range(count):
            angle, self.direction = next_angle(self.angle_grad, self.direction, self.settings)
            pings.append(self.ping(angle))
        return pings

    def close(self) -> None:
        iodev = getattr(self.device, "iodev", None)
        if iodev is not None:
            iodev.close()


Echo = Callable[[float, int, float], np.ndarray]  # (angle_deg, samples, range_m) -> uint8


@dataclass
class _Head:
    """The fake sonar's state: what the last ``transducer`` request set."""

    gain_setting: int = 0
    angle: int = 0
    transmit_duration: int = 32  # the firmware's boot defaults (Ping Viewer's list)
    sample_period: int = 80
    transmit_frequency: int = 740
    number_of_samples: int = 1024


class FakePing360(FakePingDevice):
    """A Ping360 that answers in the ping protocol's own messages: its protocol version,
    its device information (type 2), ``device_data`` on request, and a ``transducer``
    request with ``device_data`` whose intensities ``echo`` draws:
    ``echo(angle_deg, number_of_samples, range_m)`` -> (number_of_samples,) uint8, the
    range from the request's samples and sample period at ``speed_of_sound``. An echo of
    another length is answered with a NACK, as the sonar refuses what it cannot do.

    See `FakePingDevice` for its use; ``pings`` lists the head angles transmitted.
    """

    name = "Ping360"

    def __init__(self, echo: Echo, port: int = 0, speed_of_sound: float = 1500.0):
        """
        Raises:
            ConfigError: the port is taken.
        """
        self.echo, self.speed_of_sound = echo, speed_of_sound
        self.pings: list[int] = []
        self.head = _Head()
        super().__init__(port)

    def _answer(self, message_id: int, payload: bytes) -> bytes | None:
        """A ``transducer`` request sets the head and may transmit."""
        if message_id == PROTOCOL_VERSION:
            return _message(PROTOCOL_VERSION, version_major=1, version_minor=0)
        if message_id == DEVICE_INFORMATION:
            return _message(
                DEVICE_INFORMATION,
                device_type=PING360_DEVICE_TYPE,
                firmware_version_major=3,
                firmware_version_minor=3,
            )
        if message_id == DEVICE_DATA:
            return self._device_data(b"")
        if message_id == TRANSDUCER and len(payload) >= 14:
            return self._transduce(payload)
        return None

    def _transduce(self, payload: bytes) -> bytes:
        fields = struct.unpack_from("<BBHHHHHBB", payload)
        mode, gain, angle, duration, period, frequency, samples, transmit, _ = fields
        self.head = _Head(gain, angle % GRADIANS, duration, period, frequency, samples)
        if not transmit:
            return self._device_data(b"")
        range_m = sonar_range_m(samples, period, self.speed_of_sound)
        echo = np.asarray(self.echo(angle * 360 / GRADIANS, samples, range_m))
        if echo.shape != (samples,) or echo.dtype != np.uint8:
            why = f"echo gave {echo.dtype} {echo.shape}, wanted uint8 ({samples},)"
            return _framed(NACK, struct.pack("<H", TRANSDUCER) + why.encode("ascii"))
        self.pings.append(self.head.angle)
        return self._device_data(echo.tobytes())

    def _device_data(self, data: bytes) -> bytes:
        """The head's state and ``data``, in the library's own layout of the message."""
        head = self.head
        fixed = struct.pack(
            "<" + definitions.payload_dict_ping360[DEVICE_DATA]["format"],
            PING360_MODE,
            head.gain_setting,
            head.angle,
            head.transmit_duration,
            head.sample_period,
            head.transmit_frequency,
            head.number_of_samples,
            len(data),
        )
        return _framed(DEVICE_DATA, fixed + data)
