"""The command line, as a user types it."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path


def cavenav(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "cavenav.cli", *args],
        capture_output=True,
        text=True,
        cwd=cwd,
        timeout=300,
    )


def test_run_writes_a_run_folder_and_prints_where(tmp_path: Path) -> None:
    done = cavenav("run", "S4", "--steps", "3", "--no-frames", "--out", str(tmp_path))
    assert done.returncode == 0, done.stderr
    (run_dir,) = tmp_path.iterdir()
    assert str(run_dir) in done.stdout
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["termination"] == "budget" and summary["steps"] == 3
    assert "episode summary" in done.stdout
    assert (run_dir / "topdown.png").exists() and (run_dir / "side.png").exists()


def test_scenarios_lists_the_five_topologies_and_example_files() -> None:
    done = cavenav("scenarios", cwd=Path(__file__).resolve().parents[1])
    assert done.returncode == 0
    for name in ("S1", "S2", "S3", "S4", "S5", "osrf_cave_L.toml"):
        assert name in done.stdout


def test_bad_input_is_one_line_on_stderr_not_a_traceback(tmp_path: Path) -> None:
    broken = tmp_path / "broken.toml"
    broken.write_text("mesh = 'cave.obj'\n[start]\nposition = [0, 0]\n")
    for args in (("run", "S9"), ("run", str(broken)), ("run", "S4", "--pilot", "oracle")):
        done = cavenav(*args)
        assert done.returncode == 2
        assert "Traceback" not in done.stderr
        assert done.stderr.startswith("error:") and done.stderr.count("\n") == 1, done.stderr


EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def test_render_writes_a_contact_sheet_of_views_along_the_passage(tmp_path: Path) -> None:
    sheet = tmp_path / "sheet.png"
    scenario = str(EXAMPLES / "osrf_cave_straight.toml")
    done = cavenav("render", scenario, "--water", "turbid", "--views", "4", "--out", str(sheet))
    assert done.returncode == 0, done.stderr
    assert str(sheet) in done.stdout
    from PIL import Image

    with Image.open(sheet) as image:
        width, height = image.size
    assert width >= 1000 and height >= 400  # two rows of colour + depth pairs


def test_a_scenario_files_optics_table_sets_the_water_and_flags_override_it(
    tmp_path: Path,
) -> None:
    source = (EXAMPLES / "osrf_cave_straight.toml").read_text()
    mesh = (EXAMPLES / "meshes" / "cave_straight_20m.dae").resolve()
    scenario = tmp_path / "murky.toml"
    scenario.write_text(
        source.replace("meshes/cave_straight_20m.dae", str(mesh))
        + '\n[optics]\nwater = "coastal"\nparticles = 0.5\n'
    )

    def optics_of(*flags: str) -> dict:
        out = tmp_path / f"runs{len(flags)}"
        done = cavenav(
            "run", str(scenario), "--steps", "1", "--no-frames", "--out", str(out), *flags
        )
        assert done.returncode == 0, done.stderr
        (run_dir,) = out.iterdir()
        return json.loads((run_dir / "summary.json").read_text())["config"]["sensors"]["optics"]

    from_file = optics_of()
    assert from_file["water"] == "coastal" and from_file["particles"] == 0.5
    overridden = optics_of("--water", "turbid")
    assert overridden["water"] == "turbid" and overridden["particles"] == 0.5

    scenario.write_text(scenario.read_text() + "fog = 3\n")
    done = cavenav("run", str(scenario), "--steps", "1")
    assert done.returncode == 2
    assert "[optics]: 'fog'" in done.stderr and done.stderr.count("\n") == 1


def test_the_random_pilot_flies_behind_the_shield_and_its_interventions_are_recorded(
    tmp_path: Path,
) -> None:
    scenario = str(EXAMPLES / "osrf_cave_straight.toml")
    args = ("run", scenario, "--pilot", "random", "--shield", "--steps", "6", "--no-frames")
    done = cavenav(*args, "--out", str(tmp_path))
    assert done.returncode == 0, done.stderr
    assert "shield interventions" in done.stdout
    (run_dir,) = tmp_path.iterdir()
    summary = json.loads((run_dir / "summary.json").read_text())
    steps = [json.loads(line) for line in (run_dir / "steps.jsonl").read_text().splitlines()]
    assert summary["pilot"] == "random" and summary["shield"] is True
    assert summary["shield_interventions"] == sum("shield" in s for s in steps) > 0
    for step in steps:
        if "shield" in step:
            assert step["action"] == step["shield"]["replacement"] != step["shield"]["proposed"]
            assert step["shield"]["reason"]
