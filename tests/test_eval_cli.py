"""`cavenav eval`, `compare` and `report` as a user types them: Ctrl-C, resume, compare."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from scipy.stats import binomtest

from .conftest import write_room
from .test_cli import table_rows


def cavenav(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "cavenav.cli", *args],
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, "COLUMNS": "160"},
    )


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
