"""The closed loop, its four endings, and the run folder it leaves behind."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import pytest

from cavenav.actions import format_action
from cavenav.episode.loop import EpisodeConfig, run_episode
from cavenav.errors import PilotFailure
from cavenav.sensors.depth import read_exr
from cavenav.types import Action, Decision, Observation, Usage
from cavenav.world.scenarios import Scenario

SUMMARY_FIELDS = {
    "scenario",
    "pilot",
    "seed",
    "success",
    "termination",
    "collisions",
    "steps",
    "path_length_m",
    "min_clearance_m",
    "mean_clearance_m",
    "steps_below_standoff",
}


class Scripted:
    """A stand-in pilot that repeats one action, optionally failing at a given step."""

    name = "scripted"

    def __init__(
        self, action: Action, fail_at: int | None = None, error: type[BaseException] = PilotFailure
    ):
        self.action, self.fail_at, self.error, self.calls = action, fail_at, error, 0

    def reset(self) -> None:
        self.calls = 0

    def decide(self, observation: Observation) -> Decision:
        self.calls += 1
        if self.fail_at is not None and self.calls > self.fail_at:
            raise self.error("no valid reply after 3 attempts")
        return Decision(self.action, format_action(self.action), "scripted")


FAST = EpisodeConfig(plots=False)


def test_reaching_the_exit_ends_the_episode_with_success(room_scenario: Scenario) -> None:
    result = run_episode(room_scenario, Scripted(Action(forward=1.0)), FAST)
    assert result.termination == "exit" and result.success
    assert result.summary["terminated"] and not result.summary["truncated"]
    assert result.summary["steps"] == 14  # from y = 8 past the exit plane at y = -6
    assert result.summary["path_length_m"] == pytest.approx(14.0)


def test_touching_a_wall_is_a_collision(room_scenario: Scenario) -> None:
    result = run_episode(room_scenario, Scripted(Action(right=1.0)), FAST)
    assert result.termination == "collision"
    assert result.summary["collisions"] == 1 and not result.success
    assert result.summary["collision_pose"] is not None


def test_running_out_of_steps_is_a_truncation(room_scenario: Scenario) -> None:
    result = run_episode(
        room_scenario, Scripted(Action(yaw_deg=10)), EpisodeConfig(max_steps=5, plots=False)
    )
    assert result.termination == "budget"
    assert result.summary["truncated"] and not result.summary["terminated"]
    assert result.summary["steps"] == 5


def test_a_pilot_that_fails_for_good_ends_as_pilot_failure(room_scenario: Scenario) -> None:
    result = run_episode(room_scenario, Scripted(Action(forward=0.5), fail_at=3), FAST)
    assert result.termination == "pilot_failure"
    assert result.summary["steps"] == 4 and "3 attempts" in result.summary["failure"]


def test_the_run_folder_holds_summary_steps_frames_and_plots(
    room_scenario: Scenario, tmp_path: Path
) -> None:
    run_dir = tmp_path / "run"
    result = run_episode(
        room_scenario, Scripted(Action(forward=1.0, yaw_deg=0)), EpisodeConfig(), run_dir
    )
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary.keys() >= SUMMARY_FIELDS
    assert summary["status"] == "finished" and summary["termination"] == "exit"
    steps = [json.loads(line) for line in (run_dir / "steps.jsonl").read_text().splitlines()]
    assert len(steps) == result.summary["steps"]
    first = steps[0]
    for key in (
        "pose",
        "action",
        "justification",
        "clearance_m",
        "d_top_m",
        "d_bottom_m",
        "timing_ms",
    ):
        assert key in first
    assert first["clearance_m"] == pytest.approx(2.0, abs=1e-3)  # corridor 4 m wide
    for path in first["frames"].values():
        assert (run_dir / path).stat().st_size > 0
    assert read_exr(run_dir / first["frames"]["depth_exr"]).shape == (480, 640)
    assert (run_dir / "topdown.png").stat().st_size > 10_000
    assert (run_dir / "side.png").stat().st_size > 10_000


def test_an_interrupted_run_leaves_a_valid_partial_record(
    room_scenario: Scenario, tmp_path: Path
) -> None:
    run_dir = tmp_path / "run"
    pilot = Scripted(Action(forward=0.5), fail_at=3, error=KeyboardInterrupt)
    with pytest.raises(KeyboardInterrupt):
        run_episode(room_scenario, pilot, EpisodeConfig(save_frames=False), run_dir)
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["status"] == "interrupted" and summary["termination"] is None
    assert summary["steps"] == 3
    lines = (run_dir / "steps.jsonl").read_text().splitlines()
    assert [json.loads(line)["step"] for line in lines] == [0, 1, 2]


class Costly:
    """A stand-in model pilot: two answered steps, then a failure that still cost tokens."""

    name = "costly"

    def __init__(self) -> None:
        self.calls = 0

    def reset(self) -> None:
        self.calls = 0

    def decide(self, observation: Observation) -> Decision:
        self.calls += 1
        if self.calls > 2:
            spent = Usage(prompt_tokens=300, completion_tokens=30, latency_s=3.0, requeries=3)
            raise PilotFailure("no valid reply after 4 attempts", (), replace(spent, cost_usd=0.03))
        usage = Usage(prompt_tokens=100, completion_tokens=10, latency_s=1.0, cost_usd=0.01)
        return Decision(Action(forward=0.5), "forward 0.5 m", "costly", usage=usage)


def test_usage_is_summed_once_and_a_failed_step_still_counts(room_scenario: Scenario) -> None:
    result = run_episode(room_scenario, Costly(), FAST)
    usage = result.summary["usage"]
    assert result.termination == "pilot_failure"
    assert usage["model_steps"] == 3 and usage["prompt_tokens"] == 500
    assert usage["completion_tokens"] == 50 and usage["requeries"] == 3
    assert usage["cost_usd"] == pytest.approx(0.05)
    assert usage["mean_latency_s"] == pytest.approx(5 / 3, abs=1e-4)
    assert [s["vlm"]["prompt_tokens"] for s in result.steps] == [100, 100, 300]
