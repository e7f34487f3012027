"""Re-fly a recorded episode with no model: the recorded actions, in order.

The simulator is deterministic, so replaying a run folder's actions through the same
scenario reproduces its trajectory exactly; the replay's own run folder can be compared
with the original step by step.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, TypeGuard

from cavenav.core.errors import ConfigError, PilotFailure
from cavenav.core.types import Decision, Observation
from cavenav.motion.actions import parse_action

__all__ = ["ReplayPilot", "recorded_noise_seed", "recorded_scenario"]


def _damaged(path: Path, why: str) -> ConfigError:
    return ConfigError(f"{path}: {why}: the recording is damaged; replay another run folder")


def _read_steps(run_dir: Path) -> list[dict[str, Any]]:
    """The recorded steps that flew an action, checked as far as a replay reads them.

    (`cavenav.episode.records` checks whole records; pilots never import the episode
    layer, so the replay checks here the few fields it uses.)
    """
    path = run_dir / "steps.jsonl"
    if not path.is_file():
        raise ConfigError(f"{run_dir} is not a run folder: no steps.jsonl")
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"cannot read {path}: {exc}") from None
    steps = []
    for number, line in enumerate(lines, 1):
        try:
            step = json.loads(line)
        except json.JSONDecodeError:
            raise _damaged(path, f"line {number} is not JSON") from None
        if not isinstance(step, dict):
            raise _damaged(path, f"line {number} is not a JSON object")
        action = step.get("action")
        if action is None or action == "":
            continue  # a step without an action (the pilot failed): nothing to replay
        if not isinstance(action, str) or not _whole(step.get("step")):
            raise _damaged(path, f"line {number} needs a text 'action' and a whole 'step'")
        steps.append(step)
    return steps


def _whole(value: Any) -> TypeGuard[int]:
    return isinstance(value, int) and not isinstance(value, bool)


def _summary(run_dir: str | Path) -> tuple[Path, dict[str, Any]]:
    """A recorded run's summary.json (its path and contents).

    Raises:
        ConfigError: summary.json is missing, unreadable or not a JSON object.
    """
    path = Path(run_dir) / "summary.json"
    try:
        summary = json.loads(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise ConfigError(f"cannot read {path}: {exc.strerror or exc}") from None
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise _damaged(path, f"not valid JSON ({exc})") from None
    if not isinstance(summary, dict):
        raise _damaged(path, "not a JSON object")
    return path, summary


def recorded_scenario(run_dir: str | Path) -> tuple[str, int | None]:
    """(scenario, seed) of a recorded run, from its summary.json.

    Raises:
        ConfigError: summary.json is missing, unreadable or damaged (naming the file).
    """
    path, summary = _summary(run_dir)
    scenario, seed = summary.get("scenario"), summary.get("seed")
    if not isinstance(scenario, str):
        raise _damaged(path, "field 'scenario' is not text")
    if seed is not None and not _whole(seed):
        raise _damaged(path, "field 'seed' is not a whole number")
    return scenario, seed


def recorded_noise_seed(run_dir: str | Path) -> int:
    """The seed of a recorded run's sensor noise: its summary's ``noise_seed``, else its
    configuration's (a run recorded before the summary named it), else 0 (the only seed
    the noise had before it was recorded).

    Raises:
        ConfigError: summary.json is missing, unreadable or damaged (naming the file).
    """
    path, summary = _summary(run_dir)
    config = summary.get("config")
    seed = summary.get("noise_seed", config.get("seed", 0) if isinstance(config, dict) else 0)
    if _whole(seed):
        return seed
    raise _damaged(path, "field 'noise_seed' is not a whole number")


class ReplayPilot:
    """Answers each step with the action recorded at that step."""

    name = "replay"

    def __init__(self, run_dir: str | Path):
        self.run_dir = Path(run_dir)
        self._steps = _read_steps(self.run_dir)
        self._next = 0

    def reset(self) -> None:
        self._next = 0

    def decide(self, observation: Observation) -> Decision:
        if self._next >= len(self._steps):
            raise PilotFailure(
                f"the recording in {self.run_dir} has only {len(self._steps)} actions"
            )
        step = self._steps[self._next]
        self._next += 1
        return Decision(
            action=parse_action(step["action"]),
            action_text=step["action"],
            justification=step.get("justification", ""),
            raw=step.get("justification", ""),
            extra={"replayed_step": step["step"]},
        )
