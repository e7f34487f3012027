"""Caves chained from several meshes, their open portals, entrances and centre lines."""

from __future__ import annotations

import math
import re
import tomllib
from pathlib import Path

import numpy as np
import pytest

from cavenav.core.errors import ConfigError
from cavenav.core.types import Pose
from cavenav.world.collision import VehicleBody
from cavenav.world.mesh import (
    SEAM_WELD_M,
    CaveMesh,
    Portal,
    join_meshes,
    load_mesh,
    make_mesh,
    open_portals,
    place_mesh,
)
from cavenav.world.raycast import RayCaster
from cavenav.world.scenarios import (
    ExitPortal,
    Scenario,
    load_scenario_file,
    validate_start,
)

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"
MESHES = EXAMPLES / "meshes"
CHAINS = ["osrf_chain_zigzag", "osrf_chain_long", "osrf_chain_junction"]


@pytest.fixture(scope="module")
def tiles() -> dict[str, CaveMesh]:
    return {name: load_mesh(MESHES / f"cave_{name}_20m.dae") for name in ("straight", "L", "3way")}


@pytest.fixture(scope="module")
def chains() -> dict[str, Scenario]:
    return {name: load_scenario_file(EXAMPLES / f"{name}.toml") for name in CHAINS}


def open_tube(radius: float = 2.0, length: float = 10.0, sides: int = 32) -> CaveMesh:
    """A cylinder along y from -length/2 to +length/2, open at both ends."""
    angle = np.linspace(0.0, 2 * np.pi, sides, endpoint=False)
    ring = np.stack([radius * np.cos(angle), np.zeros(sides), radius * np.sin(angle)], axis=1)
    vertices = np.concatenate([ring + [0, -length / 2, 0], ring + [0, length / 2, 0]])
    i = np.arange(sides)
    j = (i + 1) % sides
    faces = np.concatenate([np.stack([i, j, i + sides], 1), np.stack([j, j + sides, i + sides], 1)])
    return make_mesh(vertices, faces, "tube")


def portal_at(portals: list[Portal], point: object) -> Portal:
    """The one portal whose centre lies within 5 cm of ``point``."""
    (found,) = [p for p in portals if np.linalg.norm(p.centre - np.asarray(point)) < 0.05]
    return found


# ------------------------------------------------------------------ open portals


def test_an_open_tube_has_a_portal_at_each_end_facing_out() -> None:
    portals = open_portals(open_tube(radius=2.0, length=10.0))
    assert len(portals) == 2
    for end in (-1.0, 1.0):
        portal = portal_at(portals, [0.0, 5.0 * end, 0.0])
        assert portal.normal == pytest.approx([0.0, end, 0.0], abs=1e-9)
        assert portal.radius == pytest.approx(2.0)
        assert len(portal.loop) == 32


def test_a_closed_mesh_has_no_portal() -> None:
    import trimesh

    box = trimesh.creation.box(extents=(4.0, 20.0, 4.0))
    assert open_portals(make_mesh(box.vertices, box.faces)) == []


# Measured with open_portals: every tile is open at the middles of the sides of its 20 m
# square, 2 m up, with a rim 2.1-2.6 m from the centre; so tiles on a 20 m grid chain.
TILE_PORTALS = {
    "straight": [((0, 10, 2), (0, 1, 0)), ((0, -10, 2), (0, -1, 0))],
    "L": [((0, 10, 2), (0, 1, 0)), ((10, 0, 2), (1, 0, 0))],
    "3way": [((0, 10, 2), (0, 1, 0)), ((10, 0, 2), (1, 0, 0)), ((-10, 0, 2), (-1, 0, 0))],
}


@pytest.mark.parametrize("tile", TILE_PORTALS)
def test_each_osrf_tile_is_open_at_the_middles_of_its_20m_square(tiles, tile: str) -> None:
    portals = open_portals(tiles[tile])
    assert len(portals) == len(TILE_PORTALS[tile])
    for centre, normal in TILE_PORTALS[tile]:
        portal = portal_at(portals, centre)
        assert portal.normal == pytest.approx(normal, abs=0.01)
        assert 2.5 < portal.radius < 2.6


# ------------------------------------------------------------------ placing and joining


def test_a_positive_yaw_turns_a_piece_the_way_the_vehicle_turns_left() -> None:
    tube = open_tube()
    turned = place_mesh(tube, offset=(1.0, 2.0, 3.0), yaw_deg=90.0)
    # The tube's -y end now faces the way a vehicle heading -y faces after turning 90 left.
    far_end = portal_at(open_portals(turned), [1.0 + 5.0, 2.0, 3.0])
    assert far_end.normal == pytest.approx(Pose(0, 0, 0, psi=math.pi / 2).forward, abs=1e-9)


def test_joined_tiles_keep_their_places_and_close_their_seams(tiles) -> None:
    pieces = [
        tiles["straight"],
        place_mesh(tiles["L"], (0.0, -20.0, 0.0)),
        place_mesh(tiles["straight"], (20.0, -20.0, 0.0), yaw_deg=90.0),
    ]
    joined = join_meshes(pieces)
    assert joined.triangle_count == sum(p.triangle_count for p in pieces)
    # Welding moves rim vertices onto their neighbour's, never farther than SEAM_WELD_M.
    moved = np.linalg.norm(joined.vertices - np.concatenate([p.vertices for p in pieces]), axis=1)
    assert 0 < moved.max() <= SEAM_WELD_M
    # Open only where no tile meets another: the first tile's +y end, the last one's +x end.
    ends = open_portals(joined)
    assert len(ends) == 2
    portal_at(ends, [0.0, 10.0, 2.0])
    assert portal_at(ends, [30.0, -20.0, 2.0]).normal == pytest.approx([1, 0, 0], abs=0.01)


# ------------------------------------------------------------------ chained scenario files


def chain_file(tmp_path: Path, pieces: str, extra: str = "") -> Path:
    path = tmp_path / "chain.toml"
    path.write_text(
        f"{extra}\n{pieces}\n[start]\nposition = [0.0, 8.5, 2.0]\n"
        "[[exit]]\npoint = [0.0, -30.0, 2.0]\nnormal = [0.0, -1.0, 0.0]\nradius = 3.5\n"
    )
    return path


STRAIGHT = (MESHES / "cave_straight_20m.dae").as_posix()
L_TILE = (MESHES / "cave_L_20m.dae").as_posix()
TWO_PIECES = f"""
[[mesh]]
path = "{STRAIGHT}"
[[mesh]]
path = "{L_TILE}"
offset = [0.0, -20.0, 0.0]
yaw_deg = 180.0
"""


def test_a_chained_file_loads_one_mesh_with_each_piece_at_its_offset(tmp_path: Path, tiles) -> None:
    scenario = load_scenario_file(chain_file(tmp_path, TWO_PIECES))
    straight, bend = np.split(scenario.mesh.vertices, [len(tiles["straight"].vertices)])
    # The straight tile where its file has it: x within +-2.7 m, y from -10 to 10.
    assert straight.min(axis=0) == pytest.approx([-2.71, -10.0, -0.56], abs=0.01)
    assert straight.max(axis=0) == pytest.approx([2.57, 10.0, 4.56], abs=0.01)
    # The L (x from -2.5 to 10, y from -2.2 to 10 in its file) turned half round, then
    # moved 20 m down y: x from -10 to 2.5, y from -30 to -17.8.
    assert bend.min(axis=0)[:2] == pytest.approx([-10.0, -30.0], abs=0.03)
    assert bend.max(axis=0)[:2] == pytest.approx([2.46, -17.8], abs=0.03)
    assert scenario.mesh.name == "cave_straight_20m.dae+cave_L_20m.dae"
    validate_start(scenario, RayCaster(scenario.mesh), VehicleBody())


def test_mesh_as_one_path_still_loads_that_file_unchanged() -> None:
    scenario = load_scenario_file(EXAMPLES / "osrf_cave_straight.toml")
    assert scenario.mesh.name == "cave_straight_20m.dae"
    assert np.array_equal(
        scenario.mesh.vertices, load_mesh(MESHES / "cave_straight_20m.dae").vertices
    )
    assert scenario.centreline is None


@pytest.mark.parametrize(
    ("pieces", "extra", "field"),
    [
        (TWO_PIECES.replace("[0.0, -20.0, 0.0]", "[0.0, -20.0]"), "", "'mesh.1.offset.2'"),
        (TWO_PIECES.replace("yaw_deg = 180.0", "yaw_deg = 'half'"), "", "'mesh.1.yaw_deg'"),
        (TWO_PIECES.replace("yaw_deg = 180.0", "yaw_deg = nan"), "", "'mesh.1.yaw_deg'"),
        (TWO_PIECES.replace("yaw_deg", "rotation"), "", "'mesh.1.rotation'"),
        (TWO_PIECES.replace(f'path = "{STRAIGHT}"', ""), "", "'mesh.0.path'"),
        ("mesh = []", "", "'mesh'"),
        ("mesh = 3", "", "'mesh'"),
        (TWO_PIECES, "centreline = [[0.0, 8.0, 2.0]]", "'centreline'"),
        (TWO_PIECES, "centreline = [[0.0, 8.0, 2.0], [0.0, 8.0, 2.0]]", "'centreline'"),
        (TWO_PIECES, "centreline = [[0.0, 8.0, 2.0], [0.0, inf, 2.0]]", "'centreline.1.1'"),
        (TWO_PIECES, "step_budget = 0", "'step_budget'"),
        (TWO_PIECES, "step_budget = 300.0", "'step_budget'"),
    ],
)
def test_a_bad_chain_entry_is_one_line_naming_the_field(
    tmp_path: Path, pieces: str, extra: str, field: str
) -> None:
    path = chain_file(tmp_path, pieces, extra)
    with pytest.raises(ConfigError, match=re.escape(f"{path}: field {field}")) as info:
        load_scenario_file(path)
    assert "\n" not in str(info.value)


def test_a_long_chain_carries_its_own_step_budget(chains, tmp_path: Path) -> None:
    # About 3 steps a metre of its passage; a file that names none gets the default.
    for cave in chains.values():
        assert 2.5 <= cave.step_budget / cave.passage_length_m <= 3.5
    assert load_scenario_file(chain_file(tmp_path, TWO_PIECES)).step_budget is None


@pytest.mark.parametrize("name", CHAINS)
def test_consecutive_tiles_of_a_shipped_chain_meet_portal_to_portal(tiles, name: str) -> None:
    """Every piece but the first meets an earlier piece rim to rim: the same centre and
    size, facing each other, so there is no step for the vehicle to hit."""
    files = {
        "cave_straight_20m.dae": "straight",
        "cave_L_20m.dae": "L",
        "cave_3way_20m.dae": "3way",
    }
    placed = []
    for piece in tomllib.loads((EXAMPLES / f"{name}.toml").read_text())["mesh"]:
        mesh = tiles[files[Path(piece["path"]).name]]
        placed.append(
            open_portals(place_mesh(mesh, piece.get("offset", (0, 0, 0)), piece.get("yaw_deg", 0)))
        )
    for k, portals in enumerate(placed[1:], start=1):
        earlier = [p for ps in placed[:k] for p in ps]
        pairs = [
            (a, b)
            for a in portals
            for b in earlier
            if np.linalg.norm(a.centre - b.centre) < 0.02 and a.normal @ b.normal < -0.999
        ]
        assert len(pairs) == 1, f"piece {k} of {name} meets {len(pairs)} earlier portals"
        ((a, b),) = pairs
        assert abs(a.radius - b.radius) < 0.03


@pytest.mark.parametrize("name", CHAINS)
def test_a_shipped_chain_is_open_only_at_its_entrances_and_exits(chains, name: str) -> None:
    scenario = chains[name]
    ends = open_portals(scenario.mesh)
    assert len(ends) == len(scenario.entrances) + len(scenario.exits)
    for portal in (*scenario.entrances, *scenario.exits):
        assert portal_at(ends, portal.point).normal == pytest.approx(portal.normal, abs=0.01)


@pytest.mark.parametrize("name", CHAINS)
def test_a_shipped_chain_is_flyable_along_its_centre_line(chains, name: str) -> None:
    scenario = chains[name]
    caster = RayCaster(scenario.mesh)
    validate_start(scenario, caster, VehicleBody())
    line = scenario.centreline
    assert line is not None
    dense = np.concatenate(
        [np.linspace(a, b, 20) for a, b in zip(line[:-1], line[1:], strict=True)]
    )
    assert caster.distance(dense).min() >= 1.0  # a metre of room all the way
    assert scenario.exited(line[-1] + 0.1 * np.asarray(scenario.exits[0].normal))
    assert not scenario.exited(scenario.start.position)


# ------------------------------------------------------------------ entrances


def test_leaving_by_the_entrance_is_told_apart_from_exiting() -> None:
    scenario = load_scenario_file(EXAMPLES / "osrf_cave_straight.toml")
    (entrance,) = scenario.entrances
    assert entrance == ExitPortal((0.0, 10.0, 2.0), (0.0, 1.0, 0.0), 3.5)
    assert not scenario.left_through_entrance(scenario.start.position)
    assert scenario.left_through_entrance(np.array([0.0, 10.2, 2.0]))
    assert not scenario.exited(np.array([0.0, 10.2, 2.0]))
    assert not scenario.left_through_entrance(np.array([0.0, -10.2, 2.0]))  # the exit
    assert not scenario.left_through_entrance(np.array([5.0, 10.2, 2.0]))  # beside the disc


def test_entrances_come_as_one_table_or_a_list(chains) -> None:
    junction = chains["osrf_chain_junction"]
    assert [e.point for e in junction.entrances] == [(0.0, 10.0, 2.0), (-30.0, -20.0, 2.0)]
    assert junction.left_through_entrance(np.array([-30.5, -20.0, 2.0]))  # the side branch


def test_an_entrance_is_validated_like_an_exit(tmp_path: Path) -> None:
    bad = "[entrance]\npoint = [0.0, 10.0, 2.0]\nnormal = [0.0, 0.0, 0.0]\nradius = 3.5\n"
    path = chain_file(tmp_path, f'mesh = "{STRAIGHT}"\n{bad}')
    with pytest.raises(ConfigError, match="field 'entrance.normal': .*entrance normal"):
        load_scenario_file(path)


def test_a_cave_without_entrances_is_never_left_through_one(room_scenario: Scenario) -> None:
    assert room_scenario.entrances == ()
    assert not room_scenario.left_through_entrance(np.array([0.0, 50.0, 0.0]))


# ------------------------------------------------------------------ centre lines


def test_a_centre_line_from_the_file_measures_progress_along_it(tmp_path: Path) -> None:
    line = "centreline = [[0.0, 10.0, 2.0], [0.0, -10.0, 2.0]]"
    scenario = load_scenario_file(chain_file(tmp_path, f'mesh = "{STRAIGHT}"', line))
    assert scenario.centreline == pytest.approx(np.array([[0, 10, 2], [0, -10, 2.0]]))
    assert scenario.passage_length_m == pytest.approx(18.5)  # from the start at y = 8.5
    assert scenario.progress(np.array([1.0, 0.0, 2.5])) == pytest.approx(8.5)


def test_progress_along_a_chain_counts_the_way_round_its_bends(chains) -> None:
    zigzag = chains["osrf_chain_zigzag"]
    after_both_bends = np.array([20.0, -30.0, 2.0])
    # Only 38.5 m nearer the exit plane (y = -50) than the start (y = 8.5), but 10 m of
    # the way ran along x between the bends: round them it is about 50 m.
    assert zigzag.progress(after_both_bends) == pytest.approx(50.0, abs=2.0)
    assert zigzag.progress(np.array(zigzag.exits[0].point)) == pytest.approx(
        zigzag.passage_length_m
    )
    assert zigzag.passage_length_m > 70.0
