"""`--design direct|arrows|waypoint` as a user types it: sweeps, their results, the report
and the comparison, against the stand-in model server (tests/vlm_server.py)."""

from __future__ import annotations

import csv
import json
import re
from pathlib import Path

import pytest

from tests.conftest import cavenav
from tests.vlm_server import FakeVLM

DESIGNS = ("direct", "arrows", "waypoint")


@pytest.mark.slow
def test_the_three_designs_fly_the_same_cave_and_compare_side_by_side(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("OPENAI_API_KEY", "sk-test-designs")
    with FakeVLM() as server:
        common = ["eval", "--pilot", "vlm", "--model", "fake-vlm", "--base-url", server.base_url,
                  "--scenarios", "S4", "--seeds", "0", "--workers", "1", "--steps", "30",
                  "--frames", "none"]  # fmt: skip
        for design in DESIGNS:
            done = cavenav(*common, "--design", design, "--out", str(tmp_path / design))
            assert done.returncode == 0, done.stderr
    rows = {}
    for design in DESIGNS:
        with open(tmp_path / design / "results.csv", newline="") as table:
            (rows[design],) = csv.DictReader(table)
    direct, waypoint = rows["direct"], rows["waypoint"]
    assert int(direct["model_calls"]) == int(direct["steps"]) == 30
    assert direct["steps_without_call"] == "0" and rows["arrows"]["steps_without_call"] == "0"
    # The planner flies most waypoint steps without asking the model.
    assert int(waypoint["steps_without_call"]) >= 20
    assert float(waypoint["calls_per_m"]) * 3 <= float(direct["calls_per_m"])
    assert rows["arrows"]["pilot"] == "vlm:fake-vlm (arrows)"

    # Each design's report shows what the model saw: the choices drawn on the image.
    page = next((tmp_path / "arrows" / "report" / "episodes").glob("*.html")).read_text()
    drawn = re.findall(r'src="([^"]+)" alt="the choices drawn, as sent to the model', page)
    assert drawn and all((tmp_path / "arrows" / "report" / "episodes" / d).exists() for d in drawn)
    assert "the model chose" in page
    planned = next((tmp_path / "waypoint" / "report" / "episodes").glob("*.html")).read_text()
    assert "flown by the planner toward the waypoint, no model call" in planned

    done = cavenav("compare", *(str(tmp_path / d) for d in DESIGNS), "--out", str(tmp_path / "c"))
    assert done.returncode == 0, done.stderr
    result = json.loads((tmp_path / "c" / "compare.json").read_text())
    labels = ["vlm:fake-vlm", "vlm:fake-vlm (arrows)", "vlm:fake-vlm (waypoint)"]
    assert sorted(s["label"] for s in result["sweeps"]) == sorted(labels)
    assert all(pair["overall"]["pairs"] == 1 for pair in result["pairs"])  # paired by cave
    calls = [pair["overall"]["paired_tests"]["calls_per_m"] for pair in result["pairs"]]
    assert all(test["pairs"] == 1 for test in calls)  # and the calls a metre cost, by cave
    board = (tmp_path / "c" / "leaderboard.md").read_text()
    assert "model calls per m" in board and "steps without a call" in board


@pytest.mark.parametrize(
    ("flag", "says"),
    [(("--design", "oracle"), "unknown --design 'oracle'; choose one of direct, arrows, waypoint"),
     (("--replan-every", "0"), "--replan-every 0: the planner must fly at least 1 step")],
)  # fmt: skip
def test_an_unknown_design_or_replanning_never_is_one_line_and_exit_2(
    tmp_path: Path, flag: tuple[str, str], says: str
) -> None:
    for command in (["run", "S1"], ["eval", "--seeds", "0"]):
        out = tmp_path / "runs"
        done = cavenav(*command, "--pilot", "vlm", "--model", "m", *flag, "--out", str(out))
        assert done.returncode == 2 and done.stderr.count("\n") == 1, done.stderr
        assert done.stderr.startswith("error:") and says in done.stderr
        assert not out.exists()
