"""The cave line: a diver's guideline tied on rock along the way out, arrows to the exit."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

from cavenav.core.errors import ConfigError, ScenarioError
from cavenav.world.guideline import ARROW_LENGTH_M, Guideline, lay_guideline
from cavenav.world.raycast import RayCaster
from cavenav.world.scenarios import Scenario, check_scenario, load_scenario, procedural_scenario


@pytest.fixture(scope="module")
def s1() -> Scenario:
    return procedural_scenario("S1", 0).with_guideline()


@pytest.fixture(scope="module")
def maze() -> Scenario:
    return procedural_scenario("maze", 0).with_guideline("yellow")


def line_of(cave: Scenario) -> Guideline:
    assert cave.guideline is not None
    return cave.guideline


@pytest.mark.parametrize("name", ["s1", "maze"])
def test_every_tie_off_is_a_centimetre_off_the_rock(name: str, request) -> None:
    cave = request.getfixturevalue(name)
    gap = RayCaster(cave.mesh).distance(line_of(cave).ties)
    assert gap.min() > 0.005 and gap.max() < 0.03, (gap.min(), gap.max())


@pytest.mark.parametrize("name", ["s1", "maze"])
def test_the_line_is_tied_every_few_metres_from_behind_the_start_to_the_exit(
    name: str, request
) -> None:
    cave = request.getfixturevalue(name)
    ties = line_of(cave).ties
    spans = np.linalg.norm(np.diff(ties, axis=0), axis=1)
    assert np.median(spans) < 6.0 and spans.max() < 12.0, spans
    assert cave.progress(ties[0]) < 0.5  # a metre behind the start, give or take a knob
    assert 0 < cave.exit_distance(ties[-1]) < 2.0  # just inside the exit
    assert line_of(cave).length_m > 0.9 * cave.passage_length_m


@pytest.mark.parametrize("name", ["s1", "maze"])
def test_no_span_passes_through_rock(name: str, request) -> None:
    cave = request.getfixturevalue(name)
    caster, ties = RayCaster(cave.mesh), line_of(cave).ties
    for a, b in ((ties[:-1], ties[1:]), (ties[1:], ties[:-1])):  # cast both ways
        length = np.linalg.norm(b - a, axis=1)
        hits = caster.first_hit(a, (b - a) / length[:, None])
        assert (hits >= length).all(), np.flatnonzero(hits < length)


def test_a_span_through_rock_would_be_caught(s1: Scenario) -> None:
    """The check above can fail: from the passage's middle through a tie and as far again
    beyond it, into the rock, it meets the wall."""
    caster, tie = RayCaster(s1.mesh), line_of(s1).ties[3]
    middle = s1.centreline[np.argmin(np.linalg.norm(s1.centreline - tie, axis=1))]
    length = 2 * np.linalg.norm(tie - middle)
    assert caster.first_hit(middle, (tie - middle) * 2 / length) < length


def _span_of(ties: np.ndarray, point: np.ndarray) -> int:
    """The span of the line ``ties`` that ``point`` lies on."""
    a, b = ties[:-1], ties[1:]
    t = np.clip(((point - a) * (b - a)).sum(axis=1) / ((b - a) ** 2).sum(axis=1), 0.0, 1.0)
    return int(np.argmin(np.linalg.norm(a + t[:, None] * (b - a) - point, axis=1)))


@pytest.mark.parametrize("name", ["s1", "maze"])
def test_every_arrow_points_along_the_line_toward_the_exit(name: str, request) -> None:
    cave = request.getfixturevalue(name)
    line = line_of(cave)
    assert len(line.arrows) >= 3
    for point, direction in zip(line.arrows, line.arrow_directions, strict=True):
        span = _span_of(line.ties, point)
        toward_exit = line.ties[span + 1] - line.ties[span]
        assert direction @ toward_exit / np.linalg.norm(toward_exit) > 0.999
    tips = line.arrow_triangles()[:, 0]
    ahead = [np.linalg.norm(tip - p) for tip, p in zip(tips, line.arrows, strict=True)]
    np.testing.assert_allclose(ahead, ARROW_LENGTH_M / 2)
    # the first arrow near the start's end, the last near the exit's
    assert cave.progress(line.arrows[0]) < 3.0
    assert cave.exit_distance(line.arrows[-1]) < 3.0


def test_an_arrow_marks_each_junction_of_the_maze(maze: Scenario) -> None:
    assert len(maze.junctions) >= 3
    arrows = np.array([maze.progress(p) + maze._start_arc for p in line_of(maze).arrows])
    for station in maze.junctions:
        assert np.abs(arrows - station).min() < 3.0, (station, arrows)


def test_the_cave_is_the_same_rock_with_or_without_the_line(s1: Scenario) -> None:
    plain = procedural_scenario("S1", 0)
    assert plain.guideline is None  # off by default, as in the paper
    assert np.array_equal(plain.mesh.vertices, s1.mesh.vertices)
    assert np.array_equal(plain.mesh.faces, s1.mesh.faces)
    assert plain.start == s1.start and plain.exits == s1.exits
    assert s1.without_guideline().guideline is None


def test_the_same_seed_lays_the_same_line_and_another_seed_another(s1: Scenario) -> None:
    again = procedural_scenario("S1", 0).with_guideline()
    assert np.array_equal(line_of(again).ties, line_of(s1).ties)
    assert np.array_equal(line_of(again).arrows, line_of(s1).arrows)
    other = lay_guideline(
        s1.mesh, s1.centreline, start_arc=s1._start_arc, seed=1, junctions=s1.junctions
    )
    assert not np.array_equal(other.ties[:3], line_of(s1).ties[:3])


def test_the_colour_is_white_unless_asked(s1: Scenario, maze: Scenario) -> None:
    assert line_of(s1).colour == "white" and line_of(s1).albedo == (0.8, 0.8, 0.8)
    assert line_of(maze).colour == "yellow" and line_of(maze).albedo[2] < 0.2
    assert s1.with_guideline("white") is s1  # already laid
    with pytest.raises(ConfigError, match="choose one of white, yellow"):
        s1.with_guideline("red")


def test_a_cave_without_a_centre_line_takes_no_guideline(tmp_path: Path) -> None:
    cave = load_scenario(str(write_guided_room(tmp_path, centreline=False)))
    with pytest.raises(ScenarioError, match="centre line"):
        cave.with_guideline()


def write_guided_room(folder: Path, guideline: str = "", centreline: bool = True) -> Path:
    """A scenario file: an 8 x 20 x 7 m hall with its exit 2 m before the far wall, a
    centre line down its middle and ``guideline`` (a line of TOML, or nothing)."""
    trimesh.creation.box(extents=(8.0, 20.0, 7.0)).export(folder / "room.ply")
    path = folder / "room.toml"
    path.write_text(
        'mesh = "room.ply"\n'
        + ("centreline = [[0.0, 9.0, 0.0], [0.0, -8.0, 0.0]]\n" if centreline else "")
        + guideline
        + "[start]\nposition = [0.0, 8.0, 0.0]\n"
        "[[exit]]\npoint = [0.0, -8.0, 0.0]\nnormal = [0.0, -1.0, 0.0]\nradius = 3.0\n"
    )
    return path


@pytest.mark.parametrize(
    ("key", "colour"),
    [("", None), ("guideline = false\n", None), ("guideline = true\n", "white"),
     ('guideline = "yellow"\n', "yellow")],
)  # fmt: skip
def test_a_scenario_file_lays_the_line_its_guideline_key_asks_for(
    tmp_path: Path, key: str, colour: str | None
) -> None:
    cave = load_scenario(str(write_guided_room(tmp_path, key)))
    assert (cave.guideline and cave.guideline.colour) == colour
    if colour:  # on the hall's floor or walls, a centimetre off them
        ties = cave.guideline.ties
        walls = np.minimum(4.0 - np.abs(ties[:, 0]), 3.5 - np.abs(ties[:, 2]))
        np.testing.assert_allclose(walls, 0.01, atol=1e-4)


def test_a_family_file_lays_the_line_on_its_cave(tmp_path: Path, s1: Scenario) -> None:
    path = tmp_path / "guided.toml"
    path.write_text('family = "S1"\nguideline = true\n')
    cave = load_scenario(str(path), 0)
    assert np.array_equal(line_of(cave).ties, line_of(s1).ties)


@pytest.mark.parametrize(
    ("key", "message"),
    [
        ('guideline = "red"\n', "field 'guideline'.*not 'red'"),
        ("guideline = 1\n", "field 'guideline'.*not 1"),
        ("guideline = [true]\n", "field 'guideline'.*true, false or the line's colour"),
    ],
)
def test_a_scenario_file_with_a_bad_guideline_is_refused(
    tmp_path: Path, key: str, message: str
) -> None:
    with pytest.raises(ConfigError, match=message):
        load_scenario(str(write_guided_room(tmp_path, key)))


def test_a_mesh_file_asking_for_a_line_must_give_a_centre_line(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="field 'guideline'.*centreline"):
        load_scenario(str(write_guided_room(tmp_path, "guideline = true\n", centreline=False)))


def test_a_sweep_asking_for_a_line_in_a_cave_without_a_centre_line_is_refused_first(
    tmp_path: Path,
) -> None:
    """Before any cave is built (`check_scenario`), not episode by episode."""
    plain = str(write_guided_room(tmp_path, centreline=False))
    check_scenario(plain)
    with pytest.raises(ScenarioError, match="gives none; add centreline"):
        check_scenario(plain, guideline=True)
    other = tmp_path / "other"
    other.mkdir()
    check_scenario(str(write_guided_room(other)), guideline=True)
    check_scenario("S1", guideline=True)
