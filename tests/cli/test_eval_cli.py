"""`cavenav eval`, `compare` and `report` as a user types them: Ctrl-C, resume, compare."""

from __future__ import annotations

import csv
import fcntl
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from scipy.stats import binomtest

from tests.cli.test_cli import table_rows
from tests.conftest import cavenav, flying, full_disk, takes_ctrl_c, wide, write_room


def finished(out: Path) -> list[str]:
    done = []
    for summary in out.glob("episodes/*/summary.json"):
        try:
            if json.loads(summary.read_text())["status"] == "finished":
                done.append(summary.parent.name)
        except (ValueError, KeyError):
            pass  # being rewritten
    return done


@pytest.mark.slow
def test_a_sweep_survives_ctrl_c_and_resumes_where_it_stopped(tmp_path: Path) -> None:
    room = str(write_room(tmp_path / "caves"))
    out = tmp_path / "sweep"
    args = ["eval", "--scenarios", room, "--seeds", "0-5", "--out", str(out), "--workers", "2",
            "--steps", "12", "--frames", "none", "--no-report"]  # fmt: skip
    sweep = subprocess.Popen(
        [sys.executable, "-m", "cavenav.cli", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=takes_ctrl_c,
    )
    deadline = time.monotonic() + 240
    while not finished(out) and time.monotonic() < deadline and sweep.poll() is None:
        time.sleep(0.2)
    sweep.send_signal(signal.SIGINT)
    _, stderr = sweep.communicate(timeout=120)
    before = finished(out)
    assert sweep.returncode == 130, stderr
    assert "run the same command again to resume" in stderr and "Traceback" not in stderr
    assert 1 <= len(before) < 6
    assert (out / "results.csv").is_file()  # the tables of what was done are written

    resumed = cavenav(*args)
    assert resumed.returncode == 0, resumed.stderr
    assert f"{len(before)} of 6 episodes done" in resumed.stdout
    assert sorted(finished(out)) == [f"room-seed{k:04d}" for k in range(6)]
    results = (out / "results.csv").read_text().splitlines()
    assert len(results) == 1 + 6 and all(",finished," in line for line in results[1:])


@pytest.mark.slow
def test_compare_pairs_two_sweeps_and_names_the_caves_that_differ(tmp_path: Path) -> None:
    room = str(write_room(tmp_path / "caves"))
    common = ["--scenarios", room, "--seeds", "0-1", "--workers", "1", "--frames", "none"]
    geometric = cavenav("eval", *common, "--steps", "40", "--out", str(tmp_path / "a"))
    random = cavenav(
        "eval", *common, "--steps", "40", "--pilot", "random", "--out", str(tmp_path / "b")
    )
    assert geometric.returncode == 0 and random.returncode == 0, geometric.stderr + random.stderr
    # scenario, done, success, its 95% Wilson interval, collided: the room, then all caves
    low, high = binomtest(2, 2).proportion_ci(method="wilson")
    expected = ["2/2", "100%", f"{low:.0%}-{high:.0%}", "0"]
    assert [row[:5] for row in table_rows(geometric.stdout)] == [
        ["room", *expected],
        ["all", *expected],
    ]
    assert (tmp_path / "a" / "report" / "index.html").is_file()

    done = cavenav(
        "compare", str(tmp_path / "a"), str(tmp_path / "b"), "--json", str(tmp_path / "c.json")
    )
    assert done.returncode == 0, done.stderr
    result = json.loads((tmp_path / "c.json").read_text())["overall"]
    assert result["pairs"] == 2 and result["success_rate_a"] == 1.0
    assert result["success_rate_b"] == 0.0 and result["mcnemar_p"] == 0.5
    lines = done.stdout.splitlines()
    assert lines[lines.index("only A got through (2):") + 1 :][:2] == [
        f"  room seed {k}: {tmp_path / 'a' / 'episodes' / f'room-seed000{k}'}" for k in (0, 1)
    ]


@pytest.mark.slow
def test_trials_fly_each_cave_again_and_compare_by_the_caves_rates(tmp_path: Path) -> None:
    room = str(write_room(tmp_path / "caves"))
    common = ["--scenarios", room, "--seeds", "0-1", "--workers", "1", "--frames", "none"]
    twice = cavenav("eval", *common, "--steps", "40", "--pilot", "random", "--trials", "2",
                    "--out", str(tmp_path / "random"))  # fmt: skip
    once = cavenav("eval", *common, "--steps", "40", "--no-report", "--out", str(tmp_path / "g"))
    assert twice.returncode == 0 and once.returncode == 0, twice.stderr + once.stderr
    page = (tmp_path / "random" / "report" / "index.html").read_text()
    assert "<h2>Caves</h2>" in page and "2 flights of each cave" in page
    assert page.count('href="episodes/room-seed0001-trial2.html"') >= 1

    done = cavenav("compare", str(tmp_path / "g"), str(tmp_path / "random"))
    assert done.returncode == 0, done.stderr
    assert "Wilcoxon p (caves' rates)" in done.stdout and "A did better in 2 caves:" in done.stdout
    refused = cavenav(
        "eval", *common, "--steps", "40", "--trials", "0", "--out", str(tmp_path / "x")
    )
    assert refused.returncode == 2 and not (tmp_path / "x").exists()


@pytest.mark.slow
def test_a_different_configuration_is_refused_in_one_line(tmp_path: Path) -> None:
    room = str(write_room(tmp_path / "caves"))
    base = ["eval", "--scenarios", room, "--seeds", "0", "--workers", "1", "--frames", "none",
            "--steps", "3", "--no-report", "--out", str(tmp_path / "s")]  # fmt: skip
    assert cavenav(*base).returncode == 0
    refused = cavenav(*base, "--shield")
    assert refused.returncode == 2
    assert refused.stderr.count("\n") == 1 and "episode.shield: false there, true now" in (
        refused.stderr
    )


def test_bad_input_to_a_sweep_is_refused_in_one_line_before_anything_is_written(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    out = tmp_path / "sweep"
    monkeypatch.setenv("CAVENAV_TEST_BAD_KEY", "sk-secret-é")
    monkeypatch.setenv("CAVENAV_TEST_TWO_LINES", "sk-secret\nsecond")
    for args, refusal in [
        (["--scenarios", "S1,S9"], "error: unknown scenario 'S9'"),
        (["--scenarios", "S4", "--difficulty", "bend_deg=500"], "bend_deg=500 is outside"),
        (["--seeds", "0-9999999999"], "more than the 100,000 episodes a sweep flies"),
        (["--pilot", "vlm", "--model", "m", "--api-key-env", "CAVENAV_TEST_NO_KEY"],
         "no API key: set the environment variable CAVENAV_TEST_NO_KEY"),
        (["--pilot", "vlm", "--model", "m", "--api-key-env", "CAVENAV_TEST_BAD_KEY"],
         "the API key in CAVENAV_TEST_BAD_KEY is not a valid HTTP header value"),
        (["--pilot", "vlm", "--model", "m", "--api-key-env", "CAVENAV_TEST_TWO_LINES"],
         "the API key in CAVENAV_TEST_TWO_LINES is not a valid HTTP header value"),
    ]:  # fmt: skip
        refused = cavenav("eval", *args, "--out", str(out), "--workers", "1")
        assert refused.returncode == 2, refused.stderr
        assert refused.stderr.count("\n") == 1 and refusal in refused.stderr
        assert "secret" not in refused.stderr + refused.stdout  # the key is never shown
        assert not out.exists()


def alive(pid: int) -> bool:
    """Still running: a zombie (dead, not yet reaped by its new parent) is not."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except (FileNotFoundError, ProcessLookupError):
        return False


@pytest.fixture
def slow_model(monkeypatch: pytest.MonkeyPatch) -> Iterator[tuple[Any, list[str]]]:
    """A model server that takes 0.4 s a reply, and the options of a sweep flying it: its
    episodes last seconds, long enough to kill the sweep with both in the air."""
    from tests.vlm_server import FakeVLM

    monkeypatch.setenv("OPENAI_API_KEY", "sk-test-slow")
    with FakeVLM() as server:
        server.persistent_fault, server.slow_s = "slow", 0.4
        yield server, ["--pilot", "vlm", "--model", "fake-vlm", "--base-url", server.base_url,
                       "--seeds", "0-1", "--workers", "2", "--steps", "8", "--frames", "none",
                       "--no-report"]  # fmt: skip


@pytest.mark.slow
def test_a_killed_sweep_takes_its_workers_with_it_and_a_rerun_counts_no_error(
    tmp_path: Path, slow_model: tuple[Any, list[str]]
) -> None:
    server, options = slow_model
    room = str(write_room(tmp_path / "caves"))
    out = tmp_path / "sweep"
    args = ["eval", "--scenarios", room, *options, "--out", str(out)]
    sweep = subprocess.Popen([sys.executable, "-m", "cavenav.cli", *args],
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)  # fmt: skip
    try:
        workers = set(flying(out, 2).values())
        held = os.open(out / "episodes", os.O_RDONLY)
        with pytest.raises(BlockingIOError):  # the workers hold the folder with the sweep
            fcntl.flock(held, fcntl.LOCK_EX | fcntl.LOCK_NB)
        os.close(held)
    finally:
        sweep.kill()
        sweep.wait()
    deadline = time.monotonic() + 2  # the steps left take longer: none is flown unsupervised
    while any(alive(pid) for pid in workers) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not any(alive(pid) for pid in workers)

    server.persistent_fault = None  # quick replies from now on: the rerun's own episodes
    rerun = cavenav(*args)  # at once
    assert rerun.returncode == 0, rerun.stderr
    with open(out / "results.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert [(r["status"], r["error"]) for r in rows] == [("finished", "")] * 2
    assert not list(out.glob("episodes/*/error.txt"))


def steps_flown(out: Path, episode: str) -> tuple[str, int]:
    """(status, steps) of an episode's last whole summary."""
    while True:
        try:
            summary = json.loads((out / "episodes" / episode / "summary.json").read_text())
            return summary["status"], summary["steps"]
        except ValueError:
            continue  # being rewritten


@pytest.mark.slow
def test_sigterm_to_the_process_group_stops_a_sweep_as_ctrl_c_does_with_status_143(
    tmp_path: Path, slow_model: tuple[Any, list[str]]
) -> None:
    """As Slurm or ``kill -- -PGID`` stop a job: every process of the group gets SIGTERM.
    The workers leave it to the sweep, which stops them: the episodes in the air stay
    in flight ("running", flown again on resume), not errors of workers that died."""
    room = str(write_room(tmp_path / "caves"))
    out = tmp_path / "sweep"
    args = ["eval", "--scenarios", room, *slow_model[1], "--out", str(out)]
    sweep = subprocess.Popen([sys.executable, "-m", "cavenav.cli", *args],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                             start_new_session=True)  # fmt: skip
    in_the_air = flying(out, 2)
    workers = set(in_the_air.values())
    episode, worker = next(iter(in_the_air.items()))
    os.kill(worker, signal.SIGTERM)  # a worker alone flies on
    before = steps_flown(out, episode)
    deadline = time.monotonic() + 60
    while (now := steps_flown(out, episode)) == before and time.monotonic() < deadline:
        time.sleep(0.05)
    assert now[0] in ("running", "finished") and now[1] > before[1], f"{now}: it died"
    os.killpg(sweep.pid, signal.SIGTERM)
    _, stderr = sweep.communicate(timeout=60)
    assert sweep.returncode == 143, stderr
    assert "interrupted after" in stderr and "run the same command again to resume" in stderr
    assert "Traceback" not in stderr
    assert not any(alive(pid) for pid in workers)
    with open(out / "results.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert {r["status"] for r in rows} <= {"running", "finished"}  # in the air, or landed
    assert not any(r["error"] for r in rows)


@pytest.mark.slow
def test_a_sweep_into_a_full_disk_stops_in_one_line_and_finishes_nothing_unwritten(
    tmp_path: Path,
) -> None:
    with full_disk(tmp_path / "disk", "96k") as disk:
        room = str(write_room(tmp_path / "caves"))
        out = disk / "sweep"
        done = cavenav("eval", "--scenarios", room, "--seeds", "0-3", "--workers", "2",
                       "--steps", "30", "--frames", "none", "--out", str(out))  # fmt: skip
        assert done.returncode == 1, done.stderr
        assert done.stderr.count("\n") == 1 and "Traceback" not in done.stderr
        assert "No space left on device; the sweep stopped after" in done.stderr
        runs = {p.parent: json.loads(p.read_text()) for p in out.glob("episodes/*/summary.json")}
        assert any(s["status"] != "finished" for s in runs.values())  # the one cut short
        for run, summary in runs.items():  # a finished episode is whole, plots and all
            if summary["status"] == "finished":
                assert all((run / name).is_file() for name in summary["plots"].values())
        assert len(runs) < 4  # it stopped: no episode flew into the full disk after it


@pytest.mark.slow
def test_compare_puts_three_pilots_side_by_side_on_one_page(tmp_path: Path) -> None:
    room = str(write_room(tmp_path / "caves"))
    common = ["--scenarios", room, "--seeds", "0-1", "--workers", "1", "--frames", "none",
              "--steps", "40"]  # fmt: skip
    flown = {
        "geometric": cavenav("eval", *common, "--out", str(tmp_path / "geometric")),
        "random": cavenav("eval", *common, "--pilot", "random", "--out", str(tmp_path / "random")),
        "shielded": cavenav(
            "eval",
            *common,
            "--pilot",
            "random",
            "--shield",
            "--no-report",
            "--out",
            str(tmp_path / "shielded"),
        ),  # fmt: skip
    }
    assert all(done.returncode == 0 for done in flown.values()), [d.stderr for d in flown.values()]
    page = tmp_path / "page"
    done = cavenav("compare", *(str(tmp_path / name) for name in flown), "--out", str(page))
    assert done.returncode == 0, done.stderr
    result = json.loads((page / "compare.json").read_text())
    labels = ["geometric", "random (random)", "random (shielded)"]  # one pilot, told apart
    assert [s["label"] for s in result["sweeps"]] == labels
    assert [s["path"] for s in result["sweeps"]] == [str(tmp_path / name) for name in flown]
    assert result["leaderboard"][0]["pilot"] == "geometric"
    assert len(result["pairs"]) == 3 and result["pairs"][0]["overall"]["pairs"] == 2
    assert "| geometric | 2/2 | 100% (" in (page / "leaderboard.md").read_text()
    assert r"\begin{tabular}" in (page / "leaderboard.tex").read_text()
    html = (page / "index.html").read_text()
    assert "geometric gets through more often" not in html  # 2 caves prove nothing: p = 0.5
    assert "no clear difference in success" in html
    links = re.findall(r'href="([^"]+)"', html)
    episode_links = [link for link in links if "seed000" in link]
    assert episode_links and all((page / link).exists() for link in episode_links)
    assert any(link.startswith("../geometric/report/episodes/") for link in episode_links)
    assert any(link.startswith("../shielded/episodes/") for link in episode_links)  # no report
    assert "leaderboard" in done.stdout and "| geometric | 2/2 |" in done.stdout
    unknown = cavenav("compare", *(str(tmp_path / n) for n in flown), "--price", "gpt-x=1,2")
    assert unknown.returncode == 2 and "--price for gpt-x: no sweep flew it" in unknown.stderr
    priced = cavenav("report", str(tmp_path / "geometric"), "--price", "1,2")
    assert priced.returncode == 0, priced.stderr
    index = (tmp_path / "geometric" / "report" / "index.html").read_text()
    assert "USD 1 / 2 per million tokens in / out" in index

    # Sweeps over other caves, or another scenario set, have nothing to pair: refused,
    # unless shown side by side without tests.
    elsewhere = cavenav("eval", *common, "--seeds", "7", "--out", str(tmp_path / "elsewhere"))
    assert elsewhere.returncode == 0, elsewhere.stderr
    apart = [str(tmp_path / "geometric"), str(tmp_path / "elsewhere")]
    refused = cavenav("compare", *apart)
    assert refused.returncode == 2 and "completed no cave in common" in refused.stderr
    assert "--allow-unpaired" in refused.stderr
    shown = cavenav("compare", *apart, "--allow-unpaired", "--out", str(tmp_path / "apart"))
    assert shown.returncode == 0, shown.stderr
    assert "unpaired, no tests" in shown.stdout and "McNemar" not in shown.stdout
    side_by_side = json.loads((tmp_path / "apart" / "compare.json").read_text())
    assert side_by_side["pairs"] == [] and "no cave in common" in side_by_side["unpaired"]
    page = (tmp_path / "apart" / "index.html").read_text()
    assert "Unpaired:" in page and "<h2>Pairs</h2>" not in page
    other_set = tmp_path / "other-set"
    shutil.copytree(tmp_path / "random", other_set)
    config = json.loads((other_set / "sweep.json").read_text())
    (other_set / "sweep.json").write_text(json.dumps({**config, "scenario_set": "4"}))
    refused = cavenav("compare", str(tmp_path / "geometric"), str(other_set))
    assert refused.returncode == 2 and "different scenario sets" in refused.stderr


@pytest.mark.parametrize(
    ("command", "message"),
    [
        (["compare", "a", "b", "--price", "0.5,4"], "--price takes MODEL=IN,OUT"),
        (["compare", "a", "b", "--price", "gpt=0.5"], "--price must be 'input,output'"),
        (["report", "a", "--price", "cheap"], "--price must be 'input,output'"),
        (["compare", "a", "b", "--price", "gpt=-1,2"], "each part is a finite number of USD"),
        (["report", "a", "--price", "nan,2"], "each part is a finite number of USD"),
    ],
)
def test_a_malformed_price_is_one_line_before_any_sweep_is_read(
    command: list[str], message: str, tmp_path: Path
) -> None:
    done = cavenav(*command, cwd=tmp_path)
    assert done.returncode == 2 and message in done.stderr
    assert len(done.stderr.strip().splitlines()) == 1


@pytest.mark.slow
def test_video_failures_gives_every_failed_episode_a_video_on_its_page(tmp_path: Path) -> None:
    room = str(write_room(tmp_path / "caves"))
    common = ["eval", "--scenarios", room, "--seeds", "0-1", "--workers", "1", "--steps", "20"]
    refused = cavenav(*common, "--video", "all", "--frames", "none", "--out", str(tmp_path / "x"))
    assert refused.returncode == 2 and "--video needs the frames" in refused.stderr
    assert not (tmp_path / "x").exists()
    flown = {
        pilot: cavenav(
            *common,
            "--pilot",
            pilot,
            "--frames",
            "png",
            "--video",
            "failures",
            "--out",
            str(tmp_path / pilot),
        )  # fmt: skip
        for pilot in ("geometric", "random")
    }
    assert all(done.returncode == 0 for done in flown.values()), flown["random"].stderr
    for pilot in flown:
        rows = list(csv.DictReader((tmp_path / pilot / "results.csv").open()))
        for row in rows:
            video = tmp_path / pilot / row["run_dir"] / "episode.mp4"
            assert video.is_file() == (row["outcome"] != "success"), (pilot, row["outcome"])
            page = (tmp_path / pilot / "report" / "episodes" / f"{row['episode']}.html").read_text()
            assert ("<video" in page) == video.is_file()
    outcomes = [
        r["outcome"] for p in flown for r in csv.DictReader((tmp_path / p / "results.csv").open())
    ]
    assert "success" in outcomes and any(o != "success" for o in outcomes)  # both cases met
    assert json.loads((tmp_path / "random" / "sweep.json").read_text())["video"] == "failures"


def wandb_history(run_file: Path) -> list[dict[str, Any]]:
    """The rows ``run.log`` wrote to an offline W&B run file: LevelDB's log format (32 KiB
    blocks of records, each a 7-byte header and a piece of a protobuf `Record`) after the
    file's 7-byte ":W&B" header."""
    from wandb.proto import wandb_internal_pb2 as pb

    raw, pos, pending, history = run_file.read_bytes(), 7, b"", []
    while pos + 7 <= len(raw):
        if 32768 - pos % 32768 < 7:  # a block's tail too short for a header: padding
            pos += 32768 - pos % 32768
            continue
        length, kind = int.from_bytes(raw[pos + 4 : pos + 6], "little"), raw[pos + 6]
        pending += raw[pos + 7 : pos + 7 + length]
        pos += 7 + length
        if kind in (1, 4):  # a whole record, or the last piece of one
            record = pb.Record()
            record.ParseFromString(pending)
            pending = b""
            if record.WhichOneof("record_type") == "history":
                items = record.history.item  # a nested value is one item per leaf
                history.append(
                    {i.key or "/".join(i.nested_key): json.loads(i.value_json) for i in items}
                )
    return history


@pytest.mark.slow
def test_wandb_logs_each_episode_the_results_and_the_videos_offline(tmp_path: Path) -> None:
    pytest.importorskip("wandb")
    room = str(write_room(tmp_path / "caves"))
    out = tmp_path / "sweep"
    environment = {k: v for k, v in wide().items() if not k.startswith("WANDB")}
    done = cavenav(
        "eval", "--scenarios", room, "--seeds", "0-1", "--workers", "1", "--steps", "20",
        "--frames", "png", "--video", "all", "--wandb", "--out", str(out), env=environment,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    (run_file,) = out.glob("wandb/offline-run-*/run-*.wandb")  # offline: nothing was sent
    history = wandb_history(run_file)
    episodes = [h for h in history if "episode/id" in h]
    assert [h["episode/id"] for h in episodes] == ["room-seed0000", "room-seed0001"]
    assert all(h["episode/outcome"] == "success" and h["episode/spl"] > 0.9 for h in episodes)
    assert all(h["episode/video/_type"] == "video-file" for h in episodes)
    (table,) = run_file.parent.glob("files/media/table/results_*.table.json")
    assert len(json.loads(table.read_text())["data"]) == 2
    assert len(list(run_file.parent.glob("files/media/videos/**/*.mp4"))) == 2
