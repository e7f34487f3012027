"""Breakdown that fell: every block of rock comes to rest on the floor or on the blocks
under it, over what holds it, partly buried where the floor is silt (issue 49)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import Delaunay

from cavenav.world.morphology import BLOCK_CONTACT, SILT_BURIAL, Boulder, settle_block
from cavenav.world.procedural import build_cave, settled_blocks
from cavenav.world.scenarios import SCENARIOS

Z = np.arange(-2.0, 3.01, 0.05)  # heights of the synthetic columns below


def _columns(floor: np.ndarray) -> np.ndarray:
    """(n, len(Z)) field of rock under each column's ``floor`` height, water above."""
    return floor[:, None] - Z[None, :]


def _grid(half: float = 2.0, step: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    x, y = np.meshgrid(np.arange(-half, half, step), np.arange(-half, half, step))
    return x.ravel(), y.ravel()


def _lowest(block: Boulder) -> float:
    x, y = _grid(3.0, 0.02)
    bottom, top = block.heights(x, y)  # offsets from its centre
    return float(block.centre[2] + bottom[bottom <= top].min())


def test_a_block_dropped_over_flat_rock_comes_to_rest_on_it() -> None:
    x, y = _grid()
    block = Boulder((0.1, -0.2, 2.0), (0.8, 0.6, 0.5), angular=11)
    rested, contact = settle_block(block, x, y, Z, _columns(np.zeros_like(x)), None)
    assert rested.centre[:2] == block.centre[:2]
    assert -0.1 < _lowest(rested) <= 0.0  # on the rock, sunk by no more than a tilt's worth
    under = block.heights(x - 0.1, y + 0.2)
    assert len(contact) >= BLOCK_CONTACT * np.sum(under[0] <= under[1]) - 1
    assert Delaunay(contact).find_simplex(np.array([[0.1, -0.2]]))[0] >= 0


def test_a_block_on_a_slope_sinks_until_its_centre_lies_over_what_holds_it() -> None:
    x, y = _grid()
    block = Boulder((0.0, 0.0, 2.0), (0.8, 0.8, 0.4), angular=3)
    rested, contact = settle_block(block, x, y, Z, _columns(0.4 * x), None)  # rising to +x
    assert contact[:, 0].min() < 0.0 < contact[:, 0].max()  # held on both sides of its centre
    assert Delaunay(contact).find_simplex(np.array([[0.0, 0.0]]))[0] >= 0


def test_a_block_that_falls_into_silt_is_partly_buried() -> None:
    x, y = _grid()
    block = Boulder((0.0, 0.0, 2.0), (0.8, 0.7, 0.5), angular=5)
    rock = _columns(np.zeros_like(x))
    on_rock, _ = settle_block(block, x, y, Z, rock, None)
    in_silt, _ = settle_block(block, x, y, Z, rock, np.ones_like(rock, bool))
    height = 2 * 0.9 * 0.5 * np.array(SILT_BURIAL)
    sunk = on_rock.centre[2] - in_silt.centre[2]
    assert 0.8 * height[0] < sunk < 1.3 * height[1]


def test_a_block_with_only_wall_beneath_it_stays_where_it_was() -> None:
    x, y = _grid()
    block = Boulder((0.0, 0.0, 0.0), (0.5, 0.5, 0.5), angular=2)
    rested, contact = settle_block(block, x, y, Z, _columns(np.full_like(x, 10.0)), None)
    assert rested == block and len(contact) == 0


FALLEN = [("S3", 0), ("S3", 1), ("S5", 0), ("S5", 3)]


@pytest.mark.parametrize(("name", "seed"), FALLEN)
def test_every_block_rests_with_its_centre_over_what_holds_it(name: str, seed: int) -> None:
    for block, contact in settled_blocks(SCENARIOS[name].layout(seed).spec):
        assert len(contact) >= 3, block
        assert Delaunay(contact).find_simplex(np.array([block.centre[:2]]))[0] >= 0, block


@pytest.mark.parametrize(("name", "seed"), FALLEN)
def test_no_block_floats(name: str, seed: int) -> None:
    """Most of each block's faces are one surface with the cave's walls: a block that
    touched neither the floor nor another block would be a surface of its own. (A few
    may close a pocket of water trapped under it, a surface of its own that no ray from
    the passage reaches.)"""
    spec = SCENARIOS[name].layout(seed).spec
    mesh = build_cave(spec, name=f"{name}-seed{seed}")
    faces = mesh.faces
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]]])
    graph = coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), (len(mesh.vertices),) * 2)
    _, label = connected_components(graph, directed=False)
    cave = np.argmax(np.bincount(label[faces.ravel()]))
    for block, _ in settled_blocks(spec):
        near = np.linalg.norm(mesh.vertices - block.centre, axis=1) < block.reach + 0.3
        on_block = near & (np.abs(block.field(mesh.vertices.astype(np.float64))) < 0.05)
        assert on_block.sum() > 20, block  # the block shows
        assert np.mean(label[on_block] == cave) > 0.5, block


@pytest.mark.parametrize("name", ["S3", "S5", "long"])
def test_blocks_are_angular_and_0_2_to_3_m_across(name: str) -> None:
    spec = SCENARIOS[name].layout(2).spec
    blocks = (*spec.boulders, *spec.breakdown)
    assert blocks and all(b.angular is not None for b in blocks)
    edges = np.array([2 * 0.9 * np.asarray(b.radii) for b in blocks])
    assert edges.min() >= 0.2 and edges.max() <= 3.0


def test_blocks_on_a_silted_floor_are_partly_buried_in_it() -> None:
    """S3's floor is silted 0.5 m deep over rock 3 m under the axis: its top lies 2.5 m
    under the axis, give or take its 4 cm ripples, 4 m across. (Toward the walls the
    rock rises out of it.)"""
    for seed in (0, 1, 2):
        blocks = [block for block, _ in settled_blocks(SCENARIOS["S3"].layout(seed).spec)]
        middle = [b for b in blocks if abs(b.centre[0]) < 1.5 and _lowest(b) < -2.0]
        assert middle  # the frontal pile's base, not the block on top of it
        assert all(_lowest(b) < -2.5 - 0.05 for b in middle)
