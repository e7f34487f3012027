"""The run folder: an append-only, crash-safe record of one episode.

RUN_DIR/
  summary.json   rewritten atomically after every step (status "running" until the
                 end), so a crash or Ctrl-C leaves a valid partial summary
  steps.jsonl    one JSON object per step, written once the step's frames are on disk
  frames/        step_NNNN_rgb.png, step_NNNN_depth.png, step_NNNN_depth.exr (unless off)
  topdown.png, side.png   trajectory plots, written at the end
  exchanges.jsonl  (model pilots) every request and raw reply, reasoning included
  images/        the images those requests carried, stored once by content hash
  mavlink.jsonl  (cavenav fly) every MAVLink message sent to and received from the vehicle
"""

from __future__ import annotations

import base64
import errno
import hashlib
import itertools
import json
import os
import queue
import re
import signal
import threading
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from contextlib import contextmanager, suppress
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from cavenav.core.errors import CavenavError, ConfigError, RecordingError
from cavenav.core.files import probe_writable, write_then_rename
from cavenav.core.redaction import redact
from cavenav.core.types import Observation, SonarImage
from cavenav.episode.records import numbered_jsonl
from cavenav.sensors.depth import EXR_COMPRESSIONS, ExrCompression, save_png, write_exr

if TYPE_CHECKING:
    from cavenav.episode.record import EpisodeLog
    from cavenav.world.raycast import RayCaster

__all__ = [
    "LostStep",
    "RunFolder",
    "new_run_dir",
    "numbered_jsonl",
    "prepare_root",
    "read_jsonl",
    "write_atomic",
    "write_json",
]


@contextmanager
def prepared_root(root: str | Path) -> Iterator[Path]:
    """`prepare_root`, for a block that may still refuse its input (an unknown
    scenario, a start inside rock): the folders it created are removed again if the
    block raises a `CavenavError` and leaves them empty, so exit status 2 writes nothing."""
    root = Path(root).absolute()
    first_new = next((p for p in [*reversed(root.parents), root] if not p.exists()), None)
    prepare_root(root)
    try:
        yield root
    except CavenavError:
        if first_new is not None:
            with suppress(OSError):  # not empty, or gone: left as it is
                for folder in [root, *root.parents]:
                    folder.rmdir()
                    if folder == first_new:
                        break
        raise


def prepare_root(root: str | Path) -> Path:
    """``root`` created if needed and checked writable, before any cave is built.

    Raises:
        ConfigError: ``root`` is a file, read-only or cannot be created (bad input, exit
            status 2).
    """
    root = Path(root)
    if root.exists() and not root.is_dir():
        raise ConfigError(f"cannot write run folders into {root}: it is a file")
    try:
        root.mkdir(parents=True, exist_ok=True)
        probe_writable(root)
    except OSError as exc:
        raise ConfigError(f"cannot write run folders into {root}: {exc.strerror or exc}") from None
    return root


def new_run_dir(root: str | Path, scenario: str, pilot: str, seed: int | None) -> Path:
    """Create a fresh, empty folder under ``root`` named by time, scenario, pilot and seed.

    The name is claimed by creating the folder, which the file system does atomically:
    two runs started in the same second (or in parallel) get ``NAME`` and ``NAME_2``.
    `prepare_root` checks ``root`` first, before the cave is built.
    """
    root = Path(root)
    stamp = datetime.now().strftime("%Y%m%d-%H%M%S")
    seeded = "" if seed is None else f"_seed{seed}"  # a vehicle's own sensors have none
    safe = re.sub(r"[^A-Za-z0-9_.-]+", "_", f"{stamp}_{scenario}_{pilot}{seeded}")
    for suffix in itertools.count(1):
        path = root / (safe if suffix == 1 else f"{safe}_{suffix}")
        try:
            path.mkdir(parents=True)
        except FileExistsError:
            continue
        except OSError as exc:
            raise RecordingError(f"cannot create {path}: {exc.strerror or exc}") from None
        return path
    raise AssertionError("unreachable")


def read_jsonl(path: Path) -> list[dict[str, Any]]:
    """The records of steps.jsonl or exchanges.jsonl ([] when there is none).

    A line cut short by a crash or a kill is skipped: the record up to it is valid.
    """
    return [record for _, record in numbered_jsonl(path)]


def write_atomic(path: Path, text: str) -> None:
    """(Re)write a text file through a temporary beside it: readers never see half a file."""
    write_then_rename(path, lambda tmp: tmp.write_text(text, encoding="utf-8"))


@contextmanager
def interrupts_deferred() -> Iterator[None]:
    """Hold Ctrl-C (SIGINT) until the block ends, so the final summary is written whole.

    Only the main thread can handle signals; elsewhere this does nothing.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    caught: list[int] = []
    previous = signal.signal(signal.SIGINT, lambda signum, frame: caught.append(signum))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
    if caught:
        raise KeyboardInterrupt


def write_json(path: Path, data: Mapping[str, Any]) -> None:
    """Atomically (re)write a JSON file; inf and NaN become null, numpy values plain, API
    keys redacted (`cavenav.core.redaction`)."""
    write_atomic(path, _dumps(data, indent=2) + "\n")


def _save_echoes(path: Path, sonar: SonarImage) -> None:
    """A sonar's raw echoes as NPZ: ``echoes`` (beams, bins) uint8, ``bearings_deg``,
    ``fresh``, ``range_m`` and ``frequency_khz``; ``kind`` as text."""
    with open(path, "wb") as out:  # an open file: np.savez would add its own suffix
        np.savez_compressed(
            out, echoes=sonar.echoes, bearings_deg=sonar.bearings_deg, fresh=sonar.fresh,
            range_m=sonar.range_m, frequency_khz=sonar.frequency_khz, kind=sonar.kind,
        )  # fmt: skip


def _dumps(data: Mapping[str, Any], indent: int | None = None) -> str:
    """One record as JSON, as every file of a run folder holds it: finite numbers, plain
    values, and no credential, whatever a server or a model echoed into it."""
    return json.dumps(redact(_finite(dict(data))), indent=indent, default=_json_default)


def _json_default(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"cannot write {type(value).__name__} to JSON")


def _finite(value: Any) -> Any:
    """JSON has no inf or NaN: write them as null, recursively."""
    if isinstance(value, float) and not np.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_finite(v) for v in value]
    return value


class LostStep(Exception):
    """A step the run folder's writer could not write; the steps queued after it are
    dropped, so the folder ends at the step before ``step``.

    Attributes:
        step: the step's number.
        error: why (a full disk is an OSError).
        undo: what the caller handed `RunFolder.record` with the step, to take it back.
    """

    def __init__(self, step: int, error: BaseException, undo: object):
        super().__init__(f"step {step} could not be written: {error}")
        self.step, self.error, self.undo = step, error, undo

    def taken_back(self, log: Any, folder: Path) -> RecordingError:  # noqa: ANN401 - any log
        """Take this step and those after it back from ``log`` (its ``rewind`` to
        ``undo``); the error to end the episode with."""
        log.rewind(self.undo)
        return RecordingError.cannot_write(f"the run folder {folder}", self.error)


@dataclass(frozen=True)
class _Step:
    """One whole step, queued for the writer: what `RunFolder.record` was given."""

    record: dict[str, Any]
    obs: Observation
    exchanges: Sequence[Mapping[str, Any]]
    summary: Mapping[str, Any]
    undo: object


class _StepWriter:
    """Writes queued steps in order on a thread of its own, so that encoding the frames
    (about 45 ms a step) overlaps with the pilot and the next step instead of adding to
    them.

    The queue holds at most ``depth`` steps (about 2.4 MB each at 640x480): a loop that
    outruns the disk waits. After the first step that fails, later ones are dropped; the
    failure is reported once, by the next `put` or `flush`.
    """

    def __init__(self, write: Callable[[_Step], None], depth: int = 4):
        self._write = write
        self._queue: queue.Queue[_Step | None] = queue.Queue(maxsize=depth)
        self._failed = False
        self._unreported: LostStep | None = None
        self._thread = threading.Thread(target=self._run, name="cavenav-run-folder", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while (step := self._queue.get()) is not None:
            if not self._failed:
                try:
                    self._write(step)
                except BaseException as exc:  # noqa: BLE001 - reported on the loop's thread
                    self._failed = True
                    self._unreported = LostStep(step.record["step"], exc, step.undo)
            self._queue.task_done()
        self._queue.task_done()

    def put(self, step: _Step) -> None:
        self._report()
        self._queue.put(step)

    def flush(self) -> None:
        """Wait until every queued step is written (or dropped)."""
        self._queue.join()
        self._report()

    def close(self) -> None:
        """Write what is queued, then end the thread (a failure is no longer reported)."""
        if self._thread.is_alive():
            self._queue.put(None)
            self._thread.join()

    def _report(self) -> None:
        lost, self._unreported = self._unreported, None
        if lost is not None:
            raise lost


class RunFolder:
    """Writes one episode's record as it happens, one whole step at a time.

    A step is its frames, its model exchanges, its line in steps.jsonl and the rewritten
    summary.json, in that order. Each file appears whole or not at all (frames and images
    through a temporary and a rename), so a SIGKILL leaves no half file that a line names;
    steps.jsonl may then hold one line more than the summary counts (the kill fell between
    the two). A step that cannot be written whole (a full disk) is taken back: its frames
    removed and steps.jsonl cut back, so the folder ends at the last whole step.

    Steps are written in order on a thread of their own (`_StepWriter`): `record`
    returns once the step is queued and reports a step that could not be written at a
    later call, or at `flush`, as `LostStep`.
    """

    def __init__(
        self,
        path: str | Path,
        save_frames: bool = True,
        save_exr: bool = True,
        *,
        exr_compression: ExrCompression = "none",
    ):
        """``path`` must not exist, or be an empty folder (as `new_run_dir` makes it) but
        for the command log `cavenav fly` opens there first.

        Raises:
            ConfigError: an EXR compression that is not one of `EXR_COMPRESSIONS`.
        """
        if exr_compression not in EXR_COMPRESSIONS:
            raise ConfigError(
                f"EXR compression {exr_compression!r}: choose one of {', '.join(EXR_COMPRESSIONS)}"
            )
        self.path = Path(path)
        self.save_frames = save_frames
        self.save_exr = save_exr
        self.exr_compression = exr_compression
        self.path.mkdir(parents=True, exist_ok=True)
        if {entry.name for entry in self.path.iterdir()} - {"mavlink.jsonl"}:
            raise RecordingError(f"{self.path} is not empty: a run folder starts empty")
        if save_frames:
            (self.path / "frames").mkdir()
        # Unbuffered bytes: a line is one write, and a failed one can be cut back exactly.
        self._steps = open(self.path / "steps.jsonl", "ab", buffering=0)  # noqa: SIM115
        self._stored: dict[str, str] = {}
        self._writer = _StepWriter(self._write_step)

    def frame_names(self, step: int, obs: Observation | None = None) -> dict[str, str]:
        """The paths, relative to the run folder, of the frames step ``step`` writes (with
        ``obs``'s sonar image and echoes, when it has them)."""
        if not self.save_frames:
            return {}
        stem = f"frames/step_{step:04d}"
        files = {"rgb": f"{stem}_rgb.png", "depth_png": f"{stem}_depth.png"}
        if self.save_exr:
            files["depth_exr"] = f"{stem}_depth.exr"
        if obs is not None and obs.sonar is not None:
            files.update(sonar_png=f"{stem}_sonar.png", sonar_npz=f"{stem}_sonar.npz")
        return files

    def write_frames(self, files: Mapping[str, str], obs: Observation) -> None:
        """Save the observation's images under the names `frame_names` gave ``files``."""
        if not files:
            return
        self._save_png(files["rgb"], obs.rgb)
        source = {"depth_source": obs.depth_source}  # which camera made the depth
        write_then_rename(
            self.path / files["depth_png"], lambda tmp: save_png(obs.depth_png, tmp, source)
        )
        if self.save_exr:
            write_then_rename(
                self.path / files["depth_exr"],
                lambda t: write_exr(t, obs.depth_m, self.exr_compression, source),
            )
        if "sonar_png" in files and (sonar := obs.sonar) is not None:
            self._save_png(files["sonar_png"], sonar.fan)
            write_then_rename(self.path / files["sonar_npz"], lambda t: _save_echoes(t, sonar))

    def _save_png(self, name: str, image: np.ndarray) -> None:
        write_then_rename(self.path / name, lambda tmp: save_png(image, tmp))

    def _remove(self, names: Iterable[str]) -> None:
        for name in names:
            (self.path / name).unlink(missing_ok=True)

    def append_step(self, record: dict[str, Any]) -> None:
        """Append one line to steps.jsonl (a short write is a full disk: `_write_step`
        cuts the line back)."""
        line = (_dumps(record) + "\n").encode()
        if self._steps.write(line) != len(line):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    def store_image(self, data_url: str) -> str:
        """Write a data-URL image once, named by its content hash; returns its path.

        A request re-sends the earlier observations' images: each string is decoded and
        hashed only the first time (the dict compares the very same string objects).
        """
        if data_url in self._stored:
            return self._stored[data_url]
        header, _, payload = data_url.partition(",")
        raw = base64.b64decode(payload)
        suffix = "png" if "png" in header else "jpg"
        name = f"images/{hashlib.sha256(raw).hexdigest()[:20]}.{suffix}"
        path = self.path / name
        if not path.exists():
            path.parent.mkdir(exist_ok=True)
            write_then_rename(path, lambda tmp: tmp.write_bytes(raw))
        self._stored[data_url] = name
        return name

    def record(
        self,
        step: dict[str, Any],
        obs: Observation,
        exchanges: Sequence[Mapping[str, Any]],
        summary: Mapping[str, Any],
        undo: object = None,
    ) -> None:
        """Queue one whole step: frames, model exchanges, its line, then ``summary``.

        ``step`` gains the names of its frames (``step["frames"]``) at once. None of the
        arguments may change afterwards: the writer reads them later.

        Args:
            undo: anything; a `LostStep` for this step carries it back (the loop hands
                its log's mark, to take the step back from the log too).

        Raises:
            LostStep: an earlier step could not be written.
        """
        step["frames"] = self.frame_names(step["step"], obs)
        self._writer.put(_Step(step, obs, exchanges, summary, undo))

    def flush(self) -> None:
        """Wait until every recorded step is on disk.

        Raises:
            LostStep: a step could not be written; the folder ends before it.
        """
        self._writer.flush()

    def _write_step(self, queued: _Step) -> None:
        """Write one whole step, or take back all of it that was written."""
        step = queued.record
        end = self._steps.seek(0, os.SEEK_END)
        try:
            self.write_frames(step["frames"], queued.obs)
            if queued.exchanges:
                self.record_exchanges(step["step"], queued.exchanges)
                if sent := self._sent_images(queued.obs):
                    step = {**step, "model_images": sent}
            self.append_step(step)
            self.write_json("summary.json", queued.summary)
        except BaseException:
            self._steps.truncate(end)
            self._remove(step["frames"].values())
            raise

    def record_exchanges(self, step: int, exchanges: Sequence[Mapping[str, Any]]) -> None:
        """Append every model request and raw reply of a step to exchanges.jsonl.

        ``exchanges`` are the pilot's plain records (`Decision.exchanges`). Images are
        replaced by references to images/, stored once; the request carries no
        credentials (keys live in the backend's HTTP headers, never in messages), and any
        a server echoed into a reply or an error is redacted.
        """
        lines = []
        for attempt, exchange in enumerate(exchanges):
            record = {
                "step": step,
                "attempt": attempt,
                **exchange,
                "messages": [self._strip_images(m) for m in exchange["messages"]],
            }
            lines.append(_dumps(record) + "\n")
        with open(self.path / "exchanges.jsonl", "a", encoding="utf-8") as out:
            out.write("".join(lines))

    def _sent_images(self, obs: Observation) -> dict[str, str]:
        """The stored images (under images/) that are ``obs``'s colour and depth images as
        a model pilot sent them (and the colour image with a design's choices drawn on it,
        ``drawn``, sent in its place) (`cavenav.pilots.request_images.sent_as`): the current
        observation among the earlier ones and the map that a request also carries, told
        by the images themselves rather than by the prompt's wording, and not encoded
        again. Empty for a pilot that sent them otherwise."""
        from cavenav.pilots.request_images import drawing_on, sent_as  # model requests only

        images = {
            "rgb": obs.rgb,
            "depth_png": obs.depth_png if obs.has_depth else None,
            "drawn": drawing_on(obs.rgb),  # the colour image with a design's choices drawn
        }
        sent = {}
        for key, image in images.items():
            url = None if image is None else sent_as(image)
            name = None if url is None else self._stored.get(url)
            if name is not None:
                sent[key] = name
        return sent

    def _strip_images(self, message: dict[str, Any]) -> dict[str, Any]:
        content = message["content"]
        if isinstance(content, str):
            return message
        parts = []
        for part in content:
            if part.get("type") == "image_url":
                parts.append({"type": "image", "file": self.store_image(part["image_url"]["url"])})
            else:
                parts.append(part)
        return {**message, "content": parts}

    def write_json(self, name: str, data: Mapping[str, Any]) -> None:
        """Atomically (re)write a JSON file of the run folder."""
        write_json(self.path / name, data)

    def finish(
        self, summary: dict[str, Any], log: EpisodeLog, caster: RayCaster, plots: bool
    ) -> None:
        """Draw the plots from what was recorded (if ``plots``), write the final summary.

        The summary is written whatever happens: Ctrl-C while the plots are drawn leaves
        the episode's own status with no plots, and is held while the summary is written.
        A summary that cannot be written (the disk is still full) leaves the last one,
        which agrees with steps.jsonl.
        """
        try:
            with interrupts_deferred():  # the writer must be done before the last summary
                self._writer.close()
            if plots:
                from cavenav.episode.plots import plot_episode

                try:
                    summary["plots"] = plot_episode(
                        summary, log.poses, log.clearances, log.scenario, caster, self.path
                    )
                except OSError as exc:  # a full disk: the episode is not whole, say so
                    summary.update(status="crashed", failure=f"plots not written: {exc}")
                    raise
        finally:
            self._steps.close()
            with interrupts_deferred():
                try:
                    self.write_json("summary.json", summary)
                except OSError as exc:
                    if summary["status"] != "crashed":  # else the cause is on its way up
                        raise RecordingError.cannot_write(self.path / "summary.json", exc) from None
