"""Sweeps: a grid of episodes in one folder, resumable, recorded whatever goes wrong."""

from __future__ import annotations

import csv
import errno
import json
import os
import signal
import threading
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from scipy.stats import binomtest, wilcoxon

from cavenav import SCENARIO_SET
from cavenav.core.errors import CavenavError, ConfigError, RecordingError
from cavenav.episode.records import TERMINATIONS
from cavenav.episode.settings import configured
from cavenav.evaluation.comparison import Compared, comparison, latex_table, markdown_table
from cavenav.evaluation.executors import InProcess, LocalPool, deal
from cavenav.evaluation.results import (
    aggregate,
    clustered_difference_ci,
    clustered_wilson,
    compare,
    episode_row,
    outcome,
    paired_difference_ci,
    priced,
    wilson,
)
from cavenav.evaluation.sweep import (
    MAX_EPISODES,
    EpisodeJob,
    EpisodeWorker,
    SweepConfig,
    parse_seeds,
    plan,
    prepare,
    read_rows,
    read_sweep,
    run_sweep,
)
from cavenav.pilots.factory import PilotSpec, VLMOptions
from tests.conftest import flying, write_room


@pytest.fixture
def room(tmp_path: Path) -> str:
    return str(write_room(tmp_path / "caves"))


def sweep(room: str, seeds=(0, 1, 2), **fields) -> SweepConfig:
    return SweepConfig(scenarios=(room,), seeds=tuple(seeds), steps=6, frames="none", **fields)


def test_seeds_are_read_as_ranges_and_lists() -> None:
    assert parse_seeds("0-2,5,1000-1001") == (0, 1, 2, 5, 1000, 1001)
    assert parse_seeds("3, 3,2") == (3, 2)
    with pytest.raises(ConfigError, match="'x1' is not a seed or a range"):
        parse_seeds("0-3,x1")
    with pytest.raises(ConfigError, match="runs backwards"):
        parse_seeds("9-2")


@pytest.mark.slow
def test_a_sweep_flies_every_cave_once_and_writes_its_tables(room: str, tmp_path: Path) -> None:
    out = tmp_path / "sweep"
    rows = run_sweep(sweep(room), out, InProcess())
    assert [r["episode"] for r in rows] == ["room-seed0000", "room-seed0001", "room-seed0002"]
    assert {r["outcome"] for r in rows} == {"budget"}  # 6 steps cannot cross 14 m
    with open(out / "results.csv", newline="") as f:
        table = list(csv.DictReader(f))
    assert [r["episode"] for r in table] == [r["episode"] for r in rows]
    assert table[0]["steps"] == "6" and table[0]["run_dir"] == "episodes/room-seed0000"
    groups = json.loads((out / "aggregate.json").read_text())["groups"]
    assert [(g["scenario"], g["completed"], g["successes"]) for g in groups] == [
        ("room", 3, 0),
        ("all", 3, 0),
    ]
    low, high = binomtest(0, 3).proportion_ci(method="wilson")
    assert groups[0]["success_ci95"] == [round(low, 4), round(high, 4)]
    assert json.loads((out / "sweep.json").read_text())["seeds"] == [0, 1, 2]
    assert not list(out.glob("episodes/*/frames"))  # --frames none


def test_every_record_names_the_scenario_set_its_caves_and_images_belong_to(
    room: str, tmp_path: Path
) -> None:
    out = tmp_path / "sweep"
    run_sweep(sweep(room), out, InProcess())
    assert json.loads((out / "sweep.json").read_text())["scenario_set"] == SCENARIO_SET
    summary = json.loads((out / "episodes/room-seed0000/summary.json").read_text())
    assert summary["scenario_set"] == SCENARIO_SET
    with open(out / "results.csv", newline="") as f:
        assert {row["scenario_set"] for row in csv.DictReader(f)} == {SCENARIO_SET}
    # A summary written before sets were recorded belongs to set 1.
    summary.pop("scenario_set")
    (out / "episodes/room-seed0000/summary.json").write_text(json.dumps(summary))
    assert episode_row(out / "episodes/room-seed0000", out)["scenario_set"] == "1"


@pytest.mark.slow
def test_a_rerun_skips_finished_episodes_and_reflies_interrupted_ones(
    room: str, tmp_path: Path
) -> None:
    out = tmp_path / "sweep"
    run_sweep(sweep(room), out, InProcess())
    kept = out / "episodes" / "room-seed0000" / "summary.json"
    before = kept.stat().st_mtime_ns
    # seed 1 was cut short by a kill: its summary still says running, a step is half written
    cut = out / "episodes" / "room-seed0001"
    summary = json.loads((cut / "summary.json").read_text())
    (cut / "summary.json").write_text(json.dumps({**summary, "status": "running"}))
    with open(cut / "steps.jsonl", "a") as f:
        f.write('{"step": 6, "po')
    assert read_rows(out)[1]["outcome"] == "incomplete"

    flown = []
    left = []
    run_sweep(sweep(room), out, InProcess(), flown.append, lambda n, grid: left.append((n, grid)))
    assert left == [(1, 3)] and [r["episode"] for r in flown] == ["room-seed0001"]
    assert kept.stat().st_mtime_ns == before
    assert read_rows(out)[1]["outcome"] == "budget"


def test_each_cave_seed_draws_its_own_noise_unless_the_noise_seed_is_held(
    room: str, tmp_path: Path
) -> None:
    # A scenario file is one cave whatever the seed: only the noise can tell seeds apart.
    def first_frames(out: Path, **fields) -> tuple[list[bytes], list[tuple]]:
        config = SweepConfig((room,), (0, 1), steps=1, frames="png", **fields)
        run_sweep(config, out, InProcess())
        folders = sorted((out / "episodes").iterdir())
        frames = [(f / "frames" / "step_0000_rgb.png").read_bytes() for f in folders]
        summaries = [json.loads((f / "summary.json").read_text()) for f in folders]
        return frames, [(s["seed"], s["noise_seed"], s["pilot_seed"]) for s in summaries]

    frames, seeds = first_frames(tmp_path / "own")
    assert frames[0] != frames[1] and seeds == [(None, 0, None), (None, 1, None)]
    frames, seeds = first_frames(tmp_path / "held", noise_seed=5)
    assert frames[0] == frames[1] and seeds == [(None, 5, None), (None, 5, None)]
    assert json.loads((tmp_path / "held" / "sweep.json").read_text())["episode"]["noise_seed"] == 5


def test_trials_draw_noise_of_their_own_also_when_it_is_held(room: str) -> None:
    jobs = plan(sweep(room, seeds=(7,), trials=3))
    assert [job.noise_seed() for job in jobs] == [job.pilot_seed for job in jobs]
    assert jobs[0].noise_seed() == 7 and len({job.noise_seed() for job in jobs}) == 3
    assert [job.noise_seed(held=5) for job in jobs] == [5, 6, 7]


def test_another_configuration_in_the_same_folder_is_refused(room: str, tmp_path: Path) -> None:
    out = tmp_path / "sweep"
    run_sweep(sweep(room, seeds=(0,)), out, InProcess())
    with pytest.raises(ConfigError, match=r"episode.steps: 6 there, 7 now"):
        run_sweep(SweepConfig((room,), (0,), steps=7, frames="none"), out, InProcess())
    with pytest.raises(ConfigError, match="pilot.name"):
        run_sweep(sweep(room, seeds=(0,), pilot=PilotSpec("random")), out, InProcess())
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "notes.txt").write_text("mine")
    with pytest.raises(ConfigError, match="not empty and holds no sweep.json"):
        run_sweep(sweep(room), tmp_path / "other", InProcess())


def test_a_sweep_begun_before_stuck_endings_resumes_with_the_options_it_was_flown_with(
    room: str, tmp_path: Path
) -> None:
    # sweep.json as written before episodes could end stuck: 150 steps, no stuck_after.
    out = tmp_path / "sweep"
    old = SweepConfig((room,), (0,), steps=None, stuck_after=None, frames="none").to_dict()
    old["episode"]["steps"] = 150
    del old["episode"]["stuck_after"]
    (out / "episodes").mkdir(parents=True)
    (out / "sweep.json").write_text(json.dumps(old))
    today = SweepConfig((room,), (0,), steps=None, stuck_after=50, frames="none")
    with pytest.raises(ConfigError, match="add --stuck-after 0"):
        run_sweep(today, out, InProcess())
    rows = run_sweep(replace(today, stuck_after=None), out, InProcess())
    assert len(rows) == 1


def test_a_sweep_json_written_before_episode_settings_resumes_as_the_same_sweep(
    room: str, tmp_path: Path
) -> None:
    # As `cavenav eval --scenarios ROOM --seeds 0-1 --steps 6 --frames png --shield
    # --sounder beam --depth-max 12 --water turbid --depth-noise 0.05 --resolution 160x120`
    # wrote it when SweepConfig kept loose "sensors".
    written = {
        "format": 1,
        "scenarios": [room],
        "seeds": [0, 1],
        "pilot": {"name": "geometric", "label": "geometric"},
        "episode": {"steps": 6, "stuck_after": 50, "shield": True, "frames": "png"},
        "difficulty": {},
        "sensors": {
            "sounder": "beam",
            "depth_max_m": 12.0,
            "optics": {"water": "turbid", "depth_noise_m": 0.05},
            "resolution": [160, 120],
        },
        "created_at": "2026-11-20T10:00:00+00:00",
        "cavenav_version": "0.1.0",
    }
    out = tmp_path / "sweep"
    (out / "episodes").mkdir(parents=True)
    (out / "sweep.json").write_text(json.dumps(written))
    config, _ = read_sweep(out)
    assert config.settings == configured(
        steps=6,
        shield=True,
        save_exr=False,
        sounder="beam",
        depth_max_m=12.0,
        optics={"water": "turbid", "depth_noise_m": 0.05},
        resolution=(160, 120),
        noise_seed=0,  # every episode's noise was drawn from seed 0 then
    )
    stamps = ("created_at", "cavenav_version", "scenario_set")
    again = {k: v for k, v in config.to_dict().items() if k not in stamps}
    assert again == {k: v for k, v in written.items() if k not in stamps}
    assert json.dumps(again) == json.dumps({k: written[k] for k in again})  # key order too
    assert len(prepare(config, out)) == 2  # the same command resumes it
    today = replace(config.settings, seed=None)  # the same command today
    with pytest.raises(ConfigError, match="add --noise-seed 0"):
        prepare(SweepConfig((room,), (0, 1), settings=today), out)
    with pytest.raises(ConfigError, match=r"sensors.resolution: \[160, 120\] there, null now"):
        settings = replace(config.settings, resolution=None)
        prepare(SweepConfig((room,), (0, 1), settings=settings), out)


def test_episode_settings_are_given_by_name_and_a_wrong_name_is_refused() -> None:
    config = SweepConfig(("S1",), (0,), steps=6, frames="png", difficulty={"constriction_m": 3.0})
    assert config.settings.max_steps == 6 and config.settings.frames == "png"
    assert config.settings.save_frames and not config.settings.save_exr
    with pytest.raises(TypeError, match="step"):
        SweepConfig(("S1",), (0,), step=6)
    with pytest.raises(ConfigError, match="--frames must be one of all, png, none, got 'jpeg'"):
        SweepConfig(("S1",), (0,), frames="jpeg")


def test_a_script_reads_and_sets_the_settings_by_their_names_before_episode_settings(
    room: str, tmp_path: Path
) -> None:
    sensors = {
        "sounder": "beam",
        "depth_max_m": 8.0,
        "optics": {"particles": 20.0},
        "resolution": [160, 120],
    }
    config = SweepConfig(
        (room,), (0,), steps=6, stuck_after=None, shield=True, frames="png", sensors=sensors
    )
    assert (config.steps, config.stuck_after, config.shield, config.frames) == (
        6,
        None,
        True,
        "png",
    )
    assert config.difficulty == {}
    assert config.sensors == sensors
    assert config.settings.sensors.sounder == "beam" and config.settings.resolution == (160, 120)
    with pytest.raises(AttributeError):
        config.steps = 7  # type: ignore[misc]
    with pytest.raises(ConfigError, match="sensors: unknown key"):
        SweepConfig((room,), (0,), sensors={"sidescan": "beam"})
    with pytest.raises(ConfigError, match="sonar: 'beam'; choose ping360, multibeam or none"):
        SweepConfig((room,), (0,), sensors={"sonar": "beam"})
    knobs = SweepConfig(("S1",), (0,), difficulty={"constriction_m": 3.0})
    assert knobs.difficulty == {"constriction_m": 3.0}
    assert knobs.sensors == {"sounder": "camera", "depth_max_m": 20.0, "optics": {}}
    cave = config.settings.load(room, 0)
    episode = EpisodeWorker(config, tmp_path).episode_config(cave)
    assert episode == config.settings.for_episode(cave, 0)
    assert (episode.max_steps, episode.shield, episode.save_exr) == (6, True, False)
    assert episode.sensors.sounder == "beam" and episode.sensors.resolution == (160, 120)


def test_a_failing_episode_is_recorded_and_the_sweep_goes_on(room: str, tmp_path: Path) -> None:
    bad = str(write_room(tmp_path / "caves", start_y=30.0))  # the start lies outside the room
    out = tmp_path / "sweep"
    rows = run_sweep(SweepConfig((bad, room), (0,), steps=4, frames="none"), out, InProcess())
    assert [r["outcome"] for r in rows] == ["error", "budget"]
    assert "ScenarioError" in rows[0]["error"] and "outside" in rows[0]["error"]
    assert (out / "episodes" / "room-bad-seed0000" / "error.txt").is_file()


@pytest.mark.slow
def test_worker_processes_give_the_same_episodes_as_one_process(room: str, tmp_path: Path) -> None:
    config = sweep(room, seeds=(0, 1, 2, 3), pilot=PilotSpec("random"))
    alone = run_sweep(config, tmp_path / "alone", InProcess())
    pooled = run_sweep(config, tmp_path / "pool", LocalPool(workers=2, concurrency=4))
    keys = ("episode", "outcome", "steps", "path_length_m", "min_clearance_m")
    assert [[r[k] for k in keys] for r in pooled] == [[r[k] for k in keys] for r in alone]
    pids = [
        json.loads((run / "summary.json").read_text())["pid"]
        for run in (tmp_path / "pool" / "episodes").iterdir()
    ]
    # Four episodes, two workers with room for four each: two each, in the pool's processes.
    assert sorted(Counter(pids).values()) == [2, 2] and os.getpid() not in pids


def test_jobs_are_dealt_to_the_least_loaded_worker_until_every_slot_is_taken() -> None:
    jobs = deque(EpisodeJob("S1", k) for k in range(5))
    dealt = deal(jobs, {"a": 0, "b": 1, "c": 0}, most=2)
    assert [worker for worker, _ in dealt] == ["a", "c", "a", "b", "c"]
    assert [job.seed for _, job in dealt] == [0, 1, 2, 3, 4] and not jobs
    more = deque(EpisodeJob("S1", k) for k in range(5, 8))
    assert [w for w, _ in deal(more, {"a": 2, "b": 1}, most=2)] == ["b"] and len(more) == 2


def test_the_failure_taxonomy_reads_the_last_steps() -> None:
    finished = {"status": "finished", "termination": "budget"}

    def steps(progress, xs):
        return [
            {"action": "forward 0.5 m", "progress_m": p, "pose": {"x": x, "y": 0.0, "z": 0.0}}
            for p, x in zip(progress, xs, strict=True)
        ]

    still = steps([5.0] * 30, [0.0] * 30)
    pacing = steps([5.0, 5.3] * 15, [0.0, 0.5] * 15)
    slow = steps([0.1 * k for k in range(30)], [0.1 * k for k in range(30)])
    assert outcome(finished, still) == "stuck"
    assert outcome(finished, pacing) == "oscillating"
    assert outcome(finished, slow) == "budget"
    assert outcome({"status": "finished", "termination": "exit"}, []) == "success"
    assert outcome({"status": "running"}, still) == "incomplete"
    assert outcome({"status": "crashed", "error": "boom"}, []) == "error"


def row(scenario: str, seed: int, result: str) -> dict:
    return {"scenario": scenario, "seed": seed, "pilot": "p", "outcome": result,
            "run_dir": f"episodes/{scenario}-seed{seed:04d}"}  # fmt: skip


@pytest.mark.parametrize("termination", TERMINATIONS)
def test_every_termination_but_the_exit_and_the_budget_is_its_own_outcome(
    termination: str,
) -> None:
    finished = {"status": "finished", "termination": termination}
    expected = {"exit": "success", "budget": "stuck"}.get(termination, termination)
    assert outcome(finished, []) == expected  # a budget ending with no steps went nowhere


def test_comparison_pairs_caves_and_tests_the_discordant_ones() -> None:
    a = [row("S1", k, "success") for k in range(10)] + [row("S2", 0, "collision")]
    b = [row("S1", k, "success" if k < 3 else "collision") for k in range(10)]
    b += [row("S2", 0, "success"), row("S3", 0, "success")]
    result = compare(a, b)
    overall = result["overall"]
    assert overall["pairs"] == 11 and result["unpaired"] == 1
    assert overall["difference"] == round(10 / 11 - 4 / 11, 4)
    assert overall["mcnemar_p"] == pytest.approx(binomtest(7, 8, 0.5).pvalue)
    assert [c["cave"] for c in overall["only_b"]] == ["S2 seed 0"]
    assert overall["only_a"][0] == {
        "cave": "S1 seed 3",
        "a": "episodes/S1-seed0003",
        "b": "episodes/S1-seed0003",
        "outcome_a": "success",
        "outcome_b": "collision",
    }
    assert result["per_scenario"]["S2"]["mcnemar_p"] == 1.0


def test_trials_fly_each_cave_several_times_each_with_a_draw_of_its_own(
    room: str, tmp_path: Path
) -> None:
    random = PilotSpec("random")
    rows = run_sweep(sweep(room, seeds=(0, 1), pilot=random, trials=3), tmp_path / "t", InProcess())
    assert [(r["episode"], r["trial"]) for r in rows] == [
        (f"room-seed000{seed}-trial{trial}", trial) for seed in (0, 1) for trial in (1, 2, 3)
    ]
    assert json.loads((tmp_path / "t" / "sweep.json").read_text())["trials"] == 3

    def actions(folder: Path) -> list[str]:
        steps = (folder / "steps.jsonl").read_text().splitlines()
        return [json.loads(line)["action"] for line in steps]

    once = tmp_path / "once"
    run_sweep(sweep(room, seeds=(0,), pilot=random), once, InProcess())
    first, *others = (tmp_path / "t" / "episodes" / f"room-seed0000-trial{k}" for k in (1, 2, 3))
    assert actions(first) == actions(once / "episodes" / "room-seed0000")  # trial 1: as flown once
    assert all(actions(other) != actions(first) for other in others)

    summary = json.loads((tmp_path / "t" / "aggregate.json").read_text())
    assert summary["groups"][0]["caves"] == 2 and summary["groups"][0]["completed"] == 6
    assert [(c["seed"], c["completed"], len(c["episodes"])) for c in summary["caves"]] == [
        (0, 3, 3),
        (1, 3, 3),
    ]
    with pytest.raises(ConfigError, match="trials: 3 there, 2 now"):
        run_sweep(sweep(room, seeds=(0, 1), pilot=random, trials=2), tmp_path / "t", InProcess())
    with pytest.raises(ConfigError, match="2 scenarios x 30000 seeds x 2 trials is more than"):
        SweepConfig(("S1", "S2"), tuple(range(30_000)), trials=2)


def test_a_rate_over_caves_flown_several_times_allows_for_their_trials_being_alike() -> None:
    # Every cave's trials alike: the caves are the sample, whatever the episodes' count.
    assert clustered_wilson([(3, 3), (0, 3)] * 10) == wilson(10, 20)
    assert clustered_wilson([(3, 3)] * 20) == wilson(20, 20)
    # Trials that differ within a cave as much as coins do: every episode counts.
    assert clustered_wilson([(2, 3), (1, 3)] * 10) == wilson(30, 60)
    assert clustered_wilson([(1, 1), (0, 1)] * 10) == wilson(10, 20)  # one trial a cave
    low, high = clustered_wilson([(3, 3), (2, 3), (0, 3), (1, 3)] * 5)
    assert (
        wilson(30, 60)[1] - wilson(30, 60)[0] < high - low < wilson(10, 20)[1] - wilson(10, 20)[0]
    )
    assert clustered_wilson([]) is None


def test_the_rate_interval_over_trials_covers_the_true_rate_where_wilson_over_episodes_does_not():
    """20 caves x 3 trials, the caves' own rates drawn around 0.7 with trials of a cave
    much alike (intraclass correlation 0.8): Wilson's interval over the 60 episodes misses
    the mean rate about a quarter of the time; the clustered one about one time in 20."""
    rng = np.random.default_rng(1)
    covered = naive = 0
    for _ in range(400):
        wins = rng.binomial(3, rng.beta(0.7 * 0.25, 0.3 * 0.25, 20))
        low, high = clustered_wilson([(int(k), 3) for k in wins])
        covered += low <= 0.7 <= high
        low, high = wilson(int(wins.sum()), 60)
        naive += low <= 0.7 <= high
    assert covered / 400 > 0.92 and naive / 400 < 0.82


def test_a_comparison_with_trials_tests_the_caves_success_rates() -> None:
    def trials(scenario: str, seed: int, outcomes: str) -> list[dict]:
        return [
            {**row(scenario, seed, {"s": "success", "c": "collision"}[o]), "trial": k + 1,
             "run_dir": f"episodes/{scenario}-seed{seed:04d}-trial{k + 1}"}
            for k, o in enumerate(outcomes)
        ]  # fmt: skip

    a = [r for seed in range(8) for r in trials("S1", seed, "sss" if seed < 6 else "scc")]
    b = [r for seed in range(8) for r in trials("S1", seed, "ccs" if seed < 6 else "scc")]
    result = compare(a, b)
    overall = result["overall"]
    assert result["trials"] and overall["success_test"] == "wilcoxon"
    rates_a, rates_b = [1.0] * 6 + [1 / 3] * 2, [1 / 3] * 8
    assert overall["p"] == pytest.approx(wilcoxon(rates_a, rates_b).pvalue)
    assert overall["difference"] == round(20 / 24 - 8 / 24, 4)
    low, high = overall["difference_ci95"]
    assert 0 < low < overall["difference"] < high <= 1
    assert overall["only_b"] == [] and len(overall["only_a"]) == 6
    assert overall["only_a"][0] == {
        "cave": "S1 seed 0",
        "a": "episodes/S1-seed0000-trial1",  # a success of the side that did better
        "b": "episodes/S1-seed0000-trial1",  # a failure of the other
        "outcome_a": "3/3 success",
        "outcome_b": "1/3 success",
        "rate_a": 1.0,
        "rate_b": 0.3333,
    }
    # Both always through: no difference, with the width that 8 caves (not 24 episodes) allow.
    same = compare(
        [r for seed in range(8) for r in trials("S1", seed, "sss")],
        [r for seed in range(8) for r in trials("S1", seed, "sss")],
    )["overall"]
    margin = 1 - wilson(8, 8)[0]
    assert same["difference_ci95"] == pytest.approx((-margin, margin), abs=1e-4)
    assert same["p"] == 1.0


def test_trials_alike_in_both_sweeps_narrow_the_difference_when_caves_agree() -> None:
    """The correlation between the caves' rates counts as Newcombe's counts it for pairs:
    two pilots that fail in the same hard caves differ less uncertainly."""
    hard, easy = [(0, 3)] * 4, [(3, 3)] * 4
    together = clustered_difference_ci(hard + easy + [(3, 3)] * 2, hard + easy + [(0, 3)] * 2)
    apart = clustered_difference_ci(hard + easy + [(3, 3)] * 2, easy + hard + [(0, 3)] * 2)
    assert together[1] - together[0] < apart[1] - apart[0]


def test_aggregates_count_completed_episodes_only() -> None:
    rows = [row("S1", 0, "success"), row("S1", 1, "incomplete"), row("S1", 2, "error")]
    group = aggregate(rows)[0]
    assert (group["episodes"], group["completed"], group["successes"]) == (3, 2, 1)
    assert group["outcomes"] == {"success": 1, "error": 1, "incomplete": 1}
    assert EpisodeJob("examples/hard_s1.toml", 7).episode == "hard_s1-seed0007"


def test_a_difficulty_knob_goes_to_the_families_that_have_it(room: str) -> None:
    config = SweepConfig(("S1", "S4"), (0,), difficulty={"constriction_m": 3.0, "bend_deg": 60})
    assert config.difficulty_for("S1").to_dict() == {"constriction_m": 3.0}
    assert config.difficulty_for("S4").to_dict() == {"bend_deg": 60.0}
    with pytest.raises(ConfigError, match="bend_deg applies to none of S1, S3"):
        SweepConfig(("S1", "S3"), (0,), difficulty={"bend_deg": 60})
    with pytest.raises(ConfigError, match="unknown difficulty knob 'width'"):
        SweepConfig(("S1",), (0,), difficulty={"width": 3.0})


@pytest.mark.slow
def test_a_small_grid_runs_on_a_local_ray_instance(room: str, tmp_path: Path) -> None:
    pytest.importorskip("ray", reason="Ray is an extra: pip install 'cavenav[ray]'")
    from cavenav.evaluation.executors import RayCluster

    config = sweep(room, seeds=(0, 1, 2), pilot=PilotSpec("random"))
    on_ray = run_sweep(config, tmp_path / "ray", RayCluster("local", workers=2, concurrency=2))
    here = run_sweep(config, tmp_path / "here", InProcess())
    keys = ("episode", "outcome", "steps", "path_length_m")
    assert [[r[k] for k in keys] for r in on_ray] == [[r[k] for k in keys] for r in here]
    assert all(r["status"] == "finished" for r in on_ray)


@pytest.mark.slow
def test_model_pilots_fly_several_episodes_at_once_and_keep_the_key_out(
    room: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from tests.vlm_server import FakeVLM

    secret = "sk-test-0123456789abcdef"
    monkeypatch.setenv("SWEEP_TEST_KEY", secret)
    with FakeVLM(required_key=secret) as server:
        options = VLMOptions(
            model="fake-vlm", base_url=server.base_url, api_key_env="SWEEP_TEST_KEY"
        )
        config = sweep(room, seeds=(0, 1, 2, 3), pilot=PilotSpec("vlm", options))
        rows = run_sweep(config, tmp_path / "vlm", InProcess(concurrency=4))
    assert [r["status"] for r in rows] == ["finished"] * 4
    assert all(r["pilot"] == "vlm:fake-vlm" for r in rows)
    for r in rows:
        lines = (tmp_path / "vlm" / r["run_dir"] / "exchanges.jsonl").read_text().splitlines()
        assert len(lines) == r["steps"]  # each episode its own requests
        # The row's tokens are those its own exchanges were billed.
        assert r["prompt_tokens"] == sum(json.loads(x)["prompt_tokens"] for x in lines) > 0
    for path in (tmp_path / "vlm").rglob("*"):
        if path.is_file():
            assert secret.encode() not in path.read_bytes(), path


def test_a_pilot_is_described_completely_before_any_worker_starts() -> None:
    with pytest.raises(ConfigError, match="unknown pilot 'genius'"):
        PilotSpec("genius")
    with pytest.raises(ConfigError, match="needs --model"):
        PilotSpec("vlm")
    with pytest.raises(ConfigError, match="--price must be 'input,output'"):
        PilotSpec("vlm", VLMOptions(model="m", price="cheap"))
    spec = PilotSpec("vlm", VLMOptions(model="m", api_key_env="MY_KEY"))
    assert spec.label == "vlm:m" and spec.to_dict()["options"]["api_key_env"] == "MY_KEY"


@pytest.mark.slow
def test_a_worker_killed_mid_episode_costs_only_that_episode(room: str, tmp_path: Path) -> None:
    out = tmp_path / "sweep"
    config = SweepConfig((room,), tuple(range(6)), steps=40, frames="none")
    victim: dict[str, int] = {}

    def kill_a_worker_in_flight() -> None:
        episode, pid = next(iter(flying(out, 1, steps=2).items()))
        victim.update(pid=pid, seed=int(episode[-4:]))
        os.kill(pid, signal.SIGKILL)

    killer = threading.Thread(target=kill_a_worker_in_flight)
    killer.start()
    rows = run_sweep(config, out, LocalPool(workers=2))
    killer.join()
    assert victim, "no episode was caught in flight"
    lost = rows[victim["seed"]]
    assert lost["outcome"] == "error" and "worker process died (exit code -9)" in lost["error"]
    others = [r for r in rows if r is not lost]
    assert [r["outcome"] for r in others] == ["success"] * 5  # whichever worker flew them


@pytest.mark.parametrize(("frames", "per_step"), [("all", 3), ("png", 2)])
def test_frames_mode_decides_which_images_are_kept(
    room: str, tmp_path: Path, frames: str, per_step: int
) -> None:
    run_sweep(SweepConfig((room,), (0,), steps=2, frames=frames), tmp_path / frames, InProcess())
    files = sorted(p.name for p in (tmp_path / frames / "episodes/room-seed0000/frames").iterdir())
    assert len(files) == 2 * per_step  # two steps
    assert (
        files[:per_step]
        == ["step_0000_depth.exr", "step_0000_depth.png", "step_0000_rgb.png"][3 - per_step :]
    )


def test_a_model_server_outage_is_an_error_that_a_resumed_sweep_flies_again(
    room: str, tmp_path: Path
) -> None:
    from tests.vlm_server import FakeVLM

    with FakeVLM() as server:
        options = VLMOptions(model="fake-vlm", base_url=server.base_url, retries=0)
        config = sweep(room, seeds=(0,), pilot=PilotSpec("vlm", options))
        server.persistent_fault = "500"  # the server is down, not the model wrong
        (row,) = run_sweep(config, tmp_path / "vlm", InProcess())
        assert row["outcome"] == "error" and "HTTP 500" in row["error"]
        server.persistent_fault = None
        (row,) = run_sweep(config, tmp_path / "vlm", InProcess())
    assert row["outcome"] != "error" and row["error"] is None
    assert row["steps"] == 6


def test_seeds_past_the_largest_grid_are_refused_before_they_are_counted_out(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    import cavenav.evaluation.sweep as sweeps

    def counted_out(first: int, stop: int) -> range:  # the seeds of one range, one by one
        assert stop - first <= MAX_EPISODES, f"{stop - first:,} seeds counted out"
        return range(first, stop)

    monkeypatch.setattr(sweeps, "range", counted_out, raising=False)
    with pytest.raises(ConfigError, match="more than the 100,000 episodes a sweep flies"):
        parse_seeds("0-9999999999")
    with pytest.raises(ConfigError, match="more than the 100,000 episodes"):
        parse_seeds("0-59999,100000-159999")  # each range fits, together they do not
    assert len(parse_seeds("0-99999,0-99999")) == MAX_EPISODES  # repeats count once
    with pytest.raises(ConfigError, match="2 scenarios x 60000 seeds is more than"):
        SweepConfig(("S1", "S2"), tuple(range(60_000)))


@pytest.mark.parametrize(
    ("scenario", "knobs", "refusal"),
    [
        ("S9", {}, "unknown scenario 'S9'"),
        ("S4", {"bend_deg": 500}, r"S4: bend_deg=500 is outside \(0, 150\]"),
        ("missing.toml", {}, "scenario file not found"),
        ("mesh-gone", {}, "mesh file not found"),
        ("hard-s1", {"constriction_m": 0.2}, r"constriction_m=0.2 is outside \[1, 7\]"),
    ],
)
def test_a_grid_that_could_only_crash_is_refused_before_anything_is_written(
    tmp_path: Path, scenario: str, knobs: dict, refusal: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    import cavenav.evaluation.sweep as sweeps
    import cavenav.world.scenario_file as scenarios

    def built(*args: object, **kwargs: object) -> None:
        raise AssertionError("a cave was built to find out")

    # Every way a cave is built: a family drawn, a scenario file's mesh read, a worker's.
    for module, builder in ((scenarios, "procedural_scenario"), (scenarios, "_mesh_scenario"),
                            (sweeps, "load_scenario")):  # fmt: skip
        monkeypatch.setattr(module, builder, built)
    (tmp_path / "hard-s1.toml").write_text('family = "S1"\n[difficulty]\nconstriction_m = 2.4\n')
    gone = write_room(tmp_path / "caves")
    (gone.parent / "room.ply").unlink()
    names = {"mesh-gone": str(gone), "hard-s1": str(tmp_path / "hard-s1.toml")}
    config = SweepConfig(("S1", names.get(scenario, scenario)), (0, 1), difficulty=knobs)
    with pytest.raises(CavenavError, match=refusal) as refused:
        run_sweep(config, tmp_path / "sweep", InProcess())
    assert refused.value.exit_status == 2
    assert not (tmp_path / "sweep").exists()


class FillsUp:
    """write_then_rename on a disk that is full from the ``after``-th write into ``at`` on."""

    def __init__(self, write: Callable[..., None], at: str, after: int):
        self.write, self.at, self.left = write, at, after

    def __call__(self, path: Path, *args: object) -> None:
        self.left -= self.at in str(path)
        if self.left < 0:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        self.write(path, *args)


def test_a_full_disk_stops_the_sweep_in_one_line_and_no_lost_episode_reads_finished(
    room: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from cavenav.episode import run_folder

    out = tmp_path / "sweep"
    # Seed 1 writes its first summary and one step's, then finds the disk full.
    disk = FillsUp(run_folder.write_then_rename, "room-seed0001", after=2)
    monkeypatch.setattr(run_folder, "write_then_rename", disk)
    with pytest.raises(RecordingError, match="room-seed0001.*No space left on device") as stop:
        run_sweep(sweep(room, seeds=(0, 1, 2)), out, InProcess())
    assert stop.value.exit_status == 1
    assert not (out / "results.csv").exists() and not list(out.rglob("*.tmp"))
    monkeypatch.undo()  # room again: the tables of what was flown are written
    rows = read_rows(out)
    assert [(r["status"], r["outcome"]) for r in rows] == [
        ("finished", "budget"),
        ("running", "incomplete"),  # its last whole summary: a rerun flies it again
        ("missing", "incomplete"),  # the sweep stopped: never flown into a full disk
    ]


def test_a_rerun_never_flies_beside_the_workers_of_a_killed_sweep(
    room: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import subprocess
    import sys

    import cavenav.evaluation.sweep as sweeps

    out = tmp_path / "sweep"
    config = sweep(room, seeds=(0,))
    (out / "episodes").mkdir(parents=True)
    (out / "sweep.json").write_text(json.dumps(config.to_dict()))
    # A pool worker holds episodes/ as `hold_episodes` does, for as long as it lives.
    worker = (
        "import fcntl, os, sys, time\n"
        "fcntl.flock(os.open(sys.argv[1], os.O_RDONLY), fcntl.LOCK_SH)\n"
        "print('FLYING', flush=True)\n"
        "time.sleep(float(sys.argv[2]))\n"
    )

    def leftover(lives_s: float) -> subprocess.Popen:
        process = subprocess.Popen(
            [sys.executable, "-c", worker, str(out / "episodes"), str(lives_s)],
            stdout=subprocess.PIPE,
            text=True,
        )
        assert process.stdout is not None and process.stdout.readline() == "FLYING\n"
        return process

    stubborn = leftover(60)
    try:
        monkeypatch.setattr(sweeps, "LEFTOVER_GRACE_S", 0.3)
        with pytest.raises(ConfigError, match="earlier sweep .* still hold its episodes"):
            run_sweep(config, out, InProcess())
    finally:
        stubborn.kill()
        stubborn.wait()
    assert list((out / "episodes").iterdir()) == []  # nothing flown beside it

    dying = leftover(0.5)  # as a killed sweep's workers do, within the grace
    monkeypatch.setattr(sweeps, "LEFTOVER_GRACE_S", 30.0)
    (row,) = run_sweep(config, out, InProcess())
    assert dying.poll() is not None and row["status"] == "finished"


def test_a_full_disk_elsewhere_stops_the_sweep_naming_that_file_not_the_run_folder(
    room: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import cavenav.evaluation.sweep as sweeps

    cache = str(tmp_path / "cache" / "cave.npz")

    def cache_full(*args: object, **kwargs: object) -> None:
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), cache)

    monkeypatch.setattr(sweeps, "load_scenario", cache_full)
    with pytest.raises(RecordingError) as stop:
        run_sweep(sweep(room, seeds=(0, 1)), tmp_path / "sweep", InProcess())
    assert str(stop.value) == f"cannot write {cache}: No space left on device"


def test_a_stopped_sweep_starts_no_other_episode_on_its_threads(
    room: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Once the sweep has stopped (a full disk) its folder is no longer held: a thread
    still flying finishes its episode and takes no other."""
    from cavenav.evaluation.sweep import EpisodeWorker

    started: list[int] = []
    second_in_the_air, sweep_stopped = threading.Event(), threading.Event()

    def fly(self: EpisodeWorker, job: EpisodeJob) -> dict:
        started.append(job.seed)
        if job.seed == 0:  # the disk fills while seed 1 is in the air
            assert second_in_the_air.wait(30)
            raise RecordingError("cannot write the run folder: No space left on device")
        second_in_the_air.set()
        assert sweep_stopped.wait(30)
        return {"episode": job.episode, "outcome": "budget"}

    monkeypatch.setattr(EpisodeWorker, "fly", fly)
    config = sweep(room, seeds=range(6))
    before = set(threading.enumerate())
    with pytest.raises(RecordingError):
        InProcess(concurrency=2).run(config, tmp_path, plan(config), lambda row: None)
    sweep_stopped.set()
    for thread in set(threading.enumerate()) - before:  # the sweep's threads, to their end
        thread.join(30)
    assert sorted(started) == [0, 1]


def test_ctrl_c_goes_on_even_when_the_tables_cannot_be_read_back(room: str, tmp_path: Path) -> None:
    """The tables written on the way out never replace the reason the sweep stopped."""
    out = tmp_path / "sweep"

    class Interrupted:
        def run(self, config: SweepConfig, folder: Path, jobs: object, done: object) -> None:
            (folder / "sweep.json").write_text("[1, 2]")  # damaged meanwhile
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run_sweep(sweep(room), out, Interrupted())


def test_newcombes_paired_interval_matches_the_published_example() -> None:
    """Fagerland, Lydersen and Laake (2017), chapter 8 (Cavo et al. 2012): 59 caves both
    got through, 6 only A, 16 only B, 80 neither: -0.0621 (95% CI -0.1186 to -0.0046)."""
    assert paired_difference_ci(59, 6, 16, 80) == (-0.1186, -0.0046)
    low, high = paired_difference_ci(16, 80, 6, 59)  # the association is now negative
    assert low < (96 - 22) / 161 < high
    assert paired_difference_ci(5, 0, 0, 5)[0] < 0 < paired_difference_ci(5, 0, 0, 5)[1]
    assert paired_difference_ci(0, 0, 0, 0) is None


def test_a_pair_tests_clearance_steps_tokens_and_cost_over_the_caves_both_recorded() -> None:
    a = [{**row("S1", k, "success"), "steps": 20 + k, "min_clearance_m": 1.0} for k in range(8)]
    b = [{**row("S1", k, "collision"), "steps": 10 + 2 * k, "min_clearance_m": 1.0}
         for k in range(8)]  # fmt: skip
    for r in a:
        r.update(prompt_tokens=100, completion_tokens=50, cost_usd=0.01)
    tests = compare(a, b)["overall"]["paired_tests"]
    expected = wilcoxon([20 + k for k in range(8)], [10 + 2 * k for k in range(8)]).pvalue
    assert tests["steps"] == {"pairs": 8, "median_difference": 6.5, "p": pytest.approx(expected)}
    assert tests["min_clearance_m"] == {"pairs": 8, "median_difference": 0.0, "p": 1.0}
    assert tests["tokens"] is None and tests["cost_usd"] is None  # B is not a model


def test_a_comparison_ranks_every_sweep_and_pairs_each_with_each() -> None:
    def sweep(label: str, wins: int, scenario: str = "S1") -> Compared:
        rows = [{**row(scenario, k, "success" if k < wins else "collision"), "pilot": label}
                for k in range(10)]  # fmt: skip
        return Compared(Path(label), label, {"pilot": {"name": label}}, rows)

    result = comparison([sweep("random", 1), sweep("vlm:x_1", 9), sweep("geometric", 6)])
    assert [s["pilot"] for s in result["leaderboard"]] == ["vlm:x_1", "geometric", "random"]
    assert [(p["a"], p["b"]) for p in result["pairs"]] == [
        ("random", "vlm:x_1"), ("random", "geometric"), ("vlm:x_1", "geometric")
    ]  # fmt: skip
    assert [s["label"] for s in result["sweeps"]] == ["random", "vlm:x_1", "geometric"]
    assert list(result["per_family"]) == ["S1"]
    low, high = wilson(9, 10)
    markdown = markdown_table(result).splitlines()
    assert markdown[2].startswith(f"| vlm:x_1 | 9/10 | 90% ({low:.0%}-{high:.0%}) | 1 |")
    assert len(markdown) == 2 + 3
    assert r"vlm:x\_1 & 9/10 & 90\% (" in latex_table(result)


def test_spl_averages_every_completed_episode_a_failure_scoring_nothing() -> None:
    rows = [
        {**row("S1", 0, "success"), "spl": 0.9},
        {**row("S1", 1, "success"), "spl": 0.7},
        {**row("S1", 2, "collision"), "spl": 0.0},
        {**row("S1", 3, "error"), "spl": None},  # crashed: no record of it, still a failure
        row("S1", 4, "incomplete"),
    ]
    assert aggregate(rows)[0]["spl"] == pytest.approx((0.9 + 0.7) / 4)
    rows[1]["spl"] = None  # a success flown before SPL was recorded: no honest mean
    assert aggregate(rows)[0]["spl"] is None


def test_recorded_tokens_are_priced_after_the_fact() -> None:
    model = {**row("S1", 0, "success"), "prompt_tokens": 2_000_000, "completion_tokens": 100_000}
    geometric = {**row("S1", 1, "success"), "prompt_tokens": None, "cost_usd": None}
    priced_rows = priced([model, geometric], (0.5, 4.0))
    assert priced_rows[0]["cost_usd"] == pytest.approx(2 * 0.5 + 0.1 * 4.0)
    assert priced_rows[1]["cost_usd"] is None and "cost_usd" not in model  # a copy


def test_a_group_says_what_one_success_costs_and_its_path_efficiency_over_every_episode():
    spent = {"prompt_tokens": 900, "completion_tokens": 100, "cost_usd": 0.02}
    rows = [
        {**row("S1", 0, "success"), **spent, "path_efficiency": 0.9},
        {**row("S1", 1, "collision"), **spent, "path_efficiency": 0.3},
    ]
    group = aggregate(rows)[0]
    assert group["tokens_per_success"] == 2000 and group["cost_per_success_usd"] == 0.04
    assert group["path_efficiency"] == 0.9 and group["path_efficiency_all"] == 0.6
    no_model = aggregate([row("S1", 0, "success")])[0]
    assert no_model["tokens_per_success"] is None and no_model["cost_per_success_usd"] is None
