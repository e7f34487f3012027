"""Records read back, whatever was done to them: a damaged summary.json, steps.jsonl or
sweep.json is one line naming the file and the field, a damaged episode never stops the
report or the comparison of the others, and a folder that refuses the report or the
comparison is one line too.

One 3-step run folder is flown per module in the test corridor; sweep folders are
assembled from copies of it as `cavenav eval` lays them out.
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from pathlib import Path

import pytest

from cavenav.core.errors import CavenavWarning, ConfigError, RecordError, RecordingError
from cavenav.episode.loop import run_episode
from cavenav.episode.records import read_steps, read_summary, read_sweep_file
from cavenav.episode.settings import EpisodeConfig
from cavenav.evaluation.report import write_report
from cavenav.evaluation.results import compare
from cavenav.evaluation.sweep import SweepConfig, prepare, read_rows
from tests.conftest import cavenav, read_only, write_room
from tests.evaluation.test_report import ScriptedPilot, corridor, make_sweep

EPISODES = ("room-seed0000", "room-seed0001")


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Three 1 m moves down the test corridor, frames saved, no plots."""
    run_dir = tmp_path_factory.mktemp("records") / "run"
    config = EpisodeConfig(max_steps=3, plots=False)
    run_episode(corridor(), ScriptedPilot(("forward 1 m",)), config, run_dir)
    return run_dir


@pytest.fixture
def sweep(run: Path, tmp_path: Path) -> Callable[[str], Path]:
    """A new two-episode sweep folder named ``name`` under tmp_path, each time it is called."""
    return lambda name: make_sweep(tmp_path / name, {episode: run for episode in EPISODES})


def damage(path: Path, text: str) -> Path:
    path.write_text(text, encoding="utf-8")
    return path


def one_line(error: pytest.ExceptionInfo[Exception]) -> str:
    message = str(error.value)
    assert "\n" not in message
    return message


# ------------------------------------------------------------------ the reader


@pytest.mark.parametrize(
    ("text", "says"),
    [
        ("[1, 2]", "holds an array, not a JSON object"),
        ('"finished"', "holds a string, not a JSON object"),
        ("3", "holds a number, not a JSON object"),
        ("null", "holds null, not a JSON object"),
        ("true", "holds true, not a JSON object"),
        ('{"steps": "many"}', "field 'steps': Input should be a valid integer"),
        ('{"status": 5}', "field 'status': Input should be a valid string"),
        ('{"usage": 3}', "field 'usage': Input should be a valid dictionary"),
        ('{"path_length_m": "far"}', "field 'path_length_m': Input should be a valid number"),
        ('{"exits": [{"point": [0, 1], "normal": [0, 0, 1], "radius": 3}]}', "'exits.0.point.2'"),
        ('{"status": "finish', "not valid JSON"),
    ],
)
def test_a_damaged_summary_is_one_line_naming_the_file_and_the_field(
    tmp_path: Path, text: str, says: str
) -> None:
    path = damage(tmp_path / "summary.json", text)
    with pytest.raises(RecordError) as error:
        read_summary(path)
    assert one_line(error).startswith(f"{path}: ") and says in str(error.value)
    assert error.value.exit_status == 2


def test_a_summary_reads_back_as_it_was_written(run: Path) -> None:
    """Nothing added (no defaults), nothing dropped (fields the models do not name)."""
    written = json.loads((run / "summary.json").read_text())
    assert json.loads(json.dumps(read_summary(run / "summary.json"))) == written


def test_a_whole_number_reads_back_whole_where_it_must(run: Path, tmp_path: Path) -> None:
    """A difficulty count (obstacles = 3) read back as 3.0 would be refused by Difficulty:
    a resumed sweep over harder caves would fail."""
    knobs = {"obstacles": 3, "constriction_m": 2.4}
    sweep_json = {**SweepConfig(("S3",), (0,)).to_dict(), "difficulty": knobs}
    path = damage(tmp_path / "sweep.json", json.dumps(sweep_json))
    assert read_sweep_file(path)["difficulty"] == knobs
    assert type(read_sweep_file(path)["difficulty"]["obstacles"]) is int
    summary = json.loads((run / "summary.json").read_text())
    path = damage(tmp_path / "summary.json", json.dumps({**summary, "difficulty": knobs}))
    assert type(read_summary(path)["difficulty"]["obstacles"]) is int


def test_a_steps_line_cut_short_is_skipped_and_a_wrong_one_is_named_by_its_line(
    run: Path, tmp_path: Path
) -> None:
    lines = (run / "steps.jsonl").read_text().splitlines()
    cut = damage(tmp_path / "cut.jsonl", "\n".join([*lines[:2], lines[2][:40]]))
    assert [s["step"] for s in read_steps(cut)] == [0, 1]  # a kill cut the last line short
    step = json.loads(lines[1])
    for record, field in (({**step, "pose": None}, "(top level)"), ([1, 2], None),
                          ({**step, "progress_m": "far"}, "progress_m")):  # fmt: skip
        wrong = damage(tmp_path / "wrong.jsonl", "\n".join([lines[0], json.dumps(record)]))
        with pytest.raises(RecordError) as error:
            read_steps(wrong)
        assert one_line(error).startswith(f"{wrong} line 2: ")
        assert field is None or f"field '{field}'" in str(error.value)


# ------------------------------------------------------------------ sweeps


@pytest.mark.parametrize(
    ("text", "says"),
    [
        ("{}", "field 'scenarios': Field required"),
        ("[]", "holds an array, not a JSON object"),
        ('{"scenarios": ["room"], "seeds": [0], "pilot": {}, "episode": {}}', "field 'pilot.name'"),
    ],
)
def test_a_damaged_sweep_json_is_one_line_naming_the_field_wherever_it_is_read(
    sweep: Callable[[str], Path], text: str, says: str
) -> None:
    folder = sweep("s")
    damage(folder / "sweep.json", text)
    for read in (
        lambda: read_rows(folder),  # report, compare
        lambda: prepare(SweepConfig(("room",), (0, 1)), folder),  # a resumed eval
        lambda: read_sweep_file(folder / "sweep.json"),
    ):
        with pytest.raises(RecordError) as error:
            read()
        assert one_line(error).startswith(f"{folder / 'sweep.json'}: {says}")


def test_the_command_line_says_which_field_of_sweep_json_is_damaged(
    sweep: Callable[[str], Path],
) -> None:
    folder = damage(sweep("s") / "sweep.json", "{}").parent
    for command in (("report", str(folder)), ("compare", str(folder), str(sweep("good")))):
        done = cavenav(*command)
        assert done.returncode == 2, done.stderr
        assert done.stderr == f"error: {folder / 'sweep.json'}: field 'scenarios': Field required\n"


@pytest.mark.parametrize("text", ["[1, 2]", '{"status": "finished", "steps": "many"}'])
def test_a_damaged_episode_counts_as_an_error_and_the_report_and_comparison_go_on(
    sweep: Callable[[str], Path], text: str
) -> None:
    folder, good = sweep("s"), sweep("good")
    summary = damage(folder / "episodes" / EPISODES[1] / "summary.json", text)
    with pytest.warns(CavenavWarning, match=f"^{summary}: .*; the episode counts as an error$"):
        rows = read_rows(folder)
    assert [r["outcome"] for r in rows] == ["budget", "error"]
    assert rows[1]["scenario"] == "room" and rows[1]["status"] == "damaged"
    assert str(summary) in rows[1]["error"]
    with pytest.warns(CavenavWarning):
        index = write_report(folder)
    page = index.parent / "episodes" / f"{EPISODES[1]}.html"
    assert "damaged record" in page.read_text() and str(summary) in page.read_text()
    with pytest.warns(CavenavWarning):
        result = compare(read_rows(folder, write=False), read_rows(good, write=False))
    assert result["overall"]["pairs"] == 2
    assert [c["cave"] for c in result["overall"]["only_b"]] == []  # both ran out of steps


@pytest.mark.parametrize(
    ("record", "text"), [("summary.json", "[1, 2]"), ("steps.jsonl", "[1, 2]")]
)
def test_a_resumed_sweep_flies_an_episode_with_a_damaged_record_again(
    sweep: Callable[[str], Path], record: str, text: str
) -> None:
    """What its results row counts as an error, a resumed sweep flies again: an error
    that no resume clears would stay in the sweep's results for good."""
    folder = sweep("s")
    damage(folder / "episodes" / EPISODES[0] / record, text)
    with pytest.warns(CavenavWarning, match="the episode counts as an error"):
        assert [r["outcome"] for r in read_rows(folder, write=False)] == ["error", "budget"]
    left = prepare(SweepConfig(("room",), (0, 1)), folder)  # as make_sweep configured it
    assert [job.episode for job in left] == [EPISODES[0]]


def test_a_resumed_sweep_whose_sweep_json_names_an_unknown_pilot_option_is_one_line(
    sweep: Callable[[str], Path],
) -> None:
    folder = sweep("s")
    settings = json.loads((folder / "sweep.json").read_text())
    settings["pilot"]["options"] = {"foo": 1}
    damage(folder / "sweep.json", json.dumps(settings))
    for read in (
        lambda: prepare(SweepConfig(("room",), (0, 1)), folder),  # a resumed eval
        lambda: read_rows(folder),  # report, compare
    ):
        with pytest.raises(ConfigError) as error:
            read()
        assert one_line(error).startswith(f"{folder / 'sweep.json'} cannot be read as a sweep: ")
        assert "foo" in str(error.value) and error.value.exit_status == 2


def test_damaged_model_exchanges_are_skipped_with_one_warning_and_the_outcome_stands(
    sweep: Callable[[str], Path],
) -> None:
    """exchanges.jsonl is the audit trail, not the result: the page shows the episode as
    its results row counts it."""
    folder = sweep("s")
    exchanges = folder / "episodes" / EPISODES[1] / "exchanges.jsonl"
    good = {"step": 0, "attempt": 0, "messages": [{"role": "system", "content": "fly"}]}
    damage(exchanges, "\n".join([json.dumps(good), '{"step": "x"}', "[1]"]))
    with pytest.warns(CavenavWarning) as warned:
        index = write_report(folder)
    about = [str(w.message) for w in warned if str(exchanges) in str(w.message)]
    assert len(about) == 1 and about[0].startswith(f"{exchanges} line 2: ")
    rows = read_rows(folder, write=False)
    assert [r["outcome"] for r in rows] == ["budget", "budget"]
    page = (index.parent / "episodes" / f"{EPISODES[1]}.html").read_text()
    assert "damaged record" not in page and "budget" in page


def test_the_page_of_an_episode_never_flown_says_it_is_incomplete(
    sweep: Callable[[str], Path],
) -> None:
    folder = sweep("s")
    shutil.rmtree(folder / "episodes" / EPISODES[1])
    index = write_report(folder)
    assert [r["outcome"] for r in read_rows(folder, write=False)] == ["budget", "incomplete"]
    page = (index.parent / "episodes" / f"{EPISODES[1]}.html").read_text()
    assert "no run folder" in page and "incomplete" in page
    assert "counts as an error" not in page


@pytest.mark.parametrize(
    ("record", "text", "says"),
    [
        ("summary.json", "[1, 2]", "not a JSON object"),
        ("summary.json", '{"scenario": 5}', "field 'scenario'"),
        ("summary.json", '{"scenario": "room", "seed": "x"}', "field 'seed'"),
        ("steps.jsonl", "[1, 2]", "line 1 is not a JSON object"),
        ("steps.jsonl", '{"step": 0, "action": 7}', "line 1 needs a text 'action'"),
    ],
)
def test_a_replay_of_a_damaged_recording_is_one_line_naming_the_file(
    run: Path, tmp_path: Path, record: str, text: str, says: str
) -> None:
    recording = tmp_path / "recording"
    shutil.copytree(run, recording)
    damage(recording / record, text)
    room = write_room(tmp_path / "caves")
    done = cavenav("run", str(room), "--pilot", "replay", "--from", str(recording),
                   "--out", str(tmp_path / "replays"))  # fmt: skip
    assert done.returncode == 2, done.stderr
    assert done.stderr.startswith(f"error: {recording / record}: ")
    assert says in done.stderr and done.stderr.count("\n") == 1
    assert not (tmp_path / "replays").exists()  # refused before anything was written


# ------------------------------------------------------------------ writing


def test_a_report_into_a_read_only_folder_is_one_line_and_exits_1(
    run: Path, sweep: Callable[[str], Path], tmp_path: Path
) -> None:
    lone = tmp_path / "lone"
    shutil.copytree(run, lone)
    for folder in (sweep("s"), lone):
        with read_only(folder), pytest.raises(RecordingError) as error:
            write_report(folder)
        assert one_line(error).startswith(f"cannot write the report in {folder}: ")
        assert one_line(error).endswith(("Permission denied", "Read-only file system"))
        assert error.value.exit_status == 1
    assert not (lone / "report.html").exists()


def test_compare_json_that_cannot_be_written_is_one_line(
    sweep: Callable[[str], Path], tmp_path: Path
) -> None:
    a, b = sweep("a"), sweep("b")
    (tmp_path / "a-file").write_text("")
    folder = cavenav("compare", str(a), str(b), "--json", str(tmp_path))
    assert folder.returncode == 2
    assert folder.stderr == f"error: --json {tmp_path} is a folder: name the file to write\n"
    under_a_file = tmp_path / "a-file" / "c.json"
    done = cavenav("compare", str(a), str(b), "--json", str(under_a_file))
    assert done.returncode == 2 and done.stdout == ""  # found before the sweeps are read
    assert done.stderr == (
        f"error: cannot write {under_a_file}: {tmp_path / 'a-file'} is a file, not a folder\n"
    )


def test_a_plot_cut_short_leaves_no_truncated_image_under_its_name(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    from cavenav.core.files import save_figure

    figure = Figure()
    figure.add_subplot().plot([0, 1], [1, 0])
    save_figure(figure, tmp_path / "side.png", dpi=50)
    whole = (tmp_path / "side.png").read_bytes()
    assert whole.startswith(b"\x89PNG")

    def interrupted(self: Figure, target: Path, **options: object) -> None:
        Path(target).write_bytes(whole[:124])  # Ctrl-C arrives half-way through
        raise KeyboardInterrupt

    monkeypatch.setattr(Figure, "savefig", interrupted)
    with pytest.raises(KeyboardInterrupt):
        save_figure(figure, tmp_path / "side.png", dpi=50)
    assert (tmp_path / "side.png").read_bytes() == whole  # the last whole plot stays
    with pytest.raises(KeyboardInterrupt):
        save_figure(figure, tmp_path / "topdown.png")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["side.png"]  # no half, no temporary


def test_only_a_regular_file_is_ever_replaced(tmp_path: Path) -> None:
    import os
    import stat

    from cavenav.core.files import write_then_rename

    pipe = tmp_path / "pipe"
    os.mkfifo(pipe)  # as /dev/full: a rename would leave a regular file in its place
    with pytest.raises(OSError, match="no regular file"):
        write_then_rename(pipe, lambda tmp: tmp.write_text("{}"))
    assert stat.S_ISFIFO(pipe.stat().st_mode) and sorted(tmp_path.iterdir()) == [pipe]
    for args in (["--json", str(pipe)], ["--out", str(pipe)]):
        done = cavenav("compare", "a", "b", *args)
        assert done.returncode == 2 and f"cannot write {pipe}" in done.stderr, done.stderr
    assert stat.S_ISFIFO(pipe.stat().st_mode)
    for record, page in (("summary.json", "report.html"), ("sweep.json", "report/index.html")):
        folder = tmp_path / record.removesuffix(".json")
        (folder / page).parent.mkdir(parents=True)
        (folder / record).write_text("{}")  # refused before the record is read
        os.mkfifo(folder / page)
        done = cavenav("report", str(folder))
        assert done.returncode == 2, done.stderr
        assert done.stderr.strip() == (
            f"error: cannot write the report: {folder / page} is no regular file (a device, "
            "a pipe or a socket)"
        )
        assert stat.S_ISFIFO((folder / page).stat().st_mode)
