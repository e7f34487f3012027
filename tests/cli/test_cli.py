"""The command line, as a user types it."""

from __future__ import annotations

import csv
import io
import json
from dataclasses import fields
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from cavenav.world.scenarios import SCENARIOS
from tests.conftest import cavenav, write_room


def table_rows(stdout: str) -> list[list[str]]:
    """The cells of every body row of the tables printed to ``stdout``."""
    return [
        [cell.strip() for cell in line.strip().strip("│").split("│")]
        for line in stdout.splitlines()
        if line.strip().startswith("│")
    ]


def printed(stdout: str, label: str) -> list[str]:
    """The values of the lines ``label: value`` printed to ``stdout``, however aligned."""
    lines = stdout.splitlines()
    return [line.split(":", 1)[1].strip() for line in lines if line.startswith(f"{label}:")]


def printed_summary(stdout: str) -> dict[str, str]:
    """The episode summary table as the user reads it: label -> value."""
    return {label: value for label, value in table_rows(stdout)}


@pytest.mark.slow
def test_run_writes_a_run_folder_and_prints_where(tmp_path: Path) -> None:
    out = str(tmp_path)
    done = cavenav("run", "S4", "--seed", "2", "--steps", "3", "--no-frames", "--out", out)
    assert done.returncode == 0, done.stderr
    (run_dir,) = tmp_path.iterdir()
    summary = json.loads((run_dir / "summary.json").read_text())
    assert (summary["seed"], summary["noise_seed"], summary["pilot_seed"]) == (2, 2, None)
    assert summary["termination"] == "budget" and summary["steps"] == 3
    # The table printed is the summary written.
    shown = printed_summary(done.stdout)
    assert shown["scenario"] == "S4" and shown["pilot"] == "geometric"
    assert shown["termination"] == "budget" and shown["success"] == "no"
    assert shown["steps"] == "3" and shown["collisions"] == str(summary["collisions"])
    assert shown["path length"] == f"{summary['path_length_m']:.1f} m"
    assert shown["min clearance"] == f"{summary['min_clearance_m']:.2f} m"
    assert printed(done.stdout, "run folder") == [str(run_dir)]
    assert printed(done.stdout, "plot") == [str(run_dir / "topdown.png"), str(run_dir / "side.png")]
    for plot in ("topdown.png", "side.png"):
        with Image.open(run_dir / plot) as image:
            assert image.format == "PNG"


def test_scenarios_lists_the_five_topologies_and_example_files() -> None:
    root = Path(__file__).resolve().parents[2]
    done = cavenav("scenarios", cwd=root)
    assert done.returncode == 0, done.stderr
    files = sorted((root / "examples").glob("*.toml"))
    listed = table_rows(done.stdout)
    assert [row[0] for row in listed] == [*SCENARIOS, *(f"examples/{f.name}" for f in files)]
    assert [row[0] for row in listed[:5]] == ["S1", "S2", "S3", "S4", "S5"]
    for (_, kind, description), path in zip(listed[len(SCENARIOS) :], files, strict=True):
        first_comment = next(x for x in path.read_text().splitlines() if x.startswith("#"))
        assert kind == "scenario file" and description == first_comment.lstrip("# ").strip()


def test_bad_input_is_one_line_on_stderr_not_a_traceback(tmp_path: Path) -> None:
    broken = tmp_path / "broken.toml"
    broken.write_text("mesh = 'cave.obj'\n[start]\nposition = [0, 0]\n")
    cases = [
        (("run", "S9"), "unknown scenario 'S9'"),
        (("run", str(broken)), f"{broken}: field 'start.position"),
        (("run", "S4", "--pilot", "oracle"), "unknown pilot 'oracle'"),
    ]
    for args, names_the_bad_value in cases:
        done = cavenav(*args, "--out", str(tmp_path / "new" / "runs"))
        assert done.returncode == 2
        assert "Traceback" not in done.stderr
        assert done.stderr.startswith("error:") and done.stderr.count("\n") == 1, done.stderr
        assert names_the_bad_value in done.stderr
        assert not (tmp_path / "new").exists()  # exit 2 writes nothing, not even --out


EXAMPLES = Path(__file__).resolve().parents[2] / "examples"


def test_a_rerun_recording_that_cannot_be_written_is_refused_before_anything(
    tmp_path: Path,
) -> None:
    (tmp_path / "a-file").write_text("")
    runs = tmp_path / "runs"
    for save, says in [(tmp_path, "is a folder"), (tmp_path / "a-file" / "x.rrd", "is a file")]:
        for command in (["run", "S1", "--out", str(runs)], ["fly", "--sim", "S1", "--yes"]):
            done = cavenav(*command, "--rerun-save", str(save))
            assert done.returncode == 2 and done.stderr.count("\n") == 1, done.stderr
            assert done.stderr.startswith(f"error: cannot write the Rerun recording {save}: ")
            assert says in done.stderr and not runs.exists()  # it was RuntimeError, late


@pytest.mark.parametrize(
    "args",
    [("run", "S1", "--out", "NAME"), ("eval", "--seeds", "0", "--out", "NAME"),
     ("run", "NAME.toml")],
)  # fmt: skip
def test_a_path_too_long_for_the_file_system_is_one_line(args: tuple, tmp_path: Path) -> None:
    name = str(tmp_path / ("a" * 300))  # ENAMETOOLONG: each name at most 255 bytes
    done = cavenav(*(arg.replace("NAME", name) for arg in args))
    assert done.returncode == 2 and done.stderr.count("\n") == 1, done.stderr
    assert done.stderr.startswith("error: a path is too long for the file system: ")
    assert list(tmp_path.iterdir()) == []


def test_render_checks_where_its_sheet_goes_before_it_renders(tmp_path: Path) -> None:
    (tmp_path / "a-file").write_text("")
    cases = [
        (tmp_path, "is a folder: name the image to write"),
        (tmp_path / "sheet", "name an image file (.avif, "),  # it wrote sheet.png beside it
        (tmp_path / "a-file" / "sheet.png", "a-file is a file"),
    ]
    for out, says in cases:
        done = cavenav("render", "S1", "--out", str(out))
        assert done.returncode == 2 and says in done.stderr, done.stderr
        assert done.stderr.count("\n") == 1 and "building" not in done.stdout
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a-file"]


@pytest.mark.slow
def test_render_writes_a_contact_sheet_of_views_along_the_passage(tmp_path: Path) -> None:
    sheet = tmp_path / "sheet.png"
    scenario = str(EXAMPLES / "osrf_cave_straight.toml")
    done = cavenav("render", scenario, "--water", "turbid", "--views", "4", "--out", str(sheet))
    assert done.returncode == 0, done.stderr
    assert done.stdout.splitlines() == [f"contact sheet: {sheet}"]
    with Image.open(sheet) as image:
        pixels = np.asarray(image.convert("RGB")).astype(int)
    # Four columns: colour | depth | colour | depth ...
    colour_a, depth_a, colour_b, depth_b = np.split(pixels, 4, axis=1)
    for depth in (depth_a, depth_b):  # grey levels only
        assert np.array_equal(depth[..., 0], depth[..., 1])
        assert np.array_equal(depth[..., 1], depth[..., 2])
    for colour in (colour_a, colour_b):  # turbid water: red absorbed, green left
        drawn_here = np.abs(colour - 255).max(axis=-1) > 5  # the view, not the margin
        greener = colour[..., 1] > colour[..., 0] + 2  # after a white balance of 70%
        assert (greener & drawn_here).sum() > 0.6 * drawn_here.sum()
    # ... in two rows: 4 views, 2 per row.
    drawn = (np.abs(colour_a - 255).max(axis=-1) > 5).sum(axis=1) > colour_a.shape[1] // 2
    assert np.count_nonzero(np.diff(drawn.astype(int)) == 1) + drawn[0] == 2


@pytest.mark.slow
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
        out = tmp_path / "-".join(["runs", *flags])
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
    lamps = optics_of("--lamps", "4", "--lamp-lumens", "1000", "--lamp-beam", "120",
                      "--lamp-kelvin", "4000")  # fmt: skip
    assert (lamps["lamp_count"], lamps["lamp_lumens"]) == (4, 1000.0)
    assert (lamps["lamp_beam_deg"], lamps["lamp_kelvin"]) == (120.0, 4000.0)
    too_many = cavenav("run", str(scenario), "--steps", "1", "--lamps", "5")
    assert too_many.returncode == 2 and "--lamps" in too_many.stderr

    scenario.write_text(scenario.read_text() + "fog = 3\n")
    done = cavenav("run", str(scenario), "--steps", "1")
    assert done.returncode == 2
    assert "[optics]: 'fog'" in done.stderr and done.stderr.count("\n") == 1


@pytest.mark.slow
def test_the_random_pilot_flies_behind_the_shield_and_its_interventions_are_recorded(
    tmp_path: Path,
) -> None:
    scenario = str(EXAMPLES / "osrf_cave_straight.toml")
    args = ("run", scenario, "--pilot", "random", "--shield", "--steps", "6", "--no-frames")
    done = cavenav(*args, "--out", str(tmp_path))
    assert done.returncode == 0, done.stderr
    (run_dir,) = tmp_path.iterdir()
    summary = json.loads((run_dir / "summary.json").read_text())
    shown = printed_summary(done.stdout)
    assert shown["shield interventions"] == str(summary["shield_interventions"])
    steps = [json.loads(line) for line in (run_dir / "steps.jsonl").read_text().splitlines()]
    assert summary["pilot"] == "random" and summary["shield"] is True
    assert summary["shield_interventions"] == sum("shield" in s for s in steps) > 0
    for step in steps:
        if "shield" in step:
            assert step["action"] == step["shield"]["replacement"] != step["shield"]["proposed"]
            assert step["shield"]["reason"]


def test_a_bad_resolution_is_refused_in_one_line_before_any_work(tmp_path: Path) -> None:
    cases = [
        (("run", "S1", "--resolution", "160"), "--resolution: '160' is not a resolution"),
        (("render", "S1", "--resolution", "0x10"), "--resolution: '0x10' is not a resolution"),
        (("eval", "--sounder-resolution", "axb"), "--sounder-resolution: 'axb' is not a"),
        (("run", "S1", "--resolution", "100000x1"), "'100000x1' is not a resolution"),
    ]
    for args, names_the_bad_value in cases:
        done = cavenav(*args, "--out", str(tmp_path / "out"))
        assert done.returncode == 2, done.stderr
        assert done.stderr.startswith("error:") and done.stderr.count("\n") == 1, done.stderr
        assert names_the_bad_value in done.stderr and "WIDTHxHEIGHT" in done.stderr
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(
    ("flag", "value", "says"),
    [("--gusts", "nan", "nan is not a finite number; give one from 0 to 1"),
     ("--battery-wh", "nan", "nan is not a finite number; give one of 0.001 or more"),
     ("--noise", "inf", "inf is not a finite number; give one of 0 or more"),
     ("--gusts", "2", "2.0: give a number from 0 to 1")],
)  # fmt: skip
def test_a_number_out_of_its_range_is_named_as_it_is(flag: str, value: str, says: str) -> None:
    done = cavenav("run", "S1", flag, value)
    assert done.returncode == 2 and says in " ".join(done.stderr.replace("│", " ").split())


def camera_of(run_folder_root: Path) -> tuple[list[int], list[int]]:
    """(resolution, sounder resolution) the one run folder under the root was flown with."""
    (summary,) = run_folder_root.glob("**/summary.json")
    sensors = json.loads(summary.read_text())["config"]["sensors"]
    return [sensors["camera"]["width"], sensors["camera"]["height"]], sensors["sounder_pixels"]


@pytest.mark.slow
def test_a_scenario_files_sensors_table_sets_the_resolution_and_the_flag_overrides_it(
    tmp_path: Path,
) -> None:
    scenario = write_room(tmp_path / "caves")
    scenario.write_text(
        scenario.read_text() + "[sensors]\nresolution = [84, 84]\nsounder_resolution = [8, 6]\n"
    )

    def flown_with(*flags: str) -> tuple[list[int], list[int]]:
        out = tmp_path / "-".join(["runs", *flags])
        done = cavenav(
            "run", str(scenario), "--steps", "1", "--no-frames", "--out", str(out), *flags
        )
        assert done.returncode == 0, done.stderr
        return camera_of(out)

    assert flown_with() == ([84, 84], [8, 6])
    assert flown_with("--resolution", "96x72") == ([96, 72], [8, 6])  # the table's sounders


@pytest.mark.slow
def test_eval_flies_every_episode_at_the_resolution_it_was_given(tmp_path: Path) -> None:
    room, out = str(write_room(tmp_path / "caves")), tmp_path / "sweep"
    args = ["--scenarios", room, "--seeds", "0", "--steps", "1", "--frames", "none",
            "--workers", "1", "--no-report", "--out", str(out)]  # fmt: skip
    done = cavenav("eval", *args, "--resolution", "84x84", "--sounder-resolution", "4x3")
    assert done.returncode == 0, done.stderr
    recorded = json.loads((out / "sweep.json").read_text())["sensors"]
    assert recorded["resolution"] == [84, 84] and recorded["sounder_resolution"] == [4, 3]
    assert camera_of(out / "episodes") == ([84, 84], [4, 3])


@pytest.mark.slow
def test_a_sweep_flies_in_the_current_and_budget_it_was_given_and_tables_the_energy(
    tmp_path: Path,
) -> None:
    room, out = str(write_room(tmp_path / "caves")), tmp_path / "sweep"
    args = ["--scenarios", room, "--seeds", "0", "--steps", "2", "--frames", "none",
            "--workers", "1", "--no-report", "--out", str(out),
            "--resolution", "84x84"]  # fmt: skip
    done = cavenav("eval", *args, "--discharge", "5.6", "--gusts", "0", "--battery-wh", "50")
    assert done.returncode == 0, done.stderr
    episode = json.loads((out / "sweep.json").read_text())["episode"]
    assert (episode["discharge_m3s"], episode["gusts"], episode["battery_wh"]) == (5.6, 0.0, 50.0)
    (row,) = csv.DictReader(io.StringIO((out / "results.csv").read_text()))
    assert float(row["mean_current_m_s"]) == pytest.approx(0.1, rel=0.03)  # 5.6 m³/s in 8 x 7 m
    assert float(row["energy_wh"]) > 0 and float(row["mean_drift_m"]) > 0
    refused = cavenav("eval", *args, "--gusts", "2")
    assert refused.returncode == 2 and "--gusts" in refused.stderr
    # A scenario file's bound holds for the flag: 1e300 m³/s would carry it through rock.
    refused = cavenav("eval", *args, "--discharge", "1e300")
    assert refused.returncode == 2 and "within ±10000 m³/s" in refused.stderr


def test_every_vlm_option_is_one_flag_with_one_help_in_run_eval_and_fly() -> None:
    import typer.main

    from cavenav.cli import app
    from cavenav.pilots.factory import VLMOptions

    commands = typer.main.get_command(app).commands  # type: ignore[attr-defined]
    helps = {name: {p.name: p.help for p in commands[name].params} for name in commands}
    for name in ("run", "eval", "fly"):
        for field in fields(VLMOptions):
            assert field.name in helps[name], f"{name} lacks --{field.name.replace('_', '-')}"
            assert helps[name][field.name] == helps["run"][field.name]
    asked = set(helps["ask"])
    assert {"history", "map_image", "price", "cache"}.isdisjoint(asked) and "model" in asked


def test_an_option_the_value_does_not_take_is_refused_when_declared() -> None:
    from cavenav.cli.episode_flags import VLM
    from cavenav.cli.flags import Group
    from cavenav.pilots.factory import VLMOptions

    with pytest.raises(TypeError, match="VLMOptions takes no option max_token"):
        Group((*VLM.names, "max_token"), VLMOptions)


def test_each_command_declares_its_options_with_the_defaults_of_the_value_they_build() -> None:
    """A command lists the options of each group it takes in its own signature; their
    defaults there must build the value's own defaults (one default, written once)."""
    import inspect

    from cavenav.cli.episode_flags import SETTINGS, VLM
    from cavenav.cli.episodes import ask, render, run
    from cavenav.cli.fake_sub import fake_sub
    from cavenav.cli.sweeps import eval_
    from cavenav.cli.training import dataset
    from cavenav.cli.vehicle import fly
    from cavenav.cli.vehicle_flags import CAVE_SCENE, LIVE_VIEW, OWN_SENSORS

    commands = {
        run: (SETTINGS, VLM, LIVE_VIEW),
        render: (SETTINGS,),
        ask: (VLM,),
        eval_: (SETTINGS, VLM),
        dataset: (VLM,),
        fly: (SETTINGS, VLM, LIVE_VIEW, OWN_SENSORS),
        fake_sub: (CAVE_SCENE,),
    }
    for command, groups in commands.items():
        parameters = inspect.signature(command).parameters
        for group in groups:
            declared = {
                name: parameters[name].default for name in group.names if name in parameters
            }
            assert declared, f"{command.__name__} takes none of {group.build.__name__}'s options"
            assert group.value(declared) == group.value({}), command.__name__


def test_fly_takes_the_sensor_optics_resolution_and_difficulty_flags(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from typer.testing import CliRunner

    from cavenav import cli
    from cavenav.cli import vehicle

    flown = {}
    monkeypatch.setattr(
        vehicle, "fly_vehicle", lambda bridge, cave, flyer, episode, *_, **__: flown.update(
            cave=cave, episode=episode
        )
    )  # fmt: skip
    done = CliRunner().invoke(
        cli.app,
        ["fly", "--sim", "S1", "--yes", "--out", str(tmp_path), "--no-shield", "--steps", "7",
         "--water", "turbid", "--light-power", "5", "--resolution", "160x120",
         "--sounder", "beam", "--difficulty", "constriction_m=3.0"],
    )  # fmt: skip
    assert done.exit_code == 0, done.output
    episode, cave = flown["episode"], flown["cave"]
    assert episode.max_steps == 7 and not episode.shield
    assert episode.sensors.optics.water_name == "turbid" and episode.sensors.optics.light_power == 5
    assert (episode.sensors.camera.width, episode.sensors.camera.height) == (160, 120)
    assert episode.sensors.sounder == "beam"
    assert cave.difficulty.to_dict() == {"constriction_m": 3.0}
    refused = cavenav("fly", "--sim", "S1", "--yes", "--resolution", "160", "--out", str(tmp_path))
    assert refused.returncode == 2 and "--resolution: '160' is not a resolution" in refused.stderr


def test_a_table_printed_to_a_pipe_keeps_every_cell_whole():
    """Rich fits a table to 80 columns where it cannot ask a terminal ("51%-1…"): a
    table sent to a file or a pipe must stay whole."""
    import os
    import subprocess
    import sys

    draw = (
        "from rich.table import Table; from cavenav.cli.output import _print_table; "
        "t = Table(); [t.add_column(f'column {i}') for i in range(12)]; "
        "t.add_row(*['51%-100%'] * 12); _print_table(t)"
    )
    environment = {k: v for k, v in os.environ.items() if k != "COLUMNS"}
    shown = subprocess.run(
        [sys.executable, "-c", draw], capture_output=True, text=True, env=environment, check=True
    ).stdout
    assert shown.count("51%-100%") == 12 and "…" not in shown
    assert max(len(line) for line in shown.splitlines()) > 80


def test_run_with_a_sonar_a_dvl_and_a_stereo_camera_records_them(tmp_path: Path) -> None:
    room = write_room(tmp_path / "caves")
    flags = ("--sonar", "multibeam", "--dvl", "--depth-source", "stereo", "--steps", "3")
    result = cavenav("run", str(room), "--pilot", "geometric", *flags, "--out", str(tmp_path))
    assert result.returncode == 0, result.stderr
    run = next(tmp_path.glob("*_room_geometric"))
    steps = [json.loads(line) for line in (run / "steps.jsonl").read_text().splitlines()]
    first, later = steps[0], steps[-1]
    assert first["sonar"] == {"kind": "multibeam", "fresh_beams": 512}
    assert later["dvl"]["locked"] and len(later["dvl"]["velocity_m_s"]) == 3
    assert later["reckoned"]["sigma_m"] > 0
    with np.load(run / first["frames"]["sonar_npz"]) as echoes:
        assert echoes["echoes"].shape == (512, 512) and str(echoes["kind"]) == "multibeam"
    assert Image.open(run / first["frames"]["sonar_png"]).size[1] == 400
    assert Image.open(run / first["frames"]["depth_png"]).text == {"depth_source": "stereo"}
    summary = json.loads((run / "summary.json").read_text())
    assert summary["config"]["sensors"]["sonar"] == "multibeam"


def test_an_unknown_sonar_is_refused_in_one_line(tmp_path: Path) -> None:
    result = cavenav("run", "S1", "--sonar", "sidescan", "--out", str(tmp_path))
    assert result.returncode == 2
    assert "sidescan" in result.stderr and "Traceback" not in result.stderr
