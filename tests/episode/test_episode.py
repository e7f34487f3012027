"""The closed loop, its seven endings, and the run folder it leaves behind."""

from __future__ import annotations

import json
import threading
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from cavenav.core.errors import PilotFailure
from cavenav.core.types import Action, Decision, Observation, Pose, Usage
from cavenav.episode.loop import run_episode
from cavenav.episode.settings import EpisodeConfig
from cavenav.evaluation.results import outcome
from cavenav.motion.actions import format_action
from cavenav.sensors.depth import read_exr
from cavenav.world.scenarios import ExitPortal, Scenario
from tests.conftest import Overshooting

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
    # Start at x = 0 heading -y: the vehicle's right is -x, the wall at x = -2.
    result = run_episode(room_scenario, Scripted(Action(right=1.0)), FAST)
    assert result.termination == "collision"
    assert result.summary["collisions"] == 1 and not result.success
    assert result.summary["steps"] == 2
    # Where the move would have ended; the vehicle stays where it was, 1 m short.
    assert result.summary["collision_pose"] == {"x": -2.0, "y": 8.0, "z": 0.0, "yaw_deg": 0.0}
    assert result.poses[-1].position == pytest.approx((-1.0, 8.0, 0.0))


def test_running_out_of_steps_is_a_truncation(room_scenario: Scenario) -> None:
    result = run_episode(
        room_scenario, Scripted(Action(yaw_deg=10)), EpisodeConfig(max_steps=5, plots=False)
    )
    assert result.termination == "budget"
    assert result.summary["truncated"] and not result.summary["terminated"]
    assert result.summary["steps"] == 5


def test_leaving_through_the_entrance_is_a_failure_not_an_exit(room_scenario: Scenario) -> None:
    entrance = ExitPortal((0.0, 9.0, 0.0), (0.0, 1.0, 0.0), 3.0)  # 1 m behind the start
    cave = replace(room_scenario, entrances=(entrance,))
    result = run_episode(cave, Scripted(Action(forward=-1.0)), FAST)
    assert result.termination == "exited_entrance" and not result.success
    assert result.summary["terminated"] and result.summary["steps"] == 1
    assert result.summary["entrances"][0]["point"] == (0.0, 9.0, 0.0)


class Alternating:
    """A pilot caught in the geometric pilot's old loop: left, right, left, right."""

    name = "alternating"

    def reset(self) -> None:
        self.calls = 0

    def decide(self, observation: Observation) -> Decision:
        self.calls += 1
        action = Action(yaw_deg=45 if self.calls % 2 else -45)
        return Decision(action, format_action(action), "looping")


def test_a_pilot_going_nowhere_ends_stuck_after_the_steps_allowed(
    room_scenario: Scenario,
) -> None:
    config = EpisodeConfig(max_steps=100, stuck_after=12, plots=False)
    result = run_episode(room_scenario, Alternating(), config)
    assert result.termination == "stuck" and not result.success
    assert result.summary["steps"] == 12
    assert result.summary["truncated"] and not result.summary["terminated"]
    never = run_episode(room_scenario, Alternating(), replace(config, stuck_after=None))
    assert never.termination == "budget" and never.summary["steps"] == 100


class Bobbing:
    """A pilot that bobs up and down 0.4 m, never getting further on."""

    name = "bobbing"

    def reset(self) -> None:
        self.calls = 0

    def decide(self, observation: Observation) -> Decision:
        self.calls += 1
        action = Action(up=0.4 if self.calls % 2 else -0.4)
        return Decision(action, format_action(action), "bobbing")


def test_an_episode_ended_stuck_is_reported_stuck_however_much_it_moved(
    room_scenario: Scenario,
) -> None:
    """The driver and the results count headway alike (`cavenav.safety.headway`): bobbing ends
    the episode as stuck, and the report says stuck, not oscillating."""
    config = EpisodeConfig(max_steps=100, stuck_after=12, plots=False)
    result = run_episode(room_scenario, Bobbing(), config)
    assert result.termination == "stuck" and result.summary["path_length_m"] > 4.0
    assert outcome(result.summary, result.steps) == "stuck"
    out_of_steps = run_episode(room_scenario, Bobbing(), replace(config, stuck_after=None))
    assert out_of_steps.termination == "budget"
    assert outcome(out_of_steps.summary, out_of_steps.steps) == "oscillating"


def test_slow_headway_is_not_being_stuck(room_scenario: Scenario) -> None:
    # 0.1 m a step: new progress of 0.5 m every 5 steps, well within 12.
    config = EpisodeConfig(max_steps=40, stuck_after=12, plots=False)
    result = run_episode(room_scenario, Scripted(Action(forward=0.1)), config)
    assert result.termination == "budget"


def test_a_pilot_that_fails_for_good_ends_as_pilot_failure(room_scenario: Scenario) -> None:
    result = run_episode(room_scenario, Scripted(Action(forward=0.5), fail_at=3), FAST)
    assert result.termination == "pilot_failure"
    assert result.summary["steps"] == 4 and "3 attempts" in result.summary["failure"]


def test_spending_the_energy_budget_ends_the_episode_as_battery(
    room_scenario: Scenario, tmp_path: Path
) -> None:
    config = EpisodeConfig(plots=False, save_frames=False, battery_wh=0.1)
    result = run_episode(room_scenario, Scripted(Action(forward=0.5)), config, tmp_path / "run")
    assert result.termination == "battery" and not result.success
    assert result.summary["terminated"] and result.summary["steps"] == 4  # 0.0263 Wh a step
    assert outcome(result.summary, result.steps) == "battery"
    steps = [
        json.loads(line) for line in (tmp_path / "run" / "steps.jsonl").read_text().splitlines()
    ]
    assert result.summary["energy_wh"] == pytest.approx(
        sum(s["energy_wh"] for s in steps), abs=1e-4
    )
    assert result.summary["energy_wh"] >= 0.1 and result.summary["moving_s"] == 4.0


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
    frames = first["frames"]
    assert set(frames) == {"rgb", "depth_png", "depth_exr"}
    depth_m = read_exr(run_dir / frames["depth_exr"])
    assert depth_m.shape == (480, 640)
    # Heading -y from y = 8: the far wall at y = -10 is 17.8 m beyond the lens.
    assert depth_m[240, 320] == pytest.approx(17.8, abs=1e-3)
    with Image.open(run_dir / frames["rgb"]) as rgb, Image.open(run_dir / frames["depth_png"]) as d:
        assert (rgb.format, rgb.mode, rgb.size) == ("PNG", "RGB", (640, 480))
        assert (d.format, d.mode, d.size) == ("PNG", "L", (640, 480))
        assert d.getpixel((320, 240)) == round(17.8 / 20 * 255)  # dark near, bright far
    assert_topdown_shows_the_corridor_and_its_exit(run_dir / "topdown.png")
    assert_side_view_shows_ceiling_and_floor(run_dir / "side.png")


# Colours as kinds a reader tells apart, not exact values: a palette or antialiasing
# change keeps each pixel in its kind.
def rgb(path: Path) -> np.ndarray:
    with Image.open(path) as png:
        return np.asarray(png.convert("RGB")).astype(int)


def neutral(image: np.ndarray, lightest: int, darkest: int) -> np.ndarray:
    """Grey pixels (channels within 8 of each other) with brightness in [darkest, lightest]."""
    spread = image.max(axis=-1) - image.min(axis=-1)
    brightness = image.mean(axis=-1)
    return (spread <= 8) & (brightness >= darkest) & (brightness <= lightest)


def orange(image: np.ndarray) -> np.ndarray:
    r, g, b = np.moveaxis(image, -1, 0)
    return (r >= 230) & (g >= 100) & (g <= 155) & (b <= 60)


def red(image: np.ndarray) -> np.ndarray:
    r, g, b = np.moveaxis(image, -1, 0)
    return (r >= 170) & (g <= 90) & (b <= 90)


def pale_blue(image: np.ndarray) -> np.ndarray:
    r, _, b = np.moveaxis(image, -1, 0)
    return (b - r >= 12) & (r >= 180)


def footprint_box(image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows and columns of the corridor's light-grey footprint: the widest band of rows
    (columns) mostly grey, across gaps a line drawn over it leaves, not the axes' frame."""

    def widest_band(counts: np.ndarray) -> np.ndarray:
        grey = np.flatnonzero(counts > 0.5 * counts.max())
        bands = np.split(grey, np.flatnonzero(np.diff(grey) > 12) + 1)
        band = max(bands, key=lambda b: b[-1] - b[0])
        return np.arange(band[0], band[-1] + 1)

    footprint = neutral(image, lightest=235, darkest=195)
    return widest_band(footprint.sum(axis=1)), widest_band(footprint.sum(axis=0))


def assert_topdown_shows_the_corridor_and_its_exit(path: Path) -> None:
    """The 4 x 20 m corridor from above at equal scale, the 6 m exit across it at y = -6."""
    image = rgb(path)
    rows, columns = footprint_box(image)
    height, width = rows[-1] - rows[0] + 1, columns[-1] - columns[0] + 1
    assert width / height == pytest.approx(4 / 20, abs=0.01)
    exit_line = orange(image)
    (exit_rows,) = np.nonzero(exit_line.sum(axis=1) > width)  # wider than the corridor
    exit_y = 10.0 - 20.0 * (exit_rows.mean() - rows[0]) / height
    assert exit_y == pytest.approx(-6.0, abs=0.15)
    exit_columns = np.flatnonzero(exit_line[exit_rows].any(axis=0))
    assert (exit_columns[-1] - exit_columns[0] + 1) / width == pytest.approx(6 / 4, abs=0.03)
    assert not red(image).any()  # no collision marker


def assert_side_view_shows_ceiling_and_floor(path: Path) -> None:
    """Unrolled side view: rock drawn 1 m beyond a ceiling and a floor 4 m apart."""
    image = rgb(path)
    column = image[:, image.shape[1] // 4]  # a quarter of the way along, clear of the legend
    (grey,) = np.nonzero(neutral(column, lightest=165, darkest=115))  # mid grey
    bands = np.split(grey, np.flatnonzero(np.diff(grey) > 1) + 1)
    rock = np.concatenate([b for b in bands if len(b) >= 5])  # not a letter of the title
    (water,) = np.nonzero(pale_blue(column))
    assert rock[0] < water[0] and water[-1] < rock[-1], "rock above the ceiling, below the floor"
    assert (water[-1] - water[0]) / (rock[-1] - rock[0]) == pytest.approx(4 / 6, abs=0.02)


def test_the_top_down_plot_draws_the_path_where_it_was_flown_darker_where_clearance_is_less(
    room_scenario: Scenario, tmp_path: Path
) -> None:
    from matplotlib import colormaps

    from cavenav.episode.plots import plot_episode
    from cavenav.world.raycast import RayCaster

    # 1 m right of the centre line, from y = 8 to y = -4, clearance rising from 0.2 to 2.8 m.
    ys = np.linspace(8.0, -4.0, 13)
    poses = [Pose(1.0, float(y), 0.0, 0.0) for y in ys]
    clearances = np.linspace(0.2, 2.8, len(ys))
    summary = {"scenario": "room", "pilot": "test", "seed": 0, "termination": "budget"}
    summary |= {"steps": len(poses), "min_clearance_m": 0.2}
    written = plot_episode(
        summary, poses, clearances, room_scenario, RayCaster(room_scenario.mesh), tmp_path
    )
    assert written == {"topdown": "topdown.png", "side": "side.png"}
    image = rgb(tmp_path / "topdown.png")
    rows, columns = footprint_box(image)
    corridor = image[rows[0] : rows[-1] + 1, columns[0] : columns[-1] + 1]
    # The coloured pixels, each read on the clearance scale where its colour is near one.
    r, c = np.nonzero(~neutral(corridor, lightest=255, darkest=0))
    scale = np.round(colormaps["viridis"](np.linspace(0, 1, 256))[:, :3] * 255)
    distance = np.linalg.norm(corridor[r, c][:, None, :] - scale[None], axis=-1)
    on_scale = distance.min(axis=-1) < 20
    r, c, value = r[on_scale], c[on_scale], distance.argmin(axis=-1)[on_scale] / 255
    assert len(r) > 100
    x = -2.0 + 4.0 * (c + 0.5) / corridor.shape[1]
    y = 10.0 - 20.0 * (r + 0.5) / corridor.shape[0]
    assert np.median(x) == pytest.approx(1.0, abs=0.15)
    assert (y.max(), y.min()) == (pytest.approx(8.0, abs=0.4), pytest.approx(-4.0, abs=0.4))
    # Clearance rose along the path: the colour climbs the scale from start to end.
    expected = np.interp(y, ys[::-1], clearances[::-1]) / 3.0  # the scale runs 0 to 3 m
    assert np.corrcoef(expected, value)[0, 1] > 0.9


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


def test_frames_are_written_behind_the_loop_and_a_line_names_only_frames_on_disk(
    room_scenario: Scenario, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from cavenav.episode import run_folder
    from cavenav.sim.env import CaveNavEnv

    env = CaveNavEnv(room_scenario)
    env.reset(seed=0)
    disk_is_slow = threading.Event()
    real_save = run_folder.save_png
    monkeypatch.setattr(
        run_folder, "save_png", lambda *args: (disk_is_slow.wait(60), real_save(*args))
    )
    folder = run_folder.RunFolder(tmp_path / "run")
    step = {"step": 0}
    try:
        folder.record(step, env.observation, [], {"status": "running", "steps": 1})
        # record() returned with the frames still being encoded: nothing names them yet.
        assert set(step["frames"]) == {"rgb", "depth_png", "depth_exr"}
        assert (tmp_path / "run" / "steps.jsonl").read_text() == ""
        assert not list((tmp_path / "run" / "frames").iterdir())
    finally:
        disk_is_slow.set()
    folder.flush()
    (line,) = run_folder.read_jsonl(tmp_path / "run" / "steps.jsonl")
    assert line["frames"] == step["frames"]
    assert all((tmp_path / "run" / name).is_file() for name in line["frames"].values())
    folder.finish({"status": "finished"}, None, None, plots=False)  # type: ignore[arg-type]
    assert json.loads((tmp_path / "run" / "summary.json").read_text())["status"] == "finished"


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


def test_the_drift_a_vehicle_reports_is_recorded_at_each_step_and_summed(
    room_scenario: Scenario,
) -> None:
    result = run_episode(room_scenario, Scripted(Action(forward=1.0)), FAST, motion=Overshooting())
    assert result.termination == "exit" and result.summary["steps"] == 13  # 14 m at 1.1 m
    assert all(s["drift_m"] == pytest.approx(0.1) for s in result.steps)
    assert result.steps[0]["commanded_pose"]["y"] == pytest.approx(8.0 - 1.0)
    assert result.steps[0]["next_pose"]["y"] == pytest.approx(8.0 - 1.1)
    assert result.summary["mean_drift_m"] == pytest.approx(0.1) == result.summary["max_drift_m"]
    assert result.summary["max_drift_deg"] == 0.0
    kinematic = run_episode(room_scenario, Scripted(Action(forward=1.0)), FAST)
    assert "mean_drift_m" not in kinematic.summary and "drift_m" not in kinematic.steps[0]
