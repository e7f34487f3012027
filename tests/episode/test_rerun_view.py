"""A live 3D view of an episode in Rerun, and any recorded episode replayed into one."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from cavenav.episode.loop import run_episode
from cavenav.episode.rerun_log import (
    ACOUSTIC_ENTITIES,
    ENTITIES,
    RerunWatcher,
    log_run_folder,
    open_recording,
)
from cavenav.episode.settings import EpisodeConfig
from tests.conftest import cavenav
from tests.evaluation.test_report import ScriptedPilot, corridor

rerun_chunk = pytest.importorskip("rerun.chunk", reason="the Rerun view needs rerun-sdk")


def entity_rows(rrd: Path) -> dict[str, int]:
    """Each entity in an .rrd file, read back with Rerun's own reader, and its rows."""
    rows: dict[str, int] = {}
    for chunk in rerun_chunk.RrdReader(rrd).stream().collect().stream():
        rows[chunk.entity_path] = rows.get(chunk.entity_path, 0) + chunk.num_rows
    return rows


FLOWN = ["S4", "--steps", "4", "--resolution", "80x60"]


@pytest.mark.slow
def test_a_run_saves_every_entity_of_the_live_view_step_by_step(tmp_path: Path) -> None:
    rrd = tmp_path / "view" / "s4.rrd"
    done = cavenav("run", *FLOWN, "--out", str(tmp_path / "runs"), "--rerun-save", str(rrd))
    assert done.returncode == 0, done.stderr
    rows = entity_rows(rrd)
    assert {f"/{name}" for name in ENTITIES} <= rows.keys()  # the geometric pilot has a map
    assert rows["/cave"] == rows["/cave/ceiling"] == 1  # static
    assert rows["/pilot/action"] == 4 and rows["/pilot/map"] == 4  # one a decision
    assert rows["/vehicle"] == rows["/vehicle/camera/rgb"] == 5  # the start, then each step


@pytest.mark.slow
def test_view_replays_a_run_folder_with_its_cave_frames_and_decisions(tmp_path: Path) -> None:
    done = cavenav("run", *FLOWN, "--out", str(tmp_path / "runs"))
    assert done.returncode == 0, done.stderr
    (run_dir,) = (tmp_path / "runs").iterdir()
    rrd = tmp_path / "replay.rrd"
    viewed = cavenav("view", str(run_dir), "--save", str(rrd))
    assert viewed.returncode == 0, viewed.stderr
    rows = entity_rows(rrd)
    assert {"/cave", "/cave/exits", "/path", "/vehicle", "/vehicle/sounders"} <= rows.keys()
    assert rows["/vehicle/camera/rgb"] == rows["/vehicle/camera/depth"] == 4  # the frames kept
    assert rows["/pilot/action"] == 4
    steps = (run_dir / "steps.jsonl").read_text().splitlines()
    assert rows["/vehicle"] == len(steps) + 1  # and where the last step left it
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["termination"] == "budget"


def test_a_live_view_with_no_display_is_refused_before_anything_is_flown(tmp_path: Path) -> None:
    headless = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    done = cavenav(
        "run", *FLOWN, "--out", str(tmp_path), "--rerun", env={**headless, "COLUMNS": "240"}
    )
    assert done.returncode == 2
    assert done.stderr.strip().splitlines() == [
        "error: the Rerun viewer needs a display (DISPLAY is not set): save the recording to "
        "a file (--rerun-save, or --save with cavenav view) and open it with `rerun FILE` "
        "where there is one"
    ]
    assert list(tmp_path.iterdir()) == []  # no empty run folder left behind


def test_a_recording_that_cannot_be_written_is_refused_before_anything_is_flown(
    tmp_path: Path,
) -> None:
    blocked = tmp_path / "a-file"
    blocked.write_text("")
    runs = tmp_path / "runs"
    done = cavenav("run", *FLOWN, "--out", str(runs), "--rerun-save", str(blocked / "s4.rrd"))
    assert done.returncode == 2 and len(done.stderr.strip().splitlines()) == 1
    assert done.stderr.startswith(f"error: cannot write the Rerun recording {blocked / 's4.rrd'}")
    assert not runs.exists() or list(runs.iterdir()) == []


def test_view_of_a_folder_that_is_not_a_run_says_so_in_one_line(tmp_path: Path) -> None:
    done = cavenav("view", str(tmp_path), "--save", str(tmp_path / "x.rrd"))
    assert done.returncode == 2
    assert (
        done.stderr.strip()
        == f"error: {tmp_path / 'summary.json'}: cannot be read (No such file or directory)"
    )


def test_the_sonar_dvl_and_reckoned_path_are_logged_live_and_replayed(tmp_path: Path) -> None:
    sensed = EpisodeConfig(max_steps=2, plots=False, sonar="multibeam", dvl=True)
    live = tmp_path / "live.rrd"
    watcher = RerunWatcher(open_recording("live", save=live), sensed.sensors.camera)
    run_dir = tmp_path / "sonar"
    run_episode(corridor(), ScriptedPilot(("forward 1 m",)), sensed, run_dir, watchers=[watcher])
    watcher.recording.disconnect()  # closes the file, as the end of `cavenav run` does
    replay = tmp_path / "replay.rrd"
    summary = json.loads((run_dir / "summary.json").read_text())
    steps = [json.loads(line) for line in (run_dir / "steps.jsonl").open()]
    log_run_folder(open_recording("replay", save=replay), run_dir, summary, steps, corridor())
    for rrd, arrivals in ((live, 3), (replay, 2)):  # live: the start, then each step's end
        rows = entity_rows(rrd)
        assert {f"/{name}" for name in ACOUSTIC_ENTITIES} <= rows.keys()
        assert rows["/vehicle/sonar"] == rows["/vehicle/camera/rgb"] == arrivals
        assert rows["/reckoned"] == rows["/reckoned/sigma"] == 2  # one a step record
        # No velocity before the first move (no bottom track yet), then one a reading.
        assert rows["/dvl/velocity/forward"] == rows["/dvl/altitude"] - 1 == arrivals - 1

    plain = tmp_path / "plain"
    run_episode(corridor(), ScriptedPilot(("forward 1 m",)), EpisodeConfig(max_steps=2), plain)
    steps = [json.loads(line) for line in (plain / "steps.jsonl").open()]
    summary = json.loads((plain / "summary.json").read_text())
    log_run_folder(
        open_recording("plain", save=tmp_path / "plain.rrd"), plain, summary, steps, None
    )
    assert (
        not {f"/{name}" for name in ACOUSTIC_ENTITIES} & entity_rows(tmp_path / "plain.rrd").keys()
    )
