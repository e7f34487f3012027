"""Re-fly a recorded episode with no model: the recorded actions, in order.

The simulator is deterministic, so replaying a run folder's actions through the same
scenario reproduces its trajectory exactly; the replay's own run folder can be compared
with the original step by step.
"""

from __future__ import annotations

import json
from pathlib import Path

from cavenav.actions import parse_action
from cavenav.errors import ConfigError, PilotFailure
from cavenav.types import Decision, Observation

__all__ = ["ReplayPilot", "recorded_scenario"]


def _read_steps(run_dir: Path) -> list[dict]:
    path = run_dir / "steps.jsonl"
    if not path.is_file():
        raise ConfigError(f"{run_dir} is not a run folder: no steps.jsonl")
    steps = []
    for number, line in enumerate(path.read_text().splitlines(), 1):
        try:
            steps.append(json.loads(line))
        except json.JSONDecodeError:
            raise ConfigError(f"{path}: line {number} is not JSON") from None
    return steps


def recorded_scenario(run_dir: str | Path) -> tuple[str, int | None]:
    """(scenario, seed) of a recorded run, from its summary.json."""
    path = Path(run_dir) / "summary.json"
    try:
        summary = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ConfigError(f"cannot read {path}: {exc}") from None
    return summary["scenario"], summary.get("seed")


class ReplayPilot:
    """Answers each step with the action recorded at that step."""

    name = "replay"

    def __init__(self, run_dir: str | Path):
        self.run_dir = Path(run_dir)
        self._steps = [s for s in _read_steps(self.run_dir) if s.get("action")]
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
