"""Weights & Biases: a sweep's episodes, results table and videos (`cavenav eval --wandb`).

Each episode is logged as it ends (its metrics under ``episode/``, its outcome, and its
episode.mp4 when the sweep makes videos), then the whole results.csv as a table and the
sweep's totals (``all/success_rate`` ...) in the run's summary. The run is named after
the sweep folder, carries sweep.json as its config and lives in ``SWEEP/wandb/``.

Offline by default, as everything in cavenav: nothing leaves the machine unless
``WANDB_MODE=online`` is set (after ``wandb login``); ``wandb sync SWEEP/wandb/offline-run-*``
sends an offline run later. Needs ``pip install 'cavenav[wandb]'``.
"""

from __future__ import annotations

import importlib.util
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, cast

from cavenav.core.errors import ConfigError, DependencyError
from cavenav.evaluation.results import COLUMNS, ResultRow, group

__all__ = ["EPISODE_METRICS", "WandbLog", "require_wandb"]

# The numbers of a results row that are logged for each episode.
EPISODE_METRICS = (
    "success", "spl", "steps", "collisions", "progress_m", "path_length_m",
    "path_efficiency", "min_clearance_m", "mean_clearance_m", "steps_below_standoff",
    "prompt_tokens", "completion_tokens", "cost_usd", "model_p50_s", "wall_time_s",
)  # fmt: skip
# The totals of the sweep that go to the run's summary.
SWEEP_TOTALS = ("success_rate", "collision_rate", "spl", "steps", "tokens_per_success",
                "cost_per_success_usd", "model_p50_s", "model_p95_s")  # fmt: skip


def require_wandb() -> None:
    """Raises DependencyError, with the install command, where wandb is not installed."""
    if importlib.util.find_spec("wandb") is None:
        raise DependencyError("--wandb needs Weights & Biases: pip install 'cavenav[wandb]'")


class WandbLog:
    """One Weights & Biases run for one sweep (a resumed sweep logs a new run).

    Raises:
        DependencyError: wandb is not installed.
        ConfigError: wandb refuses to start (online without a login, a bad WANDB_MODE).
    """

    def __init__(self, folder: Path, config: Mapping[str, Any]):
        require_wandb()
        import wandb

        self.folder, self.config, self._wandb = Path(folder), dict(config), wandb
        self._run: Any = None

    @property
    def run(self) -> Any:  # noqa: ANN401 - a wandb Run
        """The run, started at the first episode: by then the sweep folder is the sweep's
        (a folder that held anything before it would be refused as no sweep)."""
        if self._run is None:
            try:
                self._run = self._wandb.init(
                    project=os.environ.get("WANDB_PROJECT", "cavenav"),
                    name=self.folder.name,
                    dir=str(self.folder),
                    config=self.config,
                    job_type="sweep",
                    mode=os.environ.get("WANDB_MODE", "offline"),  # type: ignore[arg-type]
                    settings=self._wandb.Settings(silent=True),
                )
            except Exception as exc:  # noqa: BLE001 - wandb's own errors, of many kinds
                raise ConfigError(f"--wandb: Weights & Biases did not start: {exc}") from None
        return self._run

    def episode(self, row: ResultRow) -> None:
        """Log one finished episode's results row (and its video, where there is one)."""
        logged: dict[str, Any] = {
            f"episode/{key}": float(value)
            for key in EPISODE_METRICS
            if (value := cast(Mapping[str, Any], row).get(key)) not in (None, "")
        }
        logged.update({"episode/id": row["episode"], "episode/outcome": row["outcome"]})
        video = self.folder / str(row.get("run_dir") or "") / "episode.mp4"
        if row.get("run_dir") and video.is_file():
            logged["episode/video"] = self._wandb.Video(str(video), format="mp4")
        self.run.log(logged)

    def finish(self, rows: Sequence[ResultRow]) -> None:
        """Log the results table and the sweep's totals, and close the run."""
        table = self._wandb.Table(
            columns=list(COLUMNS),
            data=[[row.get(c) for c in COLUMNS] for row in rows],
        )
        self.run.log({"results": table})
        totals = group("all", self.folder.name, rows)  # a sweep flies one pilot
        for key in SWEEP_TOTALS:
            self.run.summary[f"all/{key}"] = totals[key]
        self.run.finish()
