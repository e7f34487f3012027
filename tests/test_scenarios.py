"""Scenarios: seeded procedural caves S1-S5 and scenario files for user meshes."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cavenav.errors import ConfigError, MeshError, ScenarioError
from cavenav.types import Pose
from cavenav.world.collision import VehicleBody, clearance
from cavenav.world.procedural import resample
from cavenav.world.raycast import RayCaster
from cavenav.world.scenarios import (
    SCENARIOS,
    Scenario,
    load_scenario,
    load_scenario_file,
    validate_start,
)

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def test_the_same_seed_builds_the_same_cave_bit_for_bit(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setenv("CAVENAV_CACHE", str(tmp_path / "a"))
    a = load_scenario("S3", seed=7)
    monkeypatch.setenv("CAVENAV_CACHE", str(tmp_path / "b"))
    b = load_scenario("S3", seed=7)
    assert np.array_equal(a.mesh.vertices, b.mesh.vertices)
    assert np.array_equal(a.mesh.faces, b.mesh.faces)
    assert a.start == b.start


def test_another_seed_builds_another_cave() -> None:
    a, b = load_scenario("S3", seed=0), load_scenario("S3", seed=1)
    assert a.mesh.vertices.shape != b.mesh.vertices.shape or not np.allclose(
        a.mesh.vertices, b.mesh.vertices
    )


@pytest.mark.parametrize("name", list(SCENARIOS))
def test_procedural_caves_have_the_promised_shape(name: str) -> None:
    layout = SCENARIOS[name].build(np.random.default_rng([0, int(name[1:])]), 0)
    spec = layout.spec
    start = int(np.argmin(np.linalg.norm(spec.centreline - layout.start.position, axis=1)))
    _, s = resample(spec.centreline[start : spec.exit_index + 1], 0.1)
    assert 40.0 <= s[-1] <= 80.0, "passage length"
    widths = 2 * spec.half_width[start : spec.exit_index]
    assert widths.min() >= 3.0 and widths.max() <= 8.0, "passages 3-8 m across"

    scenario = load_scenario(name, seed=0)
    caster = RayCaster(scenario.mesh)
    validate_start(scenario, caster, VehicleBody())
    assert scenario.exit_distance(scenario.start.position) >= 30.0


def test_s3_starts_near_a_wall_at_the_height_of_the_frontal_obstacle() -> None:
    layout = SCENARIOS["S3"].build(np.random.default_rng([0, 3]), 0)
    frontal = layout.spec.boulders[0]
    assert layout.start.z == pytest.approx(frontal.centre[2])
    scenario = load_scenario("S3", seed=0)
    assert clearance(RayCaster(scenario.mesh), scenario.start) < 2.0  # close to the wall


def test_unknown_scenario_names_the_choices() -> None:
    with pytest.raises(ScenarioError, match="S1, S2, S3, S4, S5"):
        load_scenario("S9")


@pytest.mark.parametrize("name", ["osrf_cave_straight", "osrf_cave_L", "osrf_cave_3way"])
def test_shipped_scenario_files_are_valid(name: str) -> None:
    scenario = load_scenario(str(EXAMPLES / f"{name}.toml"))
    validate_start(scenario, RayCaster(scenario.mesh), VehicleBody())
    assert not scenario.exited(scenario.start.position)


def _write(tmp_path: Path, text: str) -> Path:
    (tmp_path / "room.obj").write_text(
        "".join(f"v {x} {y} {z}\n" for x in (-2, 2) for y in (-10, 10) for z in (-2, 2))
        + "f 1 2 4\nf 1 4 3\nf 5 7 8\nf 5 8 6\nf 1 5 6\nf 1 6 2\nf 3 4 8\nf 3 8 7\n"
        + "f 1 3 7\nf 1 7 5\nf 2 6 8\nf 2 8 4\n"
    )
    path = tmp_path / "room.toml"
    path.write_text(text)
    return path


VALID = """
mesh = "room.obj"
[start]
position = [0.0, 8.0, 0.0]
[exit]
point = [0.0, -8.0, 0.0]
normal = [0.0, -1.0, 0.0]
radius = 2.0
"""


def test_a_scenario_file_with_one_exit_table(tmp_path: Path) -> None:
    scenario = load_scenario_file(_write(tmp_path, VALID))
    assert scenario.name == "room" and len(scenario.exits) == 1
    assert scenario.exited(np.array([0.0, -9.0, 0.0]))
    assert not scenario.exited(np.array([0.0, -7.0, 0.0]))
    validate_start(scenario, RayCaster(scenario.mesh), VehicleBody())


@pytest.mark.parametrize(
    ("text", "match", "error"),
    [
        ("mesh = [", "not valid TOML", ConfigError),
        (VALID.replace("radius = 2.0", "radius = -1"), "exit.radius", ConfigError),
        (VALID.replace('mesh = "room.obj"', ""), "'mesh'", ConfigError),
        (VALID.replace("[start]", "colour = 'red'\n[start]"), "colour", ConfigError),
        (VALID.replace("room.obj", "missing.obj"), "not found", MeshError),
    ],
)
def test_malformed_scenario_files_are_one_line_errors(
    tmp_path: Path, text: str, match: str, error
) -> None:
    with pytest.raises(error, match=match) as info:
        load_scenario_file(_write(tmp_path, text))
    assert "\n" not in str(info.value)


def test_a_start_outside_the_passage_is_refused(room_scenario: Scenario) -> None:
    caster = RayCaster(room_scenario.mesh)
    outside = Scenario("room", room_scenario.mesh, Pose(10.0, 0.0, 0.0), room_scenario.exits)
    with pytest.raises(ScenarioError, match="outside"):
        validate_start(outside, caster, VehicleBody())
    touching = Scenario("room", room_scenario.mesh, Pose(1.9, 0.0, 0.0), room_scenario.exits)
    with pytest.raises(ScenarioError, match="from a wall"):
        validate_start(touching, caster, VehicleBody())


def test_a_start_outside_an_open_tube_is_refused() -> None:
    scenario = load_scenario(str(EXAMPLES / "osrf_cave_straight.toml"))
    beside = Scenario("x", scenario.mesh, Pose(6.0, 0.0, 2.0), scenario.exits)
    with pytest.raises(ScenarioError, match="outside"):
        validate_start(beside, RayCaster(scenario.mesh), VehicleBody())
