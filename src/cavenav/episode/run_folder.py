"""The run folder: an append-only, crash-safe record of one episode.

RUN_DIR/
  summary.json   rewritten atomically after every step (status "running" until the
                 end), so a crash or Ctrl-C leaves a valid partial summary
  steps.jsonl    one JSON object per step, flushed as it happens
  frames/        step_NNNN_rgb.png, step_NNNN_depth.png, step_NNNN_depth.exr
  topdown.png, side.png   trajectory plots, written at the end
"""

from __future__ import annotations

import json
import os
import re
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from cavenav.sensors.depth import write_exr
from cavenav.types import Observation

__all__ = ["RunFolder", "new_run_dir"]


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

    def __init__(self, path: str | Path, save_frames: bool = True):
        self.path = Path(path)
        self.save_frames = save_frames
        self.path.mkdir(parents=True, exist_ok=False)
        if save_frames:
            (self.path / "frames").mkdir()
        self._steps = open(self.path / "steps.jsonl", "a", encoding="utf-8")  # noqa: SIM115

    def write_frames(self, step: int, obs: Observation) -> dict[str, str]:
        """Save the observation's images; returns their paths relative to the run folder."""
        if not self.save_frames:
            return {}
        stem = f"frames/step_{step:04d}"
        files = {
            "rgb": f"{stem}_rgb.png",
            "depth_png": f"{stem}_depth.png",
            "depth_exr": f"{stem}_depth.exr",
        }
        Image.fromarray(obs.rgb).save(self.path / files["rgb"], compress_level=1)
        Image.fromarray(obs.depth_png).save(self.path / files["depth_png"], compress_level=1)
        write_exr(self.path / files["depth_exr"], obs.depth_m)
        return files

    def append_step(self, record: dict[str, Any]) -> None:
        self._steps.write(json.dumps(_finite(record), default=_json_default) + "\n")
        self._steps.flush()

    def write_json(self, name: str, data: dict[str, Any]) -> None:
        """Atomically (re)write a JSON file: readers never see half a file."""
        tmp = self.path / f".{name}.tmp"
        tmp.write_text(json.dumps(_finite(data), indent=2, default=_json_default) + "\n")
        os.replace(tmp, self.path / name)

    def close(self) -> None:
        self._steps.close()
