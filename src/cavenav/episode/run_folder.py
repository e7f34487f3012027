"""The run folder: an append-only, crash-safe record of one episode.

RUN_DIR/
  summary.json   rewritten atomically after every step (status "running" until the
                 end), so a crash or Ctrl-C leaves a valid partial summary
  steps.jsonl    one JSON object per step, flushed as it happens
  frames/        step_NNNN_rgb.png, step_NNNN_depth.png, step_NNNN_depth.exr (unless off)
  topdown.png, side.png   trajectory plots, written at the end
  exchanges.jsonl  (model pilots) every request and raw reply, reasoning included
  images/        the images those requests carried, stored once by content hash
"""

from __future__ import annotations

import base64
import hashlib
import json
import os
import re
from collections.abc import Mapping, Sequence
from datetime import datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from PIL import Image

from cavenav.sensors.depth import write_exr
from cavenav.types import Observation

if TYPE_CHECKING:
    from cavenav.episode.record import EpisodeLog
    from cavenav.world.raycast import RayCaster

__all__ = ["RunFolder", "new_run_dir", "read_jsonl", "write_atomic", "write_json"]


def new_run_dir(root: str | Path, scenario: str, pilot: str, seed: int | None) -> Path:
    """A fresh folder under ``root`` named by time, scenario, pilot and seed."""
    stamp = datetime.now().strftime("%Y%m%d-%H%M%S")
    safe = re.sub(r"[^A-Za-z0-9_.-]+", "_", f"{stamp}_{scenario}_{pilot}_seed{seed}")
    path = Path(root) / safe
    suffix = 1
    while path.exists():
        suffix += 1
        path = Path(root) / f"{safe}_{suffix}"
    return path


def read_jsonl(path: Path) -> list[dict[str, Any]]:
    """The records of steps.jsonl or exchanges.jsonl ([] when there is none).

    A line cut short by a crash or a kill is skipped: the record up to it is valid.
    """
    if not path.is_file():
        return []
    records = []
    for line in path.read_text(encoding="utf-8").splitlines():
        try:
            records.append(json.loads(line))
        except json.JSONDecodeError:
            continue
    return records


def write_atomic(path: Path, text: str) -> None:
    """(Re)write a text file through a temporary beside it: readers never see half a file."""
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(text, encoding="utf-8")
    os.replace(tmp, path)


def write_json(path: Path, data: Mapping[str, Any]) -> None:
    """Atomically (re)write a JSON file; inf and NaN become null, numpy values plain."""
    write_atomic(path, json.dumps(_finite(dict(data)), indent=2, default=_json_default) + "\n")


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


class RunFolder:
    """Writes one episode's record as it happens."""

    def __init__(self, path: str | Path, save_frames: bool = True, save_exr: bool = True):
        self.path = Path(path)
        self.save_frames = save_frames
        self.save_exr = save_exr
        self.path.mkdir(parents=True, exist_ok=False)
        if save_frames:
            (self.path / "frames").mkdir()
        self._steps = open(self.path / "steps.jsonl", "a", encoding="utf-8")  # noqa: SIM115
        self._stored: dict[str, str] = {}

    def write_frames(self, step: int, obs: Observation) -> dict[str, str]:
        """Save the observation's images; returns their paths relative to the run folder."""
        if not self.save_frames:
            return {}
        stem = f"frames/step_{step:04d}"
        files = {"rgb": f"{stem}_rgb.png", "depth_png": f"{stem}_depth.png"}
        Image.fromarray(obs.rgb).save(self.path / files["rgb"], compress_level=1)
        Image.fromarray(obs.depth_png).save(self.path / files["depth_png"], compress_level=1)
        if self.save_exr:
            files["depth_exr"] = f"{stem}_depth.exr"
            write_exr(self.path / files["depth_exr"], obs.depth_m)
        return files

    def append_step(self, record: dict[str, Any]) -> None:
        self._steps.write(json.dumps(_finite(record), default=_json_default) + "\n")
        self._steps.flush()

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
            path.write_bytes(raw)
        self._stored[data_url] = name
        return name

    def record(
        self, step: dict[str, Any], obs: Observation, exchanges: Sequence[Mapping[str, Any]]
    ) -> None:
        """Write one step: its frames, its model exchanges, then its line in steps.jsonl."""
        step["frames"] = self.write_frames(step["step"], obs)
        if exchanges:
            self.record_exchanges(step["step"], exchanges)
        self.append_step(step)

    def record_exchanges(self, step: int, exchanges: Sequence[Mapping[str, Any]]) -> None:
        """Append every model request and raw reply of a step to exchanges.jsonl.

        ``exchanges`` are the pilot's plain records (`Decision.exchanges`). Images are
        replaced by references to images/, stored once; the request carries no
        credentials (keys live in the backend's HTTP headers, never in messages).
        """
        with open(self.path / "exchanges.jsonl", "a", encoding="utf-8") as out:
            for attempt, exchange in enumerate(exchanges):
                record = {
                    "step": step,
                    "attempt": attempt,
                    **exchange,
                    "messages": [self._strip_images(m) for m in exchange["messages"]],
                }
                out.write(json.dumps(record) + "\n")

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

    def write_json(self, name: str, data: dict[str, Any]) -> None:
        """Atomically (re)write a JSON file of the run folder."""
        write_json(self.path / name, data)

    def finish(
        self, summary: dict[str, Any], log: EpisodeLog, caster: RayCaster, plots: bool
    ) -> None:
        """Draw the plots from what was recorded (if ``plots``), write the final summary."""
        try:
            if plots:
                from cavenav.episode.plots import plot_episode

                summary["plots"] = plot_episode(
                    summary, log.poses, log.clearances, log.scenario, caster, self.path
                )
        finally:
            self.write_json("summary.json", summary)
            self._steps.close()
