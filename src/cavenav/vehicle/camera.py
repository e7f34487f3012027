"""A BlueROV2's camera, read from the video stream BlueOS serves, with PyAV (FFmpeg).

BlueOS's camera manager streams the forward camera as H.264 in two ways: RTP over UDP to
the topside computer (port 5600 by default) and RTSP (``rtsp://blueos.local:8554/...``).
`CameraAddress` names either: ``udp:PORT`` (RTP carrying H.264 with payload type 96,
what a GStreamer ``rtph264pay`` sends; FFmpeg reads raw RTP through a session
description, which `VideoCamera` writes itself) or an ``rtsp://`` URL (over TCP, which
survives a tether's lost datagrams); any other URL or file FFmpeg opens is taken as is.

A live stream must be read all the time or its frames queue up and go stale: a thread of
`VideoCamera` decodes every frame and keeps only the latest with the time it was decoded,
and `frame_after` waits for the first frame decoded ``latency_s`` or more after a given
moment (a move's end). The stream carries no clock shared with this machine, so the
latency from the sensor to the decoder is a setting (0.2 s by default, an H.264 stream's
over a tether; measure yours): set too short, a pilot may decide on what the camera saw
before the vehicle stopped.

`FakeCamera` streams frames from a function as RTP H.264 on 127.0.0.1, for tests and for
flying the loop without a vehicle.
"""

from __future__ import annotations

import contextlib
import math
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any
from urllib.parse import urlsplit, urlunsplit

import numpy as np

from cavenav.core.errors import ConfigError, DependencyError, VehicleError
from cavenav.core.redaction import REDACTED

__all__ = ["CameraAddress", "FakeCamera", "VideoCamera"]

RTP_H264_PAYLOAD = 96  # the dynamic payload type rtph264pay and BlueOS use
INSTALL_HINT = "PyAV reads the camera: pip install -e '.[vehicle]'"


def _av() -> Any:  # noqa: ANN401 - the av module
    try:
        import av
    except ImportError:
        raise DependencyError(INSTALL_HINT) from None
    return av


def session_description(port: int, payload: int = RTP_H264_PAYLOAD) -> str:
    """An SDP (RFC 8866) for H.264 over RTP (RFC 6184) arriving on UDP ``port``."""
    return (
        "v=0\no=- 0 0 IN IP4 127.0.0.1\ns=cavenav camera\nc=IN IP4 0.0.0.0\nt=0 0\n"
        f"m=video {port} RTP/AVP {payload}\na=rtpmap:{payload} H264/90000\n"
    )


@dataclass(frozen=True)
class CameraAddress:
    """Where the video comes from: ``udp`` (RTP H.264 on a port), ``rtsp`` or ``url``."""

    kind: str
    where: str

    @classmethod
    def parse(cls, text: str) -> CameraAddress:
        """``udp:PORT``, ``rtsp://HOST[:PORT]/PATH``, or another URL or file FFmpeg opens.

        Raises:
            ConfigError: an empty address, or a udp one whose port is not 1-65535.
        """
        if text.startswith("udp:") and not text.startswith("udp://"):
            port = text.removeprefix("udp:")
            if not (port.isdigit() and 0 < int(port) < 65536):
                raise ConfigError(
                    f"camera {text!r}: give udp:PORT (RTP H.264, BlueOS sends to 5600), "
                    "rtsp://HOST:PORT/PATH or a URL FFmpeg opens"
                )
            return cls("udp", port)
        if not text.strip():
            raise ConfigError("camera: give udp:PORT, rtsp://HOST:PORT/PATH or a URL")
        return cls("rtsp" if text.casefold().startswith("rtsp://") else "url", text)

    def __repr__(self) -> str:
        return f"CameraAddress({str(self)!r})"

    def __str__(self) -> str:
        """The address as it may be shown and recorded: a password in the URL (an IP
        camera's ``rtsp://user:password@host/...``) masked."""
        if self.kind == "udp":
            return f"udp:{self.where}"
        parts = urlsplit(self.where)
        if parts.password is None:
            return self.where
        host = parts.netloc.rpartition("@")[2]
        return urlunsplit(parts._replace(netloc=f"{parts.username}:{REDACTED}@{host}"))


class VideoCamera:
    """The latest frame of a video stream, decoded on a thread, as RGB at the pilot's size.

    A frame is converted only when asked for: centre-cropped to the pilot's aspect ratio
    (BlueOS streams 16:9; squeezing it into 4:3 would make the pixels taller than wide,
    and every reader of the depth image assumes square ones), then scaled.
    `hfov_deg` turns the stream's field of view into the frames'.
    """

    def __init__(
        self,
        address: CameraAddress,
        size: tuple[int, int] = (640, 480),
        timeout_s: float = 10.0,
        latency_s: float = 0.2,
    ):
        """Open the stream and wait for its first frame.

        Args:
            size: (width, height) of the frames given.
            latency_s: from light on the sensor to a decoded frame here (the camera's
                encoder, the tether, the decoder): a frame that arrives sooner than this
                after a moment may show what was before it.

        Raises:
            DependencyError: PyAV is not installed.
            VehicleError: the stream did not open, or sent no frame, within ``timeout_s``.
        """
        av = _av()
        self.address, self.size = address, size
        self.timeout_s, self.latency_s = timeout_s, latency_s
        self._folder = tempfile.TemporaryDirectory(prefix="cavenav-camera-")
        target, options = self._source(address)
        try:
            # (open, read) timeouts: a read that waits longer ends the decoding thread.
            self._container = av.open(target, options=options, timeout=(timeout_s, timeout_s))
        except (av.FFmpegError, OSError) as exc:  # its text names the URL: not shown
            self._folder.cleanup()
            raise VehicleError(f"camera {address}: cannot open the stream: {_why(exc)}") from None
        self._latest: tuple[Any, float] | None = None  # an av.VideoFrame, when it arrived
        self.frames = 0  # decoded so far
        self._failure: BaseException | None = None
        self._arrived = threading.Condition()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._decode, name="camera", daemon=True)
        self._thread.start()
        try:  # a stream that sends nothing is found now, before a vehicle is armed
            self._first = self._wait_after(-math.inf)
        except BaseException:
            self.close()
            raise

    def _source(self, address: CameraAddress) -> tuple[str, dict[str, str]]:
        """What FFmpeg opens, with options that keep the latency to one frame."""
        options = {"fflags": "nobuffer", "analyzeduration": "1000000", "probesize": "500000"}
        if address.kind == "udp":
            sdp = Path(self._folder.name) / "camera.sdp"
            sdp.write_text(session_description(int(address.where)))
            options.update(protocol_whitelist="file,udp,rtp", reorder_queue_size="0")
            return str(sdp), options
        if address.kind == "rtsp":
            options["rtsp_transport"] = "tcp"
        return address.where, options

    def _decode(self) -> None:
        try:
            for frame in self._container.decode(video=0):
                if self._stop.is_set():
                    break
                with self._arrived:
                    self._latest = (frame, time.monotonic())
                    self.frames += 1
                    self._arrived.notify_all()
        except BaseException as exc:  # the stream ended or broke: said at the next read
            self._failure = exc
        finally:
            with contextlib.suppress(Exception):
                self._container.close()
            with self._arrived:
                self._failure = self._failure or EOFError("the stream ended")
                self._arrived.notify_all()

    def _covering(self, frame: Any) -> tuple[int, int]:  # noqa: ANN401 - an av.VideoFrame
        """The size the stream's frame is scaled to before the crop: the pilot's size
        covered, the stream's aspect ratio kept."""
        width, height = self.size
        scale = max(width / frame.width, height / frame.height)
        return max(width, round(frame.width * scale)), max(height, round(frame.height * scale))

    def hfov_deg(self, stream_hfov_deg: float) -> float:
        """The horizontal field of view of the frames given, for a stream that sees
        ``stream_hfov_deg`` across (less where its sides are cropped)."""
        kept = self.size[0] / self._covering(self._first)[0]
        return math.degrees(2 * math.atan(kept * math.tan(math.radians(stream_hfov_deg) / 2)))

    def _wait_after(self, moment: float) -> Any:  # noqa: ANN401 - an av.VideoFrame
        deadline = time.monotonic() + self.timeout_s
        with self._arrived:
            while self._latest is None or self._latest[1] <= moment:
                if self._failure is not None:
                    raise VehicleError(f"camera {self.address}: {_why(self._failure)}")
                left = deadline - time.monotonic()
                if left <= 0:
                    raise VehicleError(
                        f"camera {self.address}: no new frame within {self.timeout_s:g} s"
                    )
                self._arrived.wait(min(left, 0.1))
            return self._latest[0]

    def frame_after(self, moment: float) -> np.ndarray:
        """The first frame that arrived ``latency_s`` or more after the monotonic time
        ``moment``, (height, width, 3) uint8 RGB at ``size``.

        Raises:
            VehicleError: none came within ``timeout_s``, or the stream ended.
        """
        frame = self._wait_after(moment + self.latency_s)
        covered_width, covered_height = self._covering(frame)
        rgb = frame.to_ndarray(format="rgb24", width=covered_width, height=covered_height)
        width, height = self.size
        top, left = (covered_height - height) // 2, (covered_width - width) // 2
        return np.ascontiguousarray(rgb[top : top + height, left : left + width])

    def close(self) -> None:
        """Stop decoding; the thread closes the stream at its next frame (or, with the
        stream silent, at its read timeout). Safe to repeat; a read waiting on it ends."""
        self._stop.set()
        with self._arrived:
            self._failure = self._failure or EOFError("the camera was closed")
            self._arrived.notify_all()
        self._thread.join(timeout=1.0)
        self._folder.cleanup()


def _why(error: BaseException) -> str:
    """What went wrong, without FFmpeg's text, which names the URL (and any password)."""
    if isinstance(error, EOFError):
        return str(error)
    return getattr(error, "strerror", None) or type(error).__name__


class FakeCamera:
    """Streams ``frame(i)`` (RGB uint8) as RTP H.264 to 127.0.0.1:``port`` at ``fps``."""

    def __init__(self, frame: Callable[[int], np.ndarray], port: int, fps: float = 10.0):
        self._frame, self.port, self.fps = frame, port, fps
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._stream, name="fake-camera", daemon=True)

    @property
    def address(self) -> str:
        return f"udp:{self.port}"

    def __enter__(self) -> FakeCamera:
        self._thread.start()
        return self

    def __exit__(
        self,
        kind: type[BaseException] | None,
        error: BaseException | None,
        trace: TracebackType | None,
    ) -> None:
        self._stop.set()
        self._thread.join(timeout=5.0)

    def _stream(self) -> None:
        av = _av()
        first = self._frame(0)
        output = av.open(f"rtp://127.0.0.1:{self.port}", "w", format="rtp")
        stream = output.add_stream("libx264", rate=round(self.fps))
        stream.height, stream.width = first.shape[:2]
        stream.pix_fmt = "yuv420p"
        # A key frame every half second: a reader that joins late starts within it.
        gop = str(max(1, round(self.fps / 2)))
        stream.options = {"preset": "ultrafast", "tune": "zerolatency", "g": gop, "bf": "0"}
        started, index = time.monotonic(), 0
        try:
            while not self._stop.is_set():
                image = first if index == 0 else self._frame(index)
                frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(image), format="rgb24")
                frame.pts = index
                for packet in stream.encode(frame):
                    output.mux(packet)
                index += 1
                self._stop.wait(max(0.0, started + index / self.fps - time.monotonic()))
        finally:
            output.close()
