"""`--guideline` on the command line: the cave line in a run and in a sweep."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tests.conftest import cavenav
from tests.world.test_guideline import write_guided_room


def flown(out: Path, *flags: str, room: str = "") -> dict:
    """The summary of a 1-step run in the guided room with ``flags``."""
    path = write_guided_room(out.parent, room)
    done = cavenav("run", str(path), "--steps", "1", "--no-frames", "--out", str(out), *flags)
    assert done.returncode == 0, done.stderr
    (run_dir,) = out.iterdir()
    return json.loads((run_dir / "summary.json").read_text())


@pytest.mark.slow
@pytest.mark.parametrize(
    ("flags", "room", "expected"),
    [
        ((), "", None),  # off by default
        (("--guideline",), "", "white"),
        (("--guideline", "--guideline-colour", "yellow"), "", "yellow"),
        (("--no-guideline",), "guideline = true\n", None),  # takes away the file's line
        ((), 'guideline = "yellow"\n', "yellow"),  # the file's own
    ],
)
def test_run_flies_the_line_the_flags_and_the_file_ask_for(
    tmp_path: Path, flags: tuple[str, ...], room: str, expected: str | None
) -> None:
    summary = flown(tmp_path / "runs", *flags, room=room)
    assert (summary["guideline"] or {}).get("colour") == expected
    if expected:
        assert summary["guideline"]["ties"] >= 3 and summary["guideline"]["length_m"] > 15


@pytest.mark.slow
def test_a_sweep_with_the_line_keeps_it_in_sweep_json(tmp_path: Path) -> None:
    room = str(write_guided_room(tmp_path))
    out = tmp_path / "sweep"
    done = cavenav(
        "eval", "--scenarios", room, "--seeds", "0", "--steps", "1", "--frames", "none",
        "--no-report", "--guideline", "--out", str(out),
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert json.loads((out / "sweep.json").read_text())["episode"]["guideline"] is True
    (summary,) = out.glob("episodes/*/summary.json")
    assert json.loads(summary.read_text())["guideline"]["colour"] == "white"


def test_a_colour_the_line_does_not_come_in_is_refused() -> None:
    done = cavenav("run", "S1", "--guideline-colour", "red", "--steps", "1")
    assert done.returncode == 2 and "red" in done.stderr


def test_fly_and_the_fake_subs_camera_take_the_line_too() -> None:
    """`fly --sim` and `fake-sub --scene` load their cave through the episode settings,
    as `run` does; the fake sub with no cave has no camera to draw a line with."""
    for command in ("fly", "fake-sub"):
        assert "--guideline" in cavenav(command, "--help").stdout
    alone = cavenav("fake-sub", "--guideline")
    assert alone.returncode == 2 and "give --scene" in alone.stderr
