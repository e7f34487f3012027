"""SPL's shortest path: through the free space the vehicle fits in, never through rock."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from cavenav.core.types import Action, Decision, Observation, Pose, VehicleBody
from cavenav.episode.loop import run_episode
from cavenav.episode.settings import EpisodeConfig
from cavenav.motion.actions import format_action
from cavenav.world import geodesic
from cavenav.world.geodesic import NoPath, shortest_path
from cavenav.world.mesh import make_mesh
from cavenav.world.raycast import RayCaster
from cavenav.world.scenario import ExitPortal, Scenario

RADIUS = VehicleBody().bounding_radius


def tube(length: float = 30.0, radius: float = 2.0) -> Scenario:
    """A closed straight tube along y: start 12 m from the middle, exit plane 12 m the
    other side, so the shortest path is 24 m."""
    cylinder = trimesh.creation.cylinder(radius=radius, height=length, sections=64)
    cylinder.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
    return Scenario(
        name="tube",
        mesh=make_mesh(cylinder.vertices, cylinder.faces, "tube"),
        start=Pose(0.0, 12.0, 0.0, 0.0),
        exits=(ExitPortal((0.0, -12.0, 0.0), (0.0, -1.0, 0.0), radius),),
    )


def test_the_shortest_path_down_a_straight_tube_is_the_straight_line():
    found = shortest_path(tube())
    assert found.length_m == pytest.approx(24.0, abs=0.01)
    assert np.allclose(found.points[0], [0.0, 12.0, 0.0])
    assert found.points[-1][1] == pytest.approx(-12.0)  # cut at the exit plane


def test_the_shortest_path_keeps_the_vehicles_radius_from_the_walls(room_scenario: Scenario):
    """In the 4 m corridor, from a start 1 m off its axis to an exit across it: a straight
    path, clear of the walls all along."""
    moved = Scenario(
        name="room",
        mesh=room_scenario.mesh,
        start=Pose(1.0, 8.0, 0.0, 0.0),
        exits=room_scenario.exits,
    )
    found = shortest_path(moved)
    assert found.length_m == pytest.approx(14.0, abs=0.01)
    caster = RayCaster(moved.mesh)
    along = found.points[0] + np.linspace(0, 1, 50)[:, None] * (found.points[-1] - found.points[0])
    assert caster.distance(along).min() >= RADIUS


def test_no_path_through_a_wall_however_thin_and_slanted():
    """A cube split by a single slanted sheet (normal (1, 1, 1)): a grid step along a
    voxel's diagonal crosses more than the band either side of the sheet (voxel centres
    0.35 m either side of it are both free), so only the rule against cutting corners
    keeps the path from stepping across."""
    cube = trimesh.creation.box(extents=(8.0, 8.0, 8.0))
    normal = np.array([1.0, 1.0, 1.0]) / np.sqrt(3.0)
    # the cube's section through its centre: a hexagon, fanned from the centre
    hexagon = [(4, -4, 0), (4, 0, -4), (0, 4, -4), (-4, 4, 0), (-4, 0, 4), (0, -4, 4)]
    sheet = np.vstack([[0.0, 0.0, 0.0], np.array(hexagon, float)])
    fan = [[0, k, k % 6 + 1] for k in range(1, 7)]
    vertices = np.vstack([cube.vertices, sheet])
    faces = np.vstack([cube.faces, np.asarray(fan) + len(cube.vertices)])
    split = Scenario(
        name="split",
        mesh=make_mesh(vertices, faces, "split"),
        start=Pose(-2.0, -2.0, -2.0, 0.0),
        exits=(ExitPortal((2.0, 2.0, 2.0), tuple(normal), 1.5),),
    )
    with pytest.raises(NoPath, match="no free path"):
        shortest_path(split)


def test_blocks_decide_the_voxels_as_one_distance_each_would(room_scenario: Scenario):
    caster = RayCaster(room_scenario.mesh)
    voxel = geodesic.VOXEL_M
    low, shape = geodesic._grid(room_scenario, voxel)
    axes = [low[k] + (np.arange(shape[k]) + 0.5) * voxel for k in range(3)]
    centres = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    fast = geodesic._free(caster, centres, shape, voxel, RADIUS)
    assert np.array_equal(fast, caster.distance(centres) >= RADIUS)
    assert 0 < fast.sum() < len(fast)


class Sequence:
    """A pilot that flies a list of actions, then holds."""

    name = "sequence"

    def __init__(self, actions: list[Action]):
        self.actions, self.k = actions, 0

    def reset(self) -> None:
        self.k = 0

    def decide(self, observation: Observation) -> Decision:
        action = self.actions[self.k] if self.k < len(self.actions) else Action()
        self.k += 1
        return Decision(action, format_action(action), "scripted")


@pytest.mark.parametrize(
    ("actions", "spl"),
    [
        ([Action(forward=1.0)] * 14, 1.0),  # 14 m straight down the corridor
        ([Action(right=1.0)] + [Action(forward=1.0)] * 14, round(14 / 15, 4)),  # a detour
    ],
)
def test_spl_is_the_shortest_path_over_the_path_flown(
    actions: list[Action], spl: float, room_scenario: Scenario
):
    result = run_episode(room_scenario, Sequence(actions), EpisodeConfig(plots=False))
    assert result.success
    assert result.summary["shortest_path_m"] == pytest.approx(14.0, abs=0.01)
    assert result.summary["spl"] == pytest.approx(spl, abs=0.001)


def test_a_failure_scores_no_spl(room_scenario: Scenario):
    result = run_episode(
        room_scenario, Sequence([Action(right=1.0)] * 3), EpisodeConfig(plots=False)
    )
    assert result.termination == "collision"
    assert result.summary["spl"] == 0.0 and result.summary.get("shortest_path_m") is None


def test_a_cave_without_a_way_out_is_searched_once(monkeypatch: pytest.MonkeyPatch):
    """A summary asks for the shortest path each time it is written: a cave with none is
    not searched again on both grids every time."""
    searched = []

    def nowhere(scenario: Scenario, voxel_m: float = geodesic.VOXEL_M) -> None:
        searched.append(voxel_m)
        raise NoPath(f"{scenario.name}: no way")

    monkeypatch.setattr(geodesic, "shortest_path", nowhere)
    cave = tube()
    for _ in range(3):
        with pytest.raises(NoPath, match="tube: no way"):
            geodesic.shortest_path_of(cave)
    assert searched == [geodesic.VOXEL_M, geodesic.VOXEL_M / 2]
