"""The harder cave families: crawl, maze and long; and the generator that meshes them."""

from __future__ import annotations

import io
import json
import math
import os
import struct
import subprocess
import sys
import warnings
import zipfile
from dataclasses import replace

import numpy as np
import pytest
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from cavenav.core.errors import CavenavWarning, ScenarioError
from cavenav.world import scenario as scenarios_module
from cavenav.world.collision import VehicleBody
from cavenav.world.mesh import CaveMesh
from cavenav.world.procedural import PassageSpec, arc_length, build_cave, rounded_corners
from cavenav.world.raycast import RayCaster
from cavenav.world.scenarios import (
    SCENARIOS,
    Difficulty,
    load_scenario,
    procedural_scenario,
    validate_start,
)

SEEDS = (0, 1, 2, 3, 1000, 1001)

# `PassageSpec.digest` of the families at more seeds, recorded when the rings went and
# the blocks fell (generator version 3, scenario set 6): a seed's cave must not move
# unless the generator's version or the scenario set says it did.
SPEC_DIGESTS = {
    ("S1", 3): "fa8ad02c468dfaff",
    ("S1", 1007): "9a6c111d6dd1eb9b",
    ("S2", 3): "14a60e9e339f2c29",
    ("S3", 1007): "55c64511085589bb",
    ("S4", 3): "ef41e86e580abdb0",
    ("S5", 1007): "51db868c98aeb158",
    ("crawl", 1000): "0e684eaf0d0f1b88",
    ("maze", 1000): "748b2dbac827970d",
    ("long", 1000): "e19e401a413902a7",
}

# numpy picks its kernels by CPU; these switch SIMD levels off for one process, as a
# machine without them would run (a level the CPU lacks is simply not used).
SIMD_LEVELS = ("", "AVX512_ICL AVX512_SKX X86_V4", "AVX512_ICL AVX512_SKX X86_V4 AVX2 FMA3 X86_V3")

# Every family's digests at two seeds, and the S1 and S5 meshes built from scratch (every
# morphology between them: scallops, silt, a ceiling half-tube, a notch, angular blocks,
# speleothems, flat roofs), as JSON.
_DIGESTS_AND_MESH = """
import hashlib, json
from cavenav.world.scenarios import SCENARIOS, load_scenario
digests = {name: [SCENARIOS[name].layout(seed).spec.digest() for seed in (0, 1007)]
           for name in SCENARIOS}
meshes = [load_scenario(name, seed=0).mesh for name in ("S1", "S5")]
mesh_hash = [hashlib.sha256(m.vertices.tobytes() + m.faces.tobytes()).hexdigest() for m in meshes]
print(json.dumps({"digests": digests, "mesh": mesh_hash}))
"""


def _between_start_and_exit(layout) -> slice:
    spec = layout.spec
    start = int(np.argmin(np.linalg.norm(spec.centreline - layout.start.position, axis=1)))
    return slice(start, spec.exit_index + 1)


def _path_length(points: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(points, axis=0), axis=1).sum())


def _openings(mesh: CaveMesh) -> int:
    """Loops of edges with one face only: the holes in an otherwise closed surface."""
    faces = mesh.faces
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    unique, count = np.unique(edges, axis=0, return_counts=True)
    rim = unique[count == 1]
    if len(rim) == 0:
        return 0
    n = len(mesh.vertices)
    graph = coo_matrix((np.ones(len(rim)), (rim[:, 0], rim[:, 1])), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    return len(np.unique(label[rim[:, 0]]))


@pytest.fixture(scope="module")
def built() -> dict[str, object]:
    """Seed 0 of the crawl and the maze, meshed once for the tests that need walls."""
    return {name: load_scenario(name, seed=0) for name in ("crawl", "maze")}


# ------------------------------------------------------------------ every family


@pytest.mark.parametrize(("name", "seed"), sorted(SPEC_DIGESTS))
def test_a_seed_draws_the_cave_it_was_recorded_with(name: str, seed: int) -> None:
    assert SCENARIOS[name].layout(seed).spec.digest() == SPEC_DIGESTS[(name, seed)]


@pytest.mark.slow
def test_a_seed_builds_the_same_cave_whatever_simd_the_cpu_has(tmp_path) -> None:
    """An AVX-512 machine and an AVX2 one must draw the same cave from the same seed:
    numpy's AVX-512 ``exp`` differs in the last bits, and it used to reach the layouts
    through scipy's Gaussian filter."""
    answers = []
    for k, level in enumerate(SIMD_LEVELS):
        env = {
            **os.environ,
            "NPY_DISABLE_CPU_FEATURES": level,
            "CAVENAV_CACHE": str(tmp_path / str(k)),
        }
        done = subprocess.run(
            [sys.executable, "-c", _DIGESTS_AND_MESH], env=env, capture_output=True, text=True
        )
        assert done.returncode == 0, done.stderr
        answers.append(json.loads(done.stdout.splitlines()[-1]))
    assert answers[0]["digests"]["S1"][1] == SPEC_DIGESTS[("S1", 1007)]
    assert all(answer == answers[0] for answer in answers[1:]), [a["mesh"] for a in answers]


@pytest.mark.parametrize("name", ["crawl", "maze", "long"])
def test_the_same_seed_draws_the_same_cave_and_another_seed_another(name: str) -> None:
    family = SCENARIOS[name]
    assert family.layout(5).spec.digest() == family.layout(5).spec.digest()
    assert family.layout(5).spec.digest() != family.layout(6).spec.digest()


# A value of each knob, in every new family's range and away from its default.
HARDER = {
    "constriction_m": 2.0,
    "undulation_m": 6.0,
    "obstacle_scale": 1.2,
    "branches": 2,
    "roughness_m": 0.12,
}


@pytest.mark.parametrize(
    ("name", "knob"), [(n, k) for n in ("crawl", "maze", "long") for k in SCENARIOS[n].knobs]
)
def test_every_knob_of_the_new_families_changes_the_cave(name: str, knob: str) -> None:
    family = SCENARIOS[name]
    harder = family.layout(0, Difficulty(**{knob: HARDER[knob]}))
    assert harder.spec.digest() != family.layout(0).spec.digest()


@pytest.mark.parametrize("spelling", ["crawl", "CRAWL", "Crawl", "s1", "LONG"])
def test_families_are_found_whatever_the_case(spelling: str, monkeypatch, room) -> None:
    monkeypatch.setattr(scenarios_module, "build_cave", lambda spec, name: room)
    cave = load_scenario(spelling, seed=2)
    assert cave.name == {"crawl": "crawl", "s1": "S1", "long": "long"}[spelling.casefold()]


def test_the_spec_families_keep_the_callers_step_budget_and_the_long_ones_get_their_own(
    monkeypatch, room
) -> None:
    monkeypatch.setattr(scenarios_module, "build_cave", lambda spec, name: room)
    for name in ("S1", "S2", "S3", "S4", "S5"):
        assert procedural_scenario(name, 0).step_budget is None
    for name in ("crawl", "maze", "long"):  # room for moves well under a metre, and turns
        cave = procedural_scenario(name, 0)
        assert cave.step_budget is not None and cave.step_budget % 10 == 0
        assert cave.step_budget >= 2.5 * cave.passage_length_m, name
    assert procedural_scenario("long", 0).step_budget > 150 * 3


# ------------------------------------------------------------------ bends


def _largest_turn_deg(points: np.ndarray) -> float:
    """The largest change of heading, in degrees, from one segment of a line to the next."""
    step = np.diff(points[:, :2], axis=0)
    heading = np.unwrap(np.arctan2(step[:, 1], step[:, 0]))
    return float(np.degrees(np.abs(np.diff(heading)).max()))


@pytest.mark.parametrize(
    ("name", "bend_deg"), [("S4", 30.0), ("S4", 90.0), ("S4", 150.0), ("long", None)]
)
def test_a_sharp_bend_turns_along_an_arc_not_at_a_point(name: str, bend_deg: float | None) -> None:
    """Each section lies in its own sample's frame: a centre line that turned at a point
    gave the outer wall of the bend a straight seam where the two legs' sections met."""
    difficulty = None if bend_deg is None else Difficulty(bend_deg=bend_deg)
    layout = SCENARIOS[name].layout(0, difficulty)
    assert _largest_turn_deg(layout.spec.centreline) < 6.5  # 0.25 m along a 2.5 m radius


def test_a_rounded_corner_is_an_arc_of_the_radius_tangent_to_both_legs() -> None:
    corners = np.array([[0.0, 10.0, 0.0], [0.0, 0.0, 0.0], [10.0, 0.0, 0.0]])
    line = rounded_corners(corners, 2.5)
    np.testing.assert_array_equal(line[[0, -1]], corners[[0, -1]])  # the legs' ends stay
    arc = line[1:-1]
    np.testing.assert_allclose(arc[[0, -1]], [[0.0, 2.5, 0.0], [2.5, 0.0, 0.0]])
    np.testing.assert_allclose(np.linalg.norm(arc[:, :2] - [2.5, 2.5], axis=1), 2.5)
    # A leg too short for the arc shortens it: it leaves the 2 m leg at its middle.
    short = rounded_corners(np.array([[0.0, 2.0, 0.0], [0.0, 0.0, 0.0], [10.0, 0.0, 0.0]]), 2.5)
    np.testing.assert_allclose(short[1], [0.0, 1.0, 0.0])
    # Straight on, nothing changes.
    straight = np.array([[0.0, 0.0, 0.0], [0.0, 5.0, 0.0], [0.0, 9.0, 0.0]])
    assert arc_length(rounded_corners(straight, 2.5))[-1] == pytest.approx(9.0)


# ------------------------------------------------------------------ crawl


@pytest.mark.parametrize("seed", SEEDS)
def test_the_crawl_is_a_winding_crawlway_too_narrow_for_a_standoff(seed: int) -> None:
    layout = SCENARIOS["crawl"].layout(seed)
    along = _between_start_and_exit(layout)
    width = 2 * layout.spec.half_width[along]
    height = 2 * layout.spec.half_height[along] - layout.spec.section.sediment[along]  # free
    assert 40.0 <= _path_length(layout.spec.centreline[along]) <= 65.0
    assert width.min() == pytest.approx(1.5, abs=0.01), "pinched to the default 1.5 m"
    assert width.max() <= 2.5, "never room for 2 m from both walls"
    assert np.mean((width >= 1.2) & (width <= 2.5)) == 1.0
    assert height.min() >= 1.5 and height.max() <= 2.2
    step = np.diff(layout.spec.centreline[along, :2], axis=0)
    heading = np.degrees(np.arctan2(step[:, 0], -step[:, 1]))  # from -y, the way out
    assert np.ptp(heading) > 25.0, "it winds"


@pytest.mark.parametrize("width", [1.0, 2.0, 2.5])
def test_constriction_m_is_the_crawls_narrowest_width(width: float) -> None:
    layout = SCENARIOS["crawl"].layout(3, Difficulty(constriction_m=width))
    assert 2 * layout.spec.half_width[_between_start_and_exit(layout)].min() == pytest.approx(
        width, abs=0.01
    )


def test_the_crawl_refuses_walls_rough_enough_to_close_it() -> None:
    with pytest.raises(ScenarioError, match=r"crawl: roughness_m=0.3 is outside \[0, 0.15\]"):
        SCENARIOS["crawl"].layout(0, Difficulty(roughness_m=0.3))


def test_the_vehicle_fits_all_along_the_crawl(built) -> None:
    cave = built["crawl"]
    caster = RayCaster(cave.mesh)
    validate_start(cave, caster, VehicleBody())
    start = int(np.argmin(np.linalg.norm(cave.centreline - cave.start.position, axis=1)))
    gaps = caster.distance(cave.centreline[start:])
    assert gaps.min() >= VehicleBody().bounding_radius + 0.15


# ------------------------------------------------------------------ maze


def _branch_angle(layout, branch) -> float:
    """Degrees between the passage's direction at a branch's junction and the branch's."""
    main = layout.spec.centreline
    j = int(np.argmin(np.linalg.norm(main - branch.centreline[0], axis=1)))
    forward = (main[j + 1] - main[j - 1])[:2]
    out = (branch.centreline[8] - branch.centreline[0])[:2]
    cosine = forward @ out / (np.linalg.norm(forward) * np.linalg.norm(out))
    return math.degrees(math.acos(np.clip(cosine, -1.0, 1.0)))


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("count", [0, 3, 4, 5])
def test_the_maze_has_the_asked_number_of_blind_branches_and_one_way_out(
    seed: int, count: int
) -> None:
    layout = SCENARIOS["maze"].layout(seed, Difficulty(branches=count))
    spec = layout.spec
    assert len(spec.branches) == count
    assert 45.0 <= _path_length(spec.centreline[_between_start_and_exit(layout)]) <= 75.0
    exit_y = spec.centreline[spec.exit_index, 1]  # the exit plane: the grid is cut past it
    main = spec.centreline
    for k, branch in enumerate(spec.branches):
        points, half_width = branch.centreline, branch.half_width[-1]
        assert 24.0 - 1.0 <= _branch_angle(layout, branch) <= 90.0 + 1.0
        assert 6.0 <= _path_length(points) <= 26.0
        # A dead end: its far end is walled off from the passage and every other branch.
        end = points[-1]
        gap_to_main = np.linalg.norm(main - end, axis=1) - spec.half_width - half_width
        assert gap_to_main.min() > 1.0, f"branch {k} runs back into the passage"
        for other in spec.branches[:k] + spec.branches[k + 1 :]:
            gap = np.linalg.norm(other.centreline - end, axis=1) - other.half_width - half_width
            assert gap.min() > 1.0, f"branch {k} meets another"
        assert points[:, 1].min() - half_width > exit_y + 1.5, "no second way out"
    if count:
        at_junction = [
            spec.half_width[np.argmin(np.linalg.norm(main - b.centreline[0], axis=1))]
            for b in spec.branches
        ]
        tempting = [b.half_width[0] >= w for b, w in zip(spec.branches, at_junction, strict=True)]
        assert sum(tempting) >= (count + 1) // 2, "every other branch as wide as the way on"
    if count in (3, 4):  # the third leaves at a shallow angle, in view from the junction
        assert _branch_angle(layout, spec.branches[2]) <= 38.0 + 1.0


def test_branches_change_the_cave_digest() -> None:
    spec = SCENARIOS["maze"].layout(0).spec
    assert replace(spec, branches=spec.branches[:-1]).digest() != spec.digest()


def test_branches_is_the_mazes_knob_alone() -> None:
    with pytest.raises(ScenarioError, match="branches does not apply to S1 .*belongs to maze"):
        SCENARIOS["S1"].layout(0, Difficulty(branches=2))
    with pytest.raises(ScenarioError, match="branches must be a whole number"):
        Difficulty(branches=2.5)


def test_a_built_maze_has_its_branches_and_a_single_opening(built) -> None:
    cave = built["maze"]
    assert _openings(cave.mesh) == 1, "the exit portal is the only hole in the walls"
    caster = RayCaster(cave.mesh)
    validate_start(cave, caster, VehicleBody())
    layout = SCENARIOS["maze"].layout(0)
    for branch in layout.spec.branches:  # water down each branch, a wall across its end
        end, way = branch.centreline[-1], branch.centreline[-1] - branch.centreline[-5]
        assert caster.distance(end[None])[0] > 0.5
        ahead = caster.first_hit(end[None], (way / np.linalg.norm(way))[None])[0]
        assert ahead < branch.half_width[-1] + 1.0
    assert cave.exit_distance(cave.start.position) > 0


# ------------------------------------------------------------------ long


def test_the_long_cave_chains_the_five_over_200_m() -> None:
    layout = SCENARIOS["long"].layout(0)
    spec = layout.spec
    along = _between_start_and_exit(layout)
    points = spec.centreline[along]
    assert _path_length(points) >= 200.0
    # Constrictions (S1, S2) to the default 3.6 m, in a passage otherwise 5.8 m or wider.
    width = 2 * spec.half_width[along]
    assert width.min() == pytest.approx(3.6, abs=0.05)
    assert np.sum(np.diff((width < 4.0).astype(int)) == 1) == 5, "five constrictions"
    # A rise and fall of about 4 m (S2).
    assert 3.6 <= np.ptp(points[: 100 * 4, 2]) <= 4.0 + 1e-9
    # Sharp 90-degree bends (S4): the heading turns by 90 degrees within a few metres, twice.
    step = np.diff(points[:, :2], axis=0)
    heading = np.unwrap(np.arctan2(step[:, 1], step[:, 0]))
    sharp = np.abs(heading[16:] - heading[:-16]) > math.radians(80)  # within 4 m
    assert np.sum(np.diff(sharp.astype(int)) == 1) == 2
    # Boulders: a frontal and a lateral one (S3), then rocks along the way back (S5).
    assert len(spec.boulders) >= 2 + 5
    # The exit runs along an axis, past the start's closed end.
    out = points[-1] - points[-5]
    assert np.abs(out / np.linalg.norm(out)).max() == pytest.approx(1.0)


def test_the_long_caves_knobs_reach_every_stretch() -> None:
    harder = SCENARIOS["long"].layout(
        1, Difficulty(constriction_m=2.4, undulation_m=6.0, obstacle_scale=1.5)
    )
    plain = SCENARIOS["long"].layout(1)
    along = _between_start_and_exit(harder)
    assert 2 * harder.spec.half_width[along].min() == pytest.approx(2.4, abs=0.05)
    assert np.ptp(harder.spec.centreline[along][:400, 2]) > np.ptp(
        plain.spec.centreline[along][:400, 2]
    )
    radii = np.array([b.radii for b in harder.spec.boulders])
    assert np.allclose(radii, 1.5 * np.array([b.radii for b in plain.spec.boulders]))


# ------------------------------------------------------------------ the mesh cache


def _small_tube() -> PassageSpec:
    """A straight 6 m tube, 2 m across, along -y: meshed in well under a second."""
    y = -np.arange(0.0, 6.01, 0.25)
    centreline = np.stack([np.zeros_like(y), y, np.zeros_like(y)], axis=1)
    ones = np.ones(len(y))
    return PassageSpec(centreline, ones, ones, exit_index=len(y) - 8, roughness=0.1, voxel=0.25)


def _break_the_compressed_stream(archive: bytes) -> bytes:
    """``archive`` (a zip) with its first member's deflate stream made invalid where it
    starts (block type 3 is reserved), the rest of the file intact."""
    with zipfile.ZipFile(io.BytesIO(archive)) as z:
        member = z.infolist()[0]
    local = member.header_offset  # its local header: 30 bytes, the name, the extra field
    name_length, extra_length = struct.unpack("<HH", archive[local + 26 : local + 30])
    start = local + 30 + name_length + extra_length
    return archive[:start] + b"\xff" + archive[start + 1 :]


DAMAGE = {
    "empty": lambda archive: b"",
    "not a zip": lambda archive: b"not a zip archive",
    "cut short": lambda archive: archive[: len(archive) // 2],
    "a byte flipped": lambda archive: archive[:-30] + bytes([archive[-30] ^ 0xFF]) + archive[-29:],
    "a broken stream": _break_the_compressed_stream,
}


@pytest.mark.parametrize("damage", DAMAGE)
def test_a_damaged_cached_cave_is_built_again_with_one_warning(
    damage: str, tmp_path, monkeypatch
) -> None:
    monkeypatch.setenv("CAVENAV_CACHE", str(tmp_path))
    fresh = build_cave(_small_tube(), "tube")
    (cached,) = tmp_path.glob("tube-*.npz")
    cached.write_bytes(DAMAGE[damage](cached.read_bytes()))
    with pytest.warns(CavenavWarning, match="is damaged.*building it again"):
        rebuilt = build_cave(_small_tube(), "tube")
    assert np.array_equal(rebuilt.vertices, fresh.vertices)
    assert np.array_equal(rebuilt.faces, fresh.faces)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the file was written again, whole
        again = build_cave(_small_tube(), "tube")
    assert np.array_equal(again.vertices, fresh.vertices)


def test_a_cache_that_cannot_be_written_still_gives_the_cave_with_one_warning(
    tmp_path, monkeypatch
) -> None:
    blocked = tmp_path / "a file, not a folder"
    blocked.write_text("")
    monkeypatch.setenv("CAVENAV_CACHE", str(blocked / "cache"))
    with pytest.warns(CavenavWarning, match="cannot keep built caves in .*CAVENAV_CACHE"):
        cave = build_cave(_small_tube(), "tube")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # said once for the folder, not for every cave
        build_cave(replace(_small_tube(), seed=1), "tube")
    monkeypatch.setenv("CAVENAV_CACHE", str(tmp_path / "cache"))
    assert np.array_equal(cave.vertices, build_cave(_small_tube(), "tube").vertices)
