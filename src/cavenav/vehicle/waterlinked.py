"""A Water Linked DVL A50 (Doppler velocity log), read over its TCP JSON API.

A DVL measures the vehicle's velocity over the bottom (or a wall) with four acoustic
beams, and the distance each beam travels to it; that is what a cave robot without
GNSS has to reckon its position with. The A50 serves a TCP server on port 16171 that
streams newline-delimited JSON reports and answers JSON commands. `WaterLinkedDvl`
keeps the latest velocity and dead-reckoning reports from a background thread;
`FakeDvl` serves the same reports on 127.0.0.1 from an injected measurement, for tests
and for flying the loop without a vehicle.

The protocol facts this relies on come from Water Linked's own documentation, "DVL
A50/A125 TCP JSON API" (github.com/waterlinked/docs, ``docs/dvl/dvl-json-protocol.md``,
describing ``json_v3.3``; published at docs.waterlinked.com/dvl/dvl-json-protocol/), and
their parser ``tcp/dvl_tcp_parser.py`` in github.com/waterlinked/dvl-python:

- port 16171; one JSON object per report, delimited by newline (the parser splits the
  stream on ``\\r\\n``); commands are JSON objects, ``{"command": NAME}`` with an optional
  ``"parameters"`` object, sent with no delimiter (Water Linked's ROS driver and
  examples send them bare).
- velocity-and-transducer report, ``"type": "velocity"``: ``time`` (ms since the last
  velocity report), ``vx``, ``vy``, ``vz`` (m/s), ``fom`` (figure of merit, m/s),
  ``covariance`` (3x3 list, (m/s)^2), ``altitude`` (m, along Z), ``transducers`` (a list
  of objects ``id`` 0-3, ``velocity`` m/s, ``distance`` m, ``rssi`` dBm, ``nsd`` dBm,
  ``beam_valid`` bool), ``velocity_valid`` (bool: a lock on the surface, so the
  altitude and velocities are valid), ``status`` (bit 0: too hot), ``format``
  (``json_v3.3``), ``time_of_validity`` and ``time_of_transmission`` (Unix time in
  microseconds). Sent at 2-15 Hz, depending on the altitude. ``"type":
  "velocity_water"`` (water tracking, json_v3.2) is the velocity through the water, not
  over the ground: it is not taken for `WaterLinkedDvl.latest`.
- axes (``docs/dvl/axes.md``): x forward, y right (starboard), z down, toward the
  transducers; the vehicle frame when a mounting rotation offset is set.
- dead reckoning report, ``"type": "position_local"``: ``ts`` (Unix time, s), ``x``,
  ``y``, ``z`` (m, z down, from where dead reckoning was last reset), ``std`` (m),
  ``roll``, ``pitch``, ``yaw`` (degrees), ``status`` (0: no errors), ``format``. About 5 Hz.
- responses: ``response_to`` (the command), ``success``, ``error_message`` (non-empty
  when it failed), ``result`` (null, or the command's answer: ``get_config`` gives
  ``speed_of_sound``, ``acoustic_enabled``, ``dark_mode_enabled``,
  ``mounting_rotation_offset``, ``range_mode``, ``periodic_cycling_enabled``),
  ``format``, ``"type": "response"``. ``reset_dead_reckoning`` zeroes the position
  (after about 50 ms) and the roll, pitch and yaw.
"""

from __future__ import annotations

import contextlib
import json
import math
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, fields
from types import TracebackType
from typing import Any

import numpy as np

from cavenav.core.errors import ConfigError, VehicleError

__all__ = ["DvlAddress", "DvlPosition", "DvlVelocity", "FakeDvl", "WaterLinkedDvl"]

TCP_PORT = 16171
FORMAT = "json_v3.3"
BEAMS = 4
LONGEST_LINE = 1 << 16  # a report is about 1 kB; more without a newline is no report
SHAPES: dict[str, tuple[int, ...]] = {  # DvlVelocity's arrays
    "velocity": (3,),
    "beam_distances_m": (BEAMS,),
    "beam_valid": (BEAMS,),
    "covariance": (3, 3),
    "beam_velocities": (BEAMS,),
    "rssi_dbm": (BEAMS,),
    "nsd_dbm": (BEAMS,),
}
DEFAULT_CONFIG = {  # the documentation's example of get_config, mounted straight
    "speed_of_sound": 1475.0,
    "acoustic_enabled": True,
    "dark_mode_enabled": False,
    "mounting_rotation_offset": 0.0,
    "range_mode": "auto",
    "periodic_cycling_enabled": True,
}


@dataclass(frozen=True)
class DvlAddress:
    """Where the DVL's TCP JSON API answers."""

    host: str
    port: int = TCP_PORT

    @classmethod
    def parse(cls, text: str) -> DvlAddress:
        """``tcp:HOST[:PORT]`` (port 16171 by default).

        Raises:
            ConfigError: anything else, in one line.
        """
        kind, _, rest = text.partition(":")
        host, colon, port = rest.rpartition(":") if ":" in rest else (rest, "", "")
        try:
            number = int(port) if colon else TCP_PORT
        except ValueError:
            number = 0
        if kind == "tcp" and host and " " not in host and 0 < number < 65536:
            return cls(host, number)
        raise ConfigError(
            f"DVL address {text!r}: give tcp:HOST[:PORT] (a DVL A50 listens on port "
            f"{TCP_PORT}; its fallback address is 192.168.194.95)"
        )

    def __str__(self) -> str:
        return f"tcp:{self.host}:{self.port}"


def _malformed(kind: str, problem: str) -> VehicleError:
    return VehicleError(f"DVL {kind} report: {problem}")


def _check_type(report: Any, kind: str) -> None:  # noqa: ANN401 - parsed JSON
    if not isinstance(report, dict):
        raise _malformed(kind, f"a JSON {type(report).__name__}, not an object")
    if report.get("type") != kind:
        raise _malformed(kind, f"field 'type' is {report.get('type')!r}, not {kind!r}")


def _number(report: dict, key: str, kind: str) -> float:
    """A finite number from the report (JSON's true and false are not numbers)."""
    value = report.get(key)
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise _malformed(kind, f"field {key!r} is {value!r}, not a number")
    return float(value)


def _flag(report: dict, key: str, kind: str) -> bool:
    value = report.get(key)
    if not isinstance(value, bool):
        raise _malformed(kind, f"field {key!r} is {value!r}, not true or false")
    return value


def _covariance(report: dict) -> np.ndarray | None:
    """The 3x3 covariance, or None where the report has none (null or absent)."""
    value = report.get("covariance")
    if value is None:
        return None
    rows = value if isinstance(value, list) and len(value) == 3 else None
    if rows is None or not all(isinstance(row, list) and len(row) == 3 for row in rows):
        raise _malformed("velocity", f"field 'covariance' is {value!r}, not a 3x3 list")
    cells = [{"c": cell} for row in rows for cell in row]
    return np.array([_number(cell, "c", "velocity") for cell in cells]).reshape(3, 3)


def _beams(report: dict) -> dict[str, np.ndarray | None]:
    """The transducers' list as (4,) arrays, in the order of their ``id`` (0-3)."""
    beams = report.get("transducers")
    if not isinstance(beams, list) or len(beams) != BEAMS:
        raise _malformed("velocity", f"field 'transducers' is {beams!r}, not a list of 4")
    ordered: list[dict] = [{}] * BEAMS
    for beam in beams:
        number = beam.get("id") if isinstance(beam, dict) else None
        # type() rather than isinstance: JSON's true is an int to Python, and no id
        if type(number) is not int or not 0 <= number < BEAMS or ordered[number]:
            raise _malformed("velocity", f"transducer {beam!r}: no id 0-3 of its own")
        ordered[number] = beam
    kind = "velocity transducer"
    optional = {"velocity": "beam_velocities", "rssi": "rssi_dbm", "nsd": "nsd_dbm"}
    arrays: dict[str, np.ndarray | None] = {
        "beam_distances_m": np.array([_number(b, "distance", kind) for b in ordered]),
        "beam_valid": np.array([_flag(b, "beam_valid", kind) for b in ordered]),
    }
    for key, name in optional.items():  # null where the fake models none of them
        given = [b.get(key) is not None for b in ordered]
        arrays[name] = np.array([_number(b, key, kind) for b in ordered]) if any(given) else None
    return arrays


def _array(value: Any, shape: tuple[int, ...], dtype: type) -> np.ndarray:  # noqa: ANN401
    array: np.ndarray = np.asarray(value, dtype=dtype)
    if array.shape != shape:
        raise ValueError(f"an array of shape {shape} is needed, not {array.shape}")
    return array


def _optional(values: np.ndarray | None, index: int) -> float | None:
    return None if values is None else float(values[index])


def _json_line(report: dict) -> bytes:
    """One report as the DVL sends it: compact JSON, then CR LF."""
    return json.dumps(report, separators=(",", ":"), allow_nan=False).encode() + b"\r\n"


def _response(name: str, success: bool, error: str = "", result: Any = None) -> dict:  # noqa: ANN401
    return {
        "response_to": name,
        "success": success,
        "error_message": error,
        "result": result,
        "format": FORMAT,
        "type": "response",
    }


@dataclass(frozen=True, eq=False)
class DvlVelocity:
    """One velocity-and-transducer report.

    Attributes:
        time_s: when the velocity holds (the report's time of validity), Unix seconds.
        velocity: (3,) m/s, vx vy vz in the DVL's frame (x forward, y right, z down).
        valid: the DVL has a lock on the surface; else velocity and altitude mean nothing.
        fom: figure of merit, m/s (how accurate the velocity is).
        altitude_m: the distance to the surface along z, m.
        beam_distances_m: (4,) each transducer's distance to the surface, m (id order).
        beam_valid: (4,) bool, each transducer's lock.
        covariance: (3, 3) of the velocity, (m/s)^2; None where not given.
        beam_velocities: (4,) m/s along each beam; None where not modelled.
        rssi_dbm, nsd_dbm: (4,) received signal strength and noise; None where not modelled.
        status: the DVL's status bits (bit 0: too hot, it will soon shut down).
    """

    time_s: float
    velocity: np.ndarray
    valid: bool
    fom: float
    altitude_m: float
    beam_distances_m: np.ndarray
    beam_valid: np.ndarray
    covariance: np.ndarray | None = None
    beam_velocities: np.ndarray | None = None
    rssi_dbm: np.ndarray | None = None
    nsd_dbm: np.ndarray | None = None
    status: int = 0

    def __post_init__(self) -> None:
        """The arrays as float (bool) arrays of their shapes; every number finite, as
        the report's JSON carries numbers only.

        Raises:
            ValueError: a wrong shape or a value that is not finite (NaN), naming it.
        """
        for name, shape in SHAPES.items():
            value = getattr(self, name)
            if value is not None:
                array = _array(value, shape, bool if name == "beam_valid" else float)
                if not np.all(np.isfinite(array)):
                    raise ValueError(f"DvlVelocity.{name} {value!r}: give finite numbers")
                object.__setattr__(self, name, array)
        for name in ("time_s", "fom", "altitude_m"):
            if not math.isfinite(getattr(self, name)):
                raise ValueError(f"DvlVelocity.{name} {getattr(self, name)!r}: give a number")

    def __eq__(self, other: object) -> bool:
        """Field by field, the arrays by value."""
        if not isinstance(other, DvlVelocity):
            return NotImplemented
        pairs = ((getattr(self, f.name), getattr(other, f.name)) for f in fields(self))
        return all(
            np.array_equal(a, b)
            if isinstance(a, np.ndarray) or isinstance(b, np.ndarray)
            else a == b
            for a, b in pairs
        )

    def to_report(self, *, time_ms: float = 0.0, sent_s: float | None = None) -> dict:
        """The json_v3 report the DVL sends for this velocity.

        Args:
            time_ms: milliseconds since the previous velocity report.
            sent_s: when it is sent, Unix seconds (None: at its time of validity).
        """
        beams = [
            {
                "id": index,
                "velocity": _optional(self.beam_velocities, index),
                "distance": float(self.beam_distances_m[index]),
                "rssi": _optional(self.rssi_dbm, index),
                "nsd": _optional(self.nsd_dbm, index),
                "beam_valid": bool(self.beam_valid[index]),
            }
            for index in range(BEAMS)
        ]
        vx, vy, vz = (float(v) for v in self.velocity)
        return {
            "time": float(time_ms),
            "vx": vx,
            "vy": vy,
            "vz": vz,
            "fom": float(self.fom),
            "covariance": None if self.covariance is None else self.covariance.tolist(),
            "altitude": float(self.altitude_m),
            "transducers": beams,
            "velocity_valid": bool(self.valid),
            "status": int(self.status),
            "format": FORMAT,
            "type": "velocity",
            "time_of_validity": round(self.time_s * 1e6),
            "time_of_transmission": round((self.time_s if sent_s is None else sent_s) * 1e6),
        }

    @classmethod
    def from_report(cls, report: Any) -> DvlVelocity:  # noqa: ANN401 - parsed JSON
        """The velocity a json_v3 ``velocity`` report carries.

        Raises:
            VehicleError: the report is malformed (a field missing or of the wrong
                kind), in one line naming the field.
        """
        _check_type(report, "velocity")
        status = report.get("status", 0)
        if isinstance(status, bool) or not isinstance(status, int):
            raise _malformed("velocity", f"field 'status' is {status!r}, not an integer")
        return cls(
            time_s=_number(report, "time_of_validity", "velocity") / 1e6,
            velocity=np.array([_number(report, key, "velocity") for key in ("vx", "vy", "vz")]),
            valid=_flag(report, "velocity_valid", "velocity"),
            fom=_number(report, "fom", "velocity"),
            altitude_m=_number(report, "altitude", "velocity"),
            covariance=_covariance(report),
            status=status,
            **_beams(report),  # type: ignore[arg-type]
        )


@dataclass(frozen=True, eq=False)
class DvlPosition:
    """One dead reckoning report: where the DVL is since dead reckoning was last reset.

    Attributes:
        time_s: the report's time stamp, Unix seconds.
        position: (3,) x, y, z in metres, in the frame the DVL had at the reset (z down).
        std_m: the position's standard deviation (figure of merit), m.
        roll_deg, pitch_deg, yaw_deg: the DVL's attitude since the reset, degrees.
        status: 0 when the DVL reports no error.
    """

    time_s: float
    position: np.ndarray
    std_m: float
    roll_deg: float = 0.0
    pitch_deg: float = 0.0
    yaw_deg: float = 0.0
    status: int = 0

    def __post_init__(self) -> None:
        object.__setattr__(self, "position", _array(self.position, (3,), float))

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, DvlPosition):
            return NotImplemented
        mine, theirs = self.to_report(), other.to_report()
        return mine == theirs

    def to_report(self) -> dict:
        """The json_v3 ``position_local`` report."""
        x, y, z = (float(v) for v in self.position)
        return {
            "ts": float(self.time_s),
            "x": x,
            "y": y,
            "z": z,
            "std": float(self.std_m),
            "roll": float(self.roll_deg),
            "pitch": float(self.pitch_deg),
            "yaw": float(self.yaw_deg),
            "type": "position_local",
            "status": int(self.status),
            "format": FORMAT,
        }

    @classmethod
    def from_report(cls, report: Any) -> DvlPosition:  # noqa: ANN401 - parsed JSON
        """The position a ``position_local`` report carries.

        Raises:
            VehicleError: the report is malformed, in one line naming the field.
        """
        _check_type(report, "position_local")
        kind = "position_local"
        return cls(
            time_s=_number(report, "ts", kind),
            position=np.array([_number(report, key, kind) for key in ("x", "y", "z")]),
            std_m=_number(report, "std", kind),
            roll_deg=_number(report, "roll", kind),
            pitch_deg=_number(report, "pitch", kind),
            yaw_deg=_number(report, "yaw", kind),
            status=int(_number(report, "status", kind)),
        )


class WaterLinkedDvl:
    """A connection to a DVL's TCP JSON API, read all the time by a thread that keeps
    the latest velocity and dead reckoning reports.

    A malformed report is not dropped in silence: the next call to `latest`,
    `latest_position` or `next_velocity` raises it (once; the stream goes on). A
    connection the DVL closes is raised by every call after.
    """

    def __init__(self, connection: socket.socket, address: DvlAddress):
        """Take over an open connection; `connect` opens one."""
        self.address = address
        self._socket = connection
        self._changed = threading.Condition()
        self._velocity: DvlVelocity | None = None
        self._position: DvlPosition | None = None
        self._velocities = self._reports = 0
        self._responses: list[dict] = []
        self._problem: VehicleError | None = None
        self._lost: VehicleError | None = None
        self._closing = False
        self._thread = threading.Thread(target=self._read, daemon=True)
        self._thread.start()

    @classmethod
    def connect(cls, address: str | DvlAddress, timeout_s: float = 3.0) -> WaterLinkedDvl:
        """Connect and wait for the DVL's first report.

        Raises:
            ConfigError: the address is malformed.
            VehicleError: the connection is refused or times out, or no report comes
                within ``timeout_s``.
        """
        where = DvlAddress.parse(address) if isinstance(address, str) else address
        try:
            connection = socket.create_connection((where.host, where.port), timeout=timeout_s)
        except OSError as exc:
            raise VehicleError(f"DVL {where}: {exc.strerror or exc}") from None
        connection.settimeout(None)
        dvl = cls(connection, where)
        with dvl._changed:
            dvl._changed.wait_for(lambda: dvl._reports or dvl._lost, timeout_s)
            lost, silent = dvl._lost, not dvl._reports
        if lost or silent:
            dvl.close()
            raise lost or VehicleError(f"DVL {where}: no report within {timeout_s:g} s")
        return dvl

    def __enter__(self) -> WaterLinkedDvl:
        return self

    def __exit__(
        self,
        kind: type[BaseException] | None,
        error: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def _read(self) -> None:
        """Split the stream into lines and take each; stop when the connection ends."""
        pending = b""
        while True:
            try:
                chunk = self._socket.recv(65536)
            except OSError:
                chunk = b""
            if not chunk:
                break
            *lines, pending = (pending + chunk).split(b"\n")
            for line in lines:
                self._take(line.strip())
            if len(pending) > LONGEST_LINE:
                self._complain(f"{len(pending)} bytes with no newline")
                pending = b""
        with self._changed:
            if not self._closing:
                self._lost = VehicleError(f"DVL {self.address}: the DVL closed the connection")
            self._changed.notify_all()

    def _take(self, line: bytes) -> None:
        if not line:
            return
        try:
            report = json.loads(line)
        except ValueError:  # JSONDecodeError, UnicodeDecodeError
            self._complain(f"a report that is no JSON: {line[:60]!r}")
            return
        kind = report.get("type") if isinstance(report, dict) else None
        try:
            velocity = DvlVelocity.from_report(report) if kind == "velocity" else None
            position = DvlPosition.from_report(report) if kind == "position_local" else None
        except VehicleError as error:  # "DVL velocity report: ..."
            self._complain(str(error).removeprefix("DVL "))
            return
        with self._changed:
            self._reports += 1
            if velocity is not None:
                self._velocity, self._velocities = velocity, self._velocities + 1
            if position is not None:
                self._position = position
            if kind == "response":
                self._responses.append(report)
            self._changed.notify_all()

    def _complain(self, problem: str) -> None:
        with self._changed:
            self._problem = VehicleError(f"DVL {self.address}: {problem}")
            self._changed.notify_all()

    def _check(self) -> None:
        """Raise what the reader found (call holding ``_changed``)."""
        problem, self._problem = self._problem, None
        if problem is not None:
            raise problem
        if self._lost is not None:
            raise self._lost

    def latest(self) -> DvlVelocity | None:
        """The latest velocity report; None before the first.

        Raises:
            VehicleError: a malformed report came since the last call, or the DVL closed
                the connection.
        """
        with self._changed:
            self._check()
            return self._velocity

    def latest_position(self) -> DvlPosition | None:
        """The latest dead reckoning report; None before the first.

        Raises:
            VehicleError: as `latest`.
        """
        with self._changed:
            self._check()
            return self._position

    def next_velocity(self, timeout_s: float = 1.0) -> DvlVelocity:
        """The first velocity report that comes after this call.

        Raises:
            VehicleError: none within ``timeout_s``, or as `latest`.
        """
        with self._changed:
            seen = self._velocities
            self._check()
            deadline = time.monotonic() + timeout_s
            while self._velocities == seen:
                left = deadline - time.monotonic()
                if left <= 0:
                    raise VehicleError(
                        f"DVL {self.address}: no velocity report within {timeout_s:g} s"
                    )
                self._changed.wait(left)
                self._check()
            assert self._velocity is not None
            return self._velocity

    def command(self, name: str, parameters: dict | None = None, timeout_s: float = 2.0) -> Any:  # noqa: ANN401
        """Send a command and wait for its response; its ``result`` (often None).

        Raises:
            VehicleError: no response within ``timeout_s``, or the DVL answers that it
                failed (with its ``error_message``).
        """
        message: dict[str, Any] = {"command": name}
        if parameters is not None:
            message["parameters"] = parameters
        with self._changed:
            self._responses = [r for r in self._responses if r.get("response_to") != name]
        try:
            self._socket.sendall(json.dumps(message).encode())
        except OSError as exc:
            raise VehicleError(f"DVL {self.address}: {name}: {exc.strerror or exc}") from None
        with self._changed:
            answered = self._changed.wait_for(
                lambda: self._lost or any(r.get("response_to") == name for r in self._responses),
                timeout_s,
            )
            if self._lost is not None:
                raise self._lost
            if not answered:
                raise VehicleError(f"DVL {self.address}: no response to {name} in {timeout_s:g} s")
            response = next(r for r in self._responses if r.get("response_to") == name)
            self._responses.remove(response)
        if response.get("success") is not True:
            why = response.get("error_message") or "no reason given"
            raise VehicleError(f"DVL {self.address}: {name} failed: {why}")
        return response.get("result")

    def reset_dead_reckoning(self, timeout_s: float = 2.0) -> None:
        """Zero the dead-reckoned position and attitude (the DVL takes about 50 ms more
        to apply it).

        Raises:
            VehicleError: as `command`.
        """
        self.command("reset_dead_reckoning", timeout_s=timeout_s)

    def get_config(self, timeout_s: float = 2.0) -> dict:
        """The DVL's configuration (speed_of_sound, acoustic_enabled, range_mode, ...).

        Raises:
            VehicleError: as `command`, or the result is no object.
        """
        result = self.command("get_config", timeout_s=timeout_s)
        if not isinstance(result, dict):
            raise VehicleError(f"DVL {self.address}: get_config gave {result!r}, not an object")
        return result

    def close(self) -> None:
        with self._changed:
            self._closing = True
        with contextlib.suppress(OSError):  # not connected any more
            self._socket.shutdown(socket.SHUT_RDWR)  # wakes the reader's recv
        self._socket.close()
        if self._thread is not threading.current_thread():
            self._thread.join(timeout=2.0)


class FakeDvl:
    """A DVL A50 on 127.0.0.1 (TCP): it streams a velocity report from ``measure()`` at
    ``rate_hz`` to every client, dead-reckons from the valid ones (position plus velocity
    times the time between reports; no attitude, so roll, pitch and yaw stay 0) and
    sends that as ``position_local`` at about 5 Hz, and answers ``reset_dead_reckoning``,
    ``get_config`` and ``set_config`` as the real unit does (any other command: success
    false). The time between reports is ``measure()``'s own (its ``time_s``).

    Use as a context manager; ``address`` is where it listens (``tcp:127.0.0.1:PORT``),
    ``commands`` lists the commands received. An exception from ``measure`` stops the
    stream, and leaving the context raises it.
    """

    def __init__(
        self,
        measure: Callable[[], DvlVelocity],
        rate_hz: float = 8.0,
        port: int = 0,
        clock: Callable[[], float] = time.time,
    ):
        """``port``: where to listen on 127.0.0.1 (0: a free port the system picks);
        ``clock``: Unix time for ``time_of_transmission`` and the position's ``ts``.

        Raises:
            ConfigError: the port is taken.
        """
        self.measure, self.rate_hz, self.clock = measure, rate_hz, clock
        self.config = dict(DEFAULT_CONFIG)
        self.commands: list[str] = []
        self.position = np.zeros(3)
        self._variance = 0.0
        self._last_s: float | None = None
        self._lock = threading.Lock()
        self._clients: list[socket.socket] = []
        self._error: BaseException | None = None
        self._server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        try:
            self._server.bind(("127.0.0.1", port))
        except OSError as exc:
            self._server.close()
            raise ConfigError(f"a fake DVL cannot listen on TCP port {port}: {exc}") from None
        self._server.listen()
        self._server.settimeout(0.1)
        self._stop = threading.Event()
        self._threads = [
            threading.Thread(target=self._accept, daemon=True),
            threading.Thread(target=self._stream, daemon=True),
        ]

    @property
    def address(self) -> str:
        return f"tcp:127.0.0.1:{self._server.getsockname()[1]}"

    def __enter__(self) -> FakeDvl:
        for thread in self._threads:
            thread.start()
        return self

    def __exit__(
        self,
        kind: type[BaseException] | None,
        error: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self._stop.set()
        for thread in list(self._threads):
            thread.join()
        with self._lock:
            for client in self._clients:
                client.close()
        self._server.close()
        if self._error is not None and error is None:
            raise self._error

    def send_line(self, text: str) -> None:
        """Send a raw line to every client (what a faulty unit might send)."""
        self._send(text.encode() + b"\r\n")

    def _send(self, data: bytes) -> None:
        with self._lock:
            for client in list(self._clients):
                try:
                    client.sendall(data)
                except OSError:  # the client went away
                    self._clients.remove(client)
                    client.close()

    def _accept(self) -> None:
        while not self._stop.is_set():
            try:
                client, _ = self._server.accept()
            except TimeoutError:
                continue
            client.settimeout(0.1)
            with self._lock:
                self._clients.append(client)
            listener = threading.Thread(target=self._listen, args=(client,), daemon=True)
            self._threads.append(listener)
            listener.start()

    def _stream(self) -> None:
        """A velocity report every 1 / rate_hz; a position report when 0.2 s have passed."""
        position_due = 0.0
        while not self._stop.is_set():
            try:
                velocity = self.measure()
                report = self._reckon(velocity)
            except Exception as error:  # handed to the test at the end of the context
                self._error = error
                return
            self._send(_json_line(report))
            if time.monotonic() >= position_due:
                position_due = time.monotonic() + 0.2
                self._send(_json_line(self.dead_reckoning().to_report()))
            self._stop.wait(1.0 / self.rate_hz)

    def _reckon(self, velocity: DvlVelocity) -> dict:
        """Add a valid velocity times the time since the last report to the position,
        and (fom times that time) squared to its variance; the report to send."""
        with self._lock:
            elapsed = 0.0 if self._last_s is None else velocity.time_s - self._last_s
            self._last_s = velocity.time_s
            if velocity.valid and elapsed > 0:
                self.position = self.position + velocity.velocity * elapsed
                self._variance += (velocity.fom * elapsed) ** 2
        return velocity.to_report(time_ms=elapsed * 1000, sent_s=self.clock())

    def dead_reckoning(self) -> DvlPosition:
        """The position the fake has reckoned since its last reset."""
        with self._lock:
            return DvlPosition(self.clock(), self.position.copy(), math.sqrt(self._variance))

    def _listen(self, client: socket.socket) -> None:
        """Take the client's commands: JSON objects, delimited or not."""
        pending, decoder = "", json.JSONDecoder()
        while not self._stop.is_set():
            try:
                chunk = client.recv(4096)
            except TimeoutError:
                continue
            except OSError:
                return
            if not chunk:
                return
            pending += chunk.decode("utf-8", "replace")
            while pending.strip():
                try:
                    message, end = decoder.raw_decode(pending.lstrip())
                except ValueError:
                    break  # not whole yet
                pending = pending.lstrip()[end:]
                self._send_to(client, _json_line(self._answer(message)))

    def _send_to(self, client: socket.socket, data: bytes) -> None:
        with self._lock, contextlib.suppress(OSError):  # gone: _send drops it
            client.sendall(data)

    def _answer(self, message: Any) -> dict:  # noqa: ANN401 - parsed JSON
        """The response to one command."""
        name = message.get("command") if isinstance(message, dict) else None
        if not isinstance(name, str):
            return _response("", False, f"not a command: {str(message)[:80]}")
        self.commands.append(name)
        if name == "reset_dead_reckoning":
            with self._lock:
                self.position, self._variance = np.zeros(3), 0.0
            return _response(name, True)
        if name == "get_config":
            return _response(name, True, result=dict(self.config))
        if name == "set_config":
            parameters = message.get("parameters")
            if not isinstance(parameters, dict) or set(parameters) - set(self.config):
                known = ", ".join(self.config)
                return _response(name, False, f"parameters {parameters!r}: give some of {known}")
            self.config.update(parameters)
            return _response(name, True)
        return _response(name, False, f"unknown command: {name}")
