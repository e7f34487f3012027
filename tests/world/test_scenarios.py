"""Scenarios: seeded procedural caves S1-S5, their difficulty knobs, and scenario files."""

from __future__ import annotations

import inspect
import json
import math
import os
import re
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from cavenav.core.errors import ConfigError, MeshError, ScenarioError
from cavenav.core.types import Pose
from cavenav.sensors.rig import SensorConfig
from cavenav.world import scenario as scenarios_module
from cavenav.world.collision import VehicleBody, clearance
from cavenav.world.procedural import cache_dir, resample, settled_blocks
from cavenav.world.raycast import RayCaster
from cavenav.world.scenario import KNOB_FACTS
from cavenav.world.scenarios import (
    HELD_OUT_SEEDS,
    KNOBS,
    SCENARIOS,
    Difficulty,
    Scenario,
    check_scenario,
    difficulty_table,
    load_scenario,
    load_scenario_file,
    parse_difficulty,
    procedural_scenario,
    validate_start,
)

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"
# The five families of SPEC section 6; crawl, maze and long have tests/test_cave_families.py.
SPEC_FAMILIES = ("S1", "S2", "S3", "S4", "S5")


@pytest.mark.slow
def test_the_same_seed_builds_the_same_cave_bit_for_bit(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setenv("CAVENAV_CACHE", str(tmp_path / "a"))
    a = load_scenario("S3", seed=7)
    monkeypatch.setenv("CAVENAV_CACHE", str(tmp_path / "b"))
    b = load_scenario("S3", seed=7)
    assert np.array_equal(a.mesh.vertices, b.mesh.vertices)
    assert np.array_equal(a.mesh.faces, b.mesh.faces)
    assert a.start == b.start


def test_a_built_cave_is_cached_in_the_folder_cavenav_cache_names() -> None:
    # conftest points CAVENAV_CACHE at this test session's own folder.
    cache = Path(os.environ["CAVENAV_CACHE"])
    assert cache_dir() == cache and cache != Path.home() / ".cache" / "cavenav"
    load_scenario("S1", seed=0)
    assert (cache / f"S1-seed0-{REFERENCE_DIGESTS['S1']}.npz").is_file()


def test_another_seed_builds_another_cave() -> None:
    a, b = load_scenario("S3", seed=0), load_scenario("S3", seed=1)
    assert a.mesh.vertices.shape != b.mesh.vertices.shape or not np.allclose(
        a.mesh.vertices, b.mesh.vertices
    )


@pytest.mark.parametrize("name", SPEC_FAMILIES)
def test_procedural_caves_have_the_promised_shape(name: str) -> None:
    layout = SCENARIOS[name].layout(0)
    spec = layout.spec
    start = int(np.argmin(np.linalg.norm(spec.centreline - layout.start.position, axis=1)))
    _, s = resample(spec.centreline[start : spec.exit_index + 1], 0.1)
    assert 40.0 <= s[-1] <= 80.0, "passage length"
    widths = 2 * spec.half_width[start : spec.exit_index]
    chamber = spec.section.squareness[start : spec.exit_index] > 0.01 if name == "S5" else False
    assert widths.min() >= 3.0 and widths[~chamber].max() <= 8.0, "passages 3-8 m across"
    assert widths.max() <= 12.0, "and S5's collapse chamber up to 12 m"

    scenario = load_scenario(name, seed=0)
    caster = RayCaster(scenario.mesh)
    validate_start(scenario, caster, VehicleBody())
    assert scenario.exit_distance(scenario.start.position) >= 30.0


def _obstacles(boulders) -> list[list]:  # noqa: ANN001
    """S3's boulders grouped into obstacles: a pile's blocks lie within a metre of its base
    (S5's rocks, as many as 20 in 60 m, are each an obstacle, however close)."""
    groups: list[list] = []
    for boulder in boulders:
        xy = np.asarray(boulder.centre[:2])
        near = [g for g in groups if np.linalg.norm(np.asarray(g[0].centre[:2]) - xy) < 1.0]
        if near:
            near[0].append(boulder)
        else:
            groups.append([boulder])
    return groups


def _height_span(block) -> tuple[float, float]:  # noqa: ANN001
    x, y = np.meshgrid(np.arange(-3, 3, 0.05), np.arange(-3, 3, 0.05))
    bottom, top = block.heights(x.ravel(), y.ravel())
    inside = bottom <= top
    return block.centre[2] + bottom[inside].min(), block.centre[2] + top[inside].max()


def test_s3_starts_near_a_wall_at_the_height_of_the_frontal_obstacle() -> None:
    layout = SCENARIOS["S3"].layout(0)
    pile = [block for block, _ in settled_blocks(layout.spec)][:2]  # the frontal pile
    low, high = _height_span(pile[0])[0], max(_height_span(b)[1] for b in pile)
    assert low < layout.start.z - 1.0 and layout.start.z + 0.3 < high
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


EXITS = "[[exit]]\npoint = [0.0, -8.0, 0.0]\nnormal = [0.0, -1.0, 0.0]\nradius = 2.0\n"
PIECE = '[[mesh]]\npath = "room.obj"\n'
REST = f"[start]\nposition = [0.0, 8.0, 0.0]\n{EXITS}"  # after a [[mesh]] piece


@pytest.mark.parametrize(
    ("text", "field", "bound"),
    [
        (VALID.replace("radius = 2.0", "radius = 1e308"), "exit.radius", "10000"),
        (
            VALID.replace("[exit]", "[[exit]]").replace("radius = 2.0", "radius = 1e308"),
            "exit.0.radius",
            "10000",
        ),
        (VALID.replace("[0.0, 8.0, 0.0]", "[0.0, 8.0e9, 0.0]"), "start.position.1", "100000"),
        (VALID.replace("[0.0, -8.0, 0.0]", "[-1e300, -8.0, 0.0]"), "exit.point.0", "-100000"),
        (VALID.replace("[0.0, -1.0, 0.0]", "[0.0, -1e308, 0.0]"), "exit.normal.1", "-100000"),
        (VALID.replace("[start]", "[start]\nyaw_deg = 1e300"), "start.yaw_deg", "360"),
        (VALID.replace('"room.obj"', '"room.obj"\nscale = 1e-300'), "scale", "0.000001"),
        (
            VALID.replace('"room.obj"', '"room.obj"\nstep_budget = 10_000_000'),
            "step_budget",
            "100000",
        ),
        (
            f"centreline = [[0.0, 8.0, 0.0], [0.0, -1e7, 0.0]]\n{VALID}",
            "centreline.1.1",
            "-100000",
        ),
        (f"{PIECE}offset = [1e308, 0.0, 0.0]\n{REST}", "mesh.0.offset.0", "100000"),
        (f"{PIECE}yaw_deg = -1e9\n{REST}", "mesh.0.yaw_deg", "-360"),
        (f"{PIECE}scale = 1e9\n{REST}", "mesh.0.scale", "1000"),
        (f"{VALID}[sensors]\nresolution = [1_000_000, 480]\n", "sensors.resolution.0", "8192"),
    ],
)
def test_every_number_of_a_scenario_file_is_bounded_by_what_a_cave_can_hold(
    tmp_path: Path, text: str, field: str, bound: str
) -> None:
    """A typo such as radius = 1e308 is refused at once, naming the field and its bound,
    instead of overflowing the plots of the episode it would fly."""
    with pytest.raises(ConfigError) as info:
        load_scenario_file(_write(tmp_path, text))
    message = str(info.value)
    assert f"field '{field}': Input should be" in message and message.endswith(bound)
    assert "\n" not in message


def test_the_largest_caves_and_portals_a_file_may_hold_still_load(tmp_path: Path) -> None:
    widest = VALID.replace("radius = 2.0", "radius = 1e4")
    bounds = widest.replace("[start]", "[start]\nyaw_deg = -360")
    scenario = load_scenario_file(_write(tmp_path, bounds))
    assert scenario.exits[0].radius == 1e4


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


# ------------------------------------------------------------------ cave families

ROOT = Path(__file__).resolve().parents[2]

# `PassageSpec.digest` of each family's cave at seed 0, at the default difficulty: however
# the knobs are spelled, the plain families build exactly these caves. (A deliberate change
# of the generator bumps GENERATOR_VERSION, which changes them all: record anew.)
REFERENCE_DIGESTS = {
    "S1": "fe29fb1e58936842",
    "S2": "743d679bfc1ca166",
    "S3": "a81be2f7e09ef70f",
    "S4": "452ebda8ae240c5d",
    "S5": "5b2350fe45d02e4d",
}

# A value of each knob, in range and away from the default, for each family that has it.
HARDER = {
    "constriction_m": 2.4,
    "undulation_m": 6.0,
    "bend_deg": 60.0,
    "obstacles": 4,
    "obstacle_scale": 1.2,
    "roughness_m": 0.45,
}


def _start_index(layout) -> int:
    return int(np.argmin(np.linalg.norm(layout.spec.centreline - layout.start.position, axis=1)))


def _narrowest_width(layout) -> float:
    """Narrowest width of the passage's profile between the start and the exit, metres."""
    return float(2 * layout.spec.half_width[_start_index(layout) : layout.spec.exit_index].min())


@pytest.mark.parametrize("name", SPEC_FAMILIES)
def test_the_default_difficulty_builds_the_reference_cave(name: str) -> None:
    family = SCENARIOS[name]
    spelled_out = Difficulty(**{knob: value.default for knob, value in family.knobs.items()})
    for difficulty in (None, Difficulty(), spelled_out):
        assert family.layout(0, difficulty).spec.digest() == REFERENCE_DIGESTS[name], difficulty


@pytest.mark.parametrize(
    ("name", "knob"), [(n, k) for n in SPEC_FAMILIES for k in SCENARIOS[n].knobs]
)
def test_every_knob_changes_the_cave_and_its_cache_key(name: str, knob: str) -> None:
    harder = SCENARIOS[name].layout(0, Difficulty(**{knob: HARDER[knob]}))
    assert harder.spec.digest() != REFERENCE_DIGESTS[name]


@pytest.mark.parametrize(("name", "default"), [("S1", 3.6), ("S2", 3.8)])
def test_constriction_m_is_the_width_of_the_narrowest_constriction(
    name: str, default: float
) -> None:
    family = SCENARIOS[name]
    for seed in (0, 3):
        assert _narrowest_width(family.layout(seed)) == pytest.approx(default, abs=0.05)
        for width in (1.5, 2.4, 5.0):
            narrowed = family.layout(seed, Difficulty(constriction_m=width))
            assert _narrowest_width(narrowed) == pytest.approx(width, abs=0.05)


def test_undulation_m_is_the_peak_to_peak_height_of_the_passage() -> None:
    for seed in (0, 5):
        for height in (0.0, 4.0, 6.0):
            layout = SCENARIOS["S2"].layout(seed, Difficulty(undulation_m=height))
            z = layout.spec.centreline[_start_index(layout) : layout.spec.exit_index, 2]
            # The portals are smoothed into straight ends, which shaves a little off a peak.
            assert 0.95 * height <= np.ptp(z) <= height + 1e-9


@pytest.mark.parametrize("bend", [30.0, 60.0, 90.0, 120.0, 150.0])
def test_bend_deg_turns_the_second_leg_that_far_from_the_first(bend: float) -> None:
    for seed in (0, 1):  # a bend to the right, then one to the left
        layout = SCENARIOS["S4"].layout(seed, Difficulty(bend_deg=bend))
        points, exit_index = layout.spec.centreline, layout.spec.exit_index
        start = _start_index(layout)
        first_leg = points[start + 8] - points[start]
        second_leg = points[exit_index] - points[exit_index - 8]
        first_leg, second_leg = (v / np.linalg.norm(v) for v in (first_leg, second_leg))
        turn = math.degrees(math.acos(np.clip(first_leg @ second_leg, -1.0, 1.0)))
        assert turn == pytest.approx(bend, abs=0.5)
        assert layout.start.forward @ first_leg == pytest.approx(1.0), "start faces the leg"
        assert abs(second_leg[0]) == pytest.approx(1.0), "the exit runs along an axis"
        assert f"{bend:g}-degree" in layout.description


def _stations_from_the_bend(bend: float) -> list[float]:
    """Metres along S4's passage from its bend's middle to each stalactite."""
    layout = SCENARIOS["S4"].layout(0, Difficulty(bend_deg=bend))
    line = layout.spec.centreline[:, :2]
    middle = np.argmin(np.linalg.norm(line - [0.0, -30.0], axis=1))  # nearest the corner
    nearest = [
        np.argmin(np.linalg.norm(line - (s.x, s.y), axis=1)) for s in layout.spec.speleothems
    ]
    return [0.25 * float(k - middle) for k in nearest]


def test_the_stalactites_hang_over_the_bend_however_sharp() -> None:
    """The rounded centre line reaches the bend sooner than the two legs it replaced (by
    6 m at 150 degrees): what is placed by the bend must come with it."""
    right_angle = _stations_from_the_bend(90.0)
    assert min(right_angle) < 0.0 < max(right_angle)
    for bend in (30.0, 150.0):
        assert _stations_from_the_bend(bend) == pytest.approx(right_angle, abs=0.5)


def test_a_hairpin_keeps_its_closed_end_behind_the_exit_plane() -> None:
    # The mesh grid is cut 1.5 m past the exit plane; a first leg reaching across that
    # plane would be cut open there, a second way out of the cave.
    for seed in (0, 1):
        layout = SCENARIOS["S4"].layout(seed, Difficulty(bend_deg=150.0))
        points, exit_index = layout.spec.centreline, layout.spec.exit_index
        outward = np.sign(points[exit_index, 0] - points[exit_index - 1, 0])
        behind = outward * (points[exit_index, 0] - points[0, 0])
        assert behind >= 7.0
        assert layout.spec.half_width.max() + 1.5 < behind


@pytest.mark.parametrize(
    ("name", "count"),
    [("S3", 0), ("S3", 1), ("S3", 5), ("S3", 8), ("S5", 0), ("S5", 3), ("S5", 20)],
)
def test_obstacles_is_the_number_of_boulders_between_start_and_exit(name: str, count: int) -> None:
    layout = SCENARIOS[name].layout(2, Difficulty(obstacles=count))
    boulders = layout.spec.boulders
    assert len(_obstacles(boulders) if name == "S3" else boulders) == count
    points = layout.spec.centreline
    for boulder in layout.spec.boulders:
        nearest = int(np.argmin(np.linalg.norm(points - np.asarray(boulder.centre), axis=1)))
        assert _start_index(layout) < nearest < layout.spec.exit_index


def test_s3_boulders_alternate_frontal_and_lateral_along_the_passage() -> None:
    layout = SCENARIOS["S3"].layout(0, Difficulty(obstacles=5))
    obstacles = _obstacles(layout.spec.boulders)
    assert [len(g) for g in obstacles] == [2, 1, 2, 1, 2], "frontal piles of two, lateral blocks"
    x = np.array([g[0].centre[0] for g in obstacles])
    y = np.array([g[0].centre[1] for g in obstacles])
    assert np.all(np.diff(y) < 0), "each farther along -y than the one before"
    frontal, lateral = x[0::2], x[1::2]
    assert np.sign(frontal).tolist() == [np.sign(layout.start.x)] * 3, "in line with the start"
    assert np.all(np.sign(lateral) == -np.sign(layout.start.x)), "from the other wall"


@pytest.mark.parametrize("name", ["S3", "S5"])
def test_obstacle_scale_grows_every_boulder_in_place(name: str) -> None:
    plain = SCENARIOS[name].layout(4).spec.boulders
    grown = SCENARIOS[name].layout(4, Difficulty(obstacle_scale=1.5)).spec.boulders
    assert [b.centre for b in grown] == [b.centre for b in plain]
    assert np.allclose([b.radii for b in grown], 1.5 * np.array([b.radii for b in plain]))


@pytest.mark.parametrize("name", SPEC_FAMILIES)
def test_roughness_m_is_the_wall_noise_of_every_family(name: str) -> None:
    assert SCENARIOS[name].layout(0).spec.roughness == 0.3
    assert SCENARIOS[name].layout(0, Difficulty(roughness_m=0.6)).spec.roughness == 0.6


@pytest.mark.parametrize(
    ("name", "knob", "owners"),
    [("S1", "bend_deg", "S4"), ("S4", "obstacles", "S3, S5"), ("S3", "constriction_m", "S1, S2")],
)
def test_a_knob_the_family_lacks_is_refused_naming_who_has_it(
    name: str, knob: str, owners: str
) -> None:
    with pytest.raises(ScenarioError) as info:
        procedural_scenario(name, 0, Difficulty(**{knob: HARDER[knob]}))
    message = str(info.value)
    assert knob in message and name in message and f"belongs to {owners}" in message


@pytest.mark.parametrize(
    ("name", "knob", "value", "admitted"),
    [
        ("S1", "constriction_m", 0.8, "[1, 7]"),  # the vehicle would have no room
        ("S2", "constriction_m", 7.0, "[1, 6.4]"),  # wider than the passage
        ("S2", "undulation_m", 9.0, "[0, 8]"),
        ("S3", "obstacles", -1, "[0, 8]"),
        ("S5", "obstacles", 21, "[0, 20]"),
        ("S3", "obstacle_scale", 0.0, "(0, 1.5]"),
        ("S4", "bend_deg", 0.0, "(0, 150]"),
        ("S4", "bend_deg", 170.0, "(0, 150]"),
        ("S1", "roughness_m", -0.1, "[0, 1]"),
    ],
)
def test_a_knob_out_of_range_is_refused_with_the_range(
    name: str, knob: str, value: float, admitted: str
) -> None:
    with pytest.raises(ScenarioError, match=rf"{name}: {knob}=") as info:
        procedural_scenario(name, 0, Difficulty(**{knob: value}))
    assert admitted in str(info.value)


@pytest.mark.parametrize(
    ("knobs", "match"),
    [
        ({"obstacles": 2.5}, "obstacles must be a whole number"),
        ({"constriction_m": "wide"}, "constriction_m must be a number"),
        ({"bend_deg": float("nan")}, "bend_deg must be finite"),
        ({"roughness_m": True}, "roughness_m must be a number"),
    ],
)
def test_a_knob_of_the_wrong_type_is_refused(knobs: dict, match: str) -> None:
    with pytest.raises(ScenarioError, match=match):
        Difficulty(**knobs)


def test_parse_difficulty_reads_the_command_line_form() -> None:
    difficulty = parse_difficulty(["constriction_m=3.0", " obstacles = 4 "])
    assert difficulty == Difficulty(constriction_m=3.0, obstacles=4)
    # What summary.json records: the knobs set, a count as a whole number.
    assert json.dumps(difficulty.to_dict()) == '{"constriction_m": 3.0, "obstacles": 4}'
    assert parse_difficulty([]) == Difficulty() and Difficulty().to_dict() == {}


_knob_values = st.builds(
    Difficulty,
    constriction_m=st.none() | st.floats(1.0, 7.0),
    undulation_m=st.none() | st.floats(0.0, 8.0),
    bend_deg=st.none() | st.floats(0.1, 150.0),
    obstacles=st.none() | st.integers(0, 20),
    obstacle_scale=st.none() | st.floats(0.01, 1.5),
    roughness_m=st.none() | st.floats(0.0, 1.0),
)


@given(_knob_values)
def test_parse_difficulty_round_trips_to_dict(difficulty: Difficulty) -> None:
    items = [f"{knob}={value!r}" for knob, value in difficulty.to_dict().items()]
    assert parse_difficulty(items) == difficulty
    assert Difficulty.from_dict(json.loads(json.dumps(difficulty.to_dict()))) == difficulty


@pytest.mark.parametrize(
    ("items", "match"),
    [
        (["width=3"], "unknown difficulty knob 'width'; the knobs are constriction_m"),
        (["constriction_m"], "KEY=VALUE"),
        (["constriction_m="], "KEY=VALUE"),
        (["obstacles=many"], "obstacles takes a whole number"),
        (["obstacles=2.5"], "obstacles takes a whole number"),
        (["constriction_m=wide"], "constriction_m takes a number"),
        (["obstacles=2", "obstacles=3"], "given twice"),
    ],
)
def test_bad_difficulty_items_are_one_line_config_errors(items: list[str], match: str) -> None:
    with pytest.raises(ConfigError, match=match) as info:
        parse_difficulty(items)
    assert "\n" not in str(info.value)


def test_a_harder_cave_is_recorded_and_cached_apart(monkeypatch, room) -> None:
    built: list[tuple[str, str]] = []

    def build_cave(spec, name):  # stands in for meshing, which takes seconds
        built.append((name, spec.digest()))
        return room

    monkeypatch.setattr(scenarios_module, "build_cave", build_cave)
    plain = procedural_scenario("S1", 3)
    harder = procedural_scenario("S1", 3, Difficulty(constriction_m=2.4))
    (plain_name, plain_digest), (harder_name, harder_digest) = built
    assert plain_name == "S1-seed3", "the plain caves keep their names and cache files"
    assert harder_name.startswith("S1-seed3-d") and harder_digest != plain_digest
    assert plain.difficulty == Difficulty()
    assert harder.difficulty == Difficulty(constriction_m=2.4)
    assert "2.4 m" in harder.description


def test_held_out_seeds_begin_where_the_training_seeds_end() -> None:
    from cavenav.sim.env import TRAINING_SEEDS

    assert HELD_OUT_SEEDS.start == TRAINING_SEEDS
    assert TRAINING_SEEDS - 1 not in HELD_OUT_SEEDS and 1234 in HELD_OUT_SEEDS


@pytest.mark.parametrize("knob", KNOBS)
def test_a_knob_past_its_range_is_refused_for_its_one_reason_from_the_command_line_and_a_file(
    knob: str, tmp_path: Path
) -> None:
    family = next(f for f in SCENARIOS.values() if knob in f.knobs)
    value = family.knobs[knob].high + 1
    text = f"{int(value)}" if KNOB_FACTS[knob].count else f"{value:g}"
    why = re.escape(f"{knob}={text} is outside {family.knobs[knob]}: {KNOB_FACTS[knob].limits}")
    with pytest.raises(ScenarioError, match=why):
        check_scenario(family.name, parse_difficulty([f"{knob}={text}"]))
    path = tmp_path / "hard.toml"
    path.write_text(f'family = "{family.name}"\n[difficulty]\n{knob} = {text}\n')
    with pytest.raises(ConfigError, match=f"{re.escape(str(path))}: \\[difficulty\\]: .*{why}"):
        check_scenario(str(path))


@pytest.mark.parametrize("knob", KNOBS)
def test_a_count_knob_takes_whole_numbers_and_the_others_real_ones(knob: str) -> None:
    if KNOB_FACTS[knob].count:
        with pytest.raises(ConfigError, match=f"{knob} takes a whole number"):
            parse_difficulty([f"{knob}=1.5"])
        assert parse_difficulty([f"{knob}=2"]).to_dict() == {knob: 2}
    else:
        assert parse_difficulty([f"{knob}=1.5"]).to_dict() == {knob: 1.5}


def test_the_knob_table_in_the_docs_is_the_one_the_families_declare() -> None:
    table = difficulty_table()
    assert table in inspect.cleandoc(Difficulty.__doc__ or "")
    assert table in (ROOT / "docs" / "guides" / "scenarios.md").read_text()


FAMILY_FILE = """
name = "tight"
family = "s1"
[difficulty]
constriction_m = 2.4
[optics]
water = "turbid"
"""


def test_a_family_file_builds_its_family_at_the_given_seed(
    tmp_path: Path, monkeypatch, room
) -> None:
    monkeypatch.setattr(scenarios_module, "build_cave", lambda spec, name: room)
    path = tmp_path / "tight.toml"
    path.write_text(FAMILY_FILE)
    cave = load_scenario(str(path), seed=7)
    expected = SCENARIOS["S1"].layout(7, Difficulty(constriction_m=2.4))
    assert (cave.name, cave.seed, cave.start) == ("tight", 7, expected.start)
    assert cave.difficulty == Difficulty(constriction_m=2.4)
    assert cave.description == expected.description  # the file gives none
    assert cave.optics == {"water": "turbid"}
    # Knobs from the command line override the file's.
    other = load_scenario(str(path), 8, Difficulty(constriction_m=3.0, roughness_m=0.4))
    assert other.seed == 8
    assert other.difficulty == Difficulty(constriction_m=3.0, roughness_m=0.4)


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ('family = "S1"\nmesh = "room.obj"', "either 'mesh' .* or 'family', not both"),
        ('name = "nothing"', "give 'mesh' .* or 'family'"),
        ('family = "S9"', "family.*unknown family 'S9'"),
        ('family = "S1"\n[difficulty]\nwidth = 2.0', r"\[difficulty\].*'width'"),
        ('family = "S1"\n[difficulty]\nbend_deg = 60.0', "bend_deg does not apply to S1"),
        ('family = "S1"\n[difficulty]\nconstriction_m = 0.5', "constriction_m=0.5"),
        ('family = "S1"\n[start]\nposition = [0.0, 0.0, 0.0]', "'start'"),
    ],
)
def test_malformed_family_files_are_one_line_config_errors(
    tmp_path: Path, text: str, match: str
) -> None:
    path = tmp_path / "family.toml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=match) as info:
        load_scenario_file(path)
    assert "\n" not in str(info.value)


def test_a_mesh_file_takes_no_difficulty(tmp_path: Path) -> None:
    path = _write(tmp_path, VALID)
    with pytest.raises(ScenarioError, match="no difficulty knobs"):
        load_scenario_file(path, difficulty=Difficulty(roughness_m=0.5))
    assert load_scenario_file(path, difficulty=Difficulty()).difficulty is None


def test_the_shipped_hard_s1_file_flies_a_narrower_s1() -> None:
    path = EXAMPLES / "hard_s1.toml"
    assert path.read_text().startswith("# "), "the line `cavenav scenarios` shows"
    cave = load_scenario(str(path), seed=0)
    assert cave.difficulty == Difficulty(constriction_m=2.4, roughness_m=0.45)
    assert cave.name == "hard-s1" and cave.mesh.name.startswith("S1-seed0-d")
    validate_start(cave, RayCaster(cave.mesh), VehicleBody())


SENSORS_TABLE = "\n[sensors]\nresolution = [160, 120]\nsounder_resolution = [8, 6]\n"


def test_a_scenario_files_sensors_table_sets_the_pixel_counts(tmp_path: Path) -> None:
    scenario = load_scenario_file(_write(tmp_path, VALID + SENSORS_TABLE))
    assert scenario.sensors == {"resolution": (160, 120), "sounder_resolution": (8, 6)}
    sensors = SensorConfig().for_scenario(scenario.name, scenario.optics, {}, scenario.sensors)
    assert sensors.resolution == (160, 120) and sensors.sounder_pixels == (8, 6)
    assert sensors.camera.hfov_deg == pytest.approx(53.13, abs=0.01)
    # Without the table: the paper's 640x480 and 32x24.
    plain = load_scenario_file(_write(tmp_path, VALID))
    assert plain.sensors == {}
    assert SensorConfig().for_scenario("room", {}, {}, plain.sensors).resolution == (640, 480)


def test_a_family_file_takes_a_sensors_table_too(tmp_path: Path, monkeypatch, room) -> None:
    monkeypatch.setattr(scenarios_module, "build_cave", lambda spec, name: room)
    path = tmp_path / "small.toml"
    path.write_text('family = "S1"\n[sensors]\nresolution = [84, 84]\n')
    assert load_scenario(str(path), seed=3).sensors == {"resolution": (84, 84)}


@pytest.mark.parametrize(
    ("table", "match"),
    [
        ("resolution = [0, 120]", r"'sensors\.resolution\.0'.*greater than 0"),
        ("resolution = [160]", r"'sensors\.resolution\.1': Field required"),
        ("resolution = [160.5, 120]", r"'sensors\.resolution\.0'.*integer"),
        ("resolution = [160.0, 120]", r"'sensors\.resolution\.0'.*integer"),
        ('resolution = "160x120"', r"'sensors\.resolution'"),
        ("sounder_resolution = [8, -6]", r"'sensors\.sounder_resolution\.1'"),
        ("fov_deg = 90", r"'sensors\.fov_deg'"),
    ],
)
def test_a_bad_sensors_table_is_a_one_line_error_naming_the_field(
    tmp_path: Path, table: str, match: str
) -> None:
    with pytest.raises(ConfigError, match=match) as info:
        load_scenario_file(_write(tmp_path, f"{VALID}\n[sensors]\n{table}\n"))
    assert "\n" not in str(info.value)
