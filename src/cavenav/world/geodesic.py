"""The shortest way out: a geodesic through a cave's free space, for SPL.

SPL (success weighted by path length, Anderson et al. 2018) divides the shortest path
from the start to the goal by the path flown. A straight line to the exit would flatter
every pilot in a winding cave, and the centre line is longer than the inside of a bend:
the shortest path is measured through the free space the vehicle fits in.

How: voxels whose centres lie at least the vehicle's bounding radius from every surface
are free; Dijkstra over them (26 neighbours, scipy) from the start to the nearest voxel
past an exit portal gives the route, and pulling it taut (each corner dropped where the
straight segment past it keeps the same clearance) removes the grid's staircase, so the
length is that of a real path, not of voxel steps. A grid too coarse for the narrowest
gap finds no path, and says so.
"""

from __future__ import annotations

import math
import weakref
from dataclasses import dataclass

import numpy as np

from cavenav.core.errors import CavenavError
from cavenav.core.types import VehicleBody
from cavenav.world.raycast import RayCaster
from cavenav.world.scenario import ExitPortal, Scenario

__all__ = ["Geodesic", "NoPath", "shortest_path", "shortest_path_of"]

# The voxel, and the most voxels a cave may take: a voxel must stay smaller than the
# band of 2 radii around every wall that no free voxel enters, or a step could cross it.
VOXEL_M = 0.4
MOST_VOXELS = 3_000_000


class NoPath(CavenavError):
    """No path of free voxels joins the start to an exit (or the grid is too coarse)."""


@dataclass(frozen=True)
class Geodesic:
    """The shortest path from the start to the first exit plane it crosses.

    Attributes:
        length_m: its length in metres, up to the exit plane.
        points: (n, 3) its corners, from the start position to the crossing.
        voxel_m: the grid it was found on.
    """

    length_m: float
    points: np.ndarray
    voxel_m: float


def _past(portals: tuple[ExitPortal, ...], points: np.ndarray) -> np.ndarray:
    """Which ``points`` (n, 3) lie past any of ``portals`` (`ExitPortal.passed`)."""
    past = np.zeros(len(points), bool)
    for portal in portals:
        past |= portal.passed(points)
    return past


def _grid(scenario: Scenario, voxel: float) -> tuple[np.ndarray, tuple[int, int, int]]:
    """The grid's origin and shape: the mesh's bounds and a voxel's margin.

    Raises:
        NoPath: the cave needs more than `MOST_VOXELS`.
    """
    low, high = scenario.mesh.bounds
    low, high = low - voxel, high + voxel
    shape = tuple(int(n) for n in np.ceil((high - low) / voxel).astype(int))
    if math.prod(shape) > MOST_VOXELS:
        raise NoPath(
            f"{scenario.name}: {math.prod(shape):,} voxels of {voxel} m, more than the "
            f"{MOST_VOXELS:,} a shortest path is sought in"
        )
    return low, shape  # type: ignore[return-value]


def _shifted(free: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """``free`` at each voxel plus ``offset`` (False past the grid's edge)."""
    out = np.zeros_like(free)
    source = tuple(slice(max(o, 0), n + min(o, 0)) for n, o in zip(free.shape, offset, strict=True))
    target = tuple(
        slice(max(-o, 0), n - max(o, 0)) for n, o in zip(free.shape, offset, strict=True)
    )
    out[target] = free[source]
    return out


def _graph(free: np.ndarray, voxel: float):  # noqa: ANN202 - a scipy sparse matrix
    """The free voxels' adjacency: each joined to its free 26 neighbours by the distance
    between their centres, a diagonal step only where every voxel of the block it
    crosses is free too (no cutting a corner, so no step across a wall)."""
    from scipy.sparse import coo_matrix

    index = np.full(free.shape, -1, np.int64)
    index[free] = np.arange(int(free.sum()))
    rows, columns, weights = [], [], []
    for step in np.ndindex(3, 3, 3):
        offset = np.array(step) - 1
        if tuple(offset) <= (0, 0, 0):  # each pair once; the graph is symmetric
            continue
        # The block from a voxel to its neighbour: its other corners, each shift once
        # (a step along one axis has one, across a face's diagonal three).
        corners = {tuple(np.array(corner) * offset) for corner in np.ndindex(2, 2, 2)}
        joined = free.copy()
        for corner in corners - {(0, 0, 0)}:
            joined &= _shifted(free, np.array(corner))
        rows.append(index[joined])
        columns.append(index[tuple(np.nonzero(joined) + offset[:, None])])
        weights.append(np.full(int(joined.sum()), voxel * float(np.linalg.norm(offset))))
    n = int(free.sum())
    i, j, w = (np.concatenate(a) for a in (rows, columns, weights))
    return coo_matrix((w, (i, j)), shape=(n, n)).tocsr()


def _clear(caster: RayCaster, a: np.ndarray, b: np.ndarray, radius: float, spacing: float) -> bool:
    samples = max(int(math.ceil(float(np.linalg.norm(b - a)) / spacing)), 1)
    points = a + np.linspace(0.0, 1.0, samples + 1)[:, None] * (b - a)
    return bool((caster.distance(points) >= radius).all())


def _taut(caster: RayCaster, route: np.ndarray, radius: float, spacing: float) -> np.ndarray:
    """``route`` with the corners dropped that a straight, equally clear segment skips:
    from each kept point, on to the farthest point found in plain view (a doubling then
    bisecting search, a few clearance checks per corner, not one per point)."""
    kept, k, last = [route[0]], 0, len(route) - 1
    while k < last:
        reach, step = k + 1, 1
        while reach + step <= last and _clear(
            caster, route[k], route[reach + step], radius, spacing
        ):
            reach, step = reach + step, step * 2
        while step > 1:
            step //= 2
            ahead = reach + step
            if ahead <= last and _clear(caster, route[k], route[ahead], radius, spacing):
                reach = ahead
        kept.append(route[reach])
        k = reach
    return np.array(kept)


def _free(caster: RayCaster, centres: np.ndarray, shape: tuple, voxel: float, radius: float):  # noqa: ANN202
    """Which voxel ``centres`` lie ``radius`` or more from every surface.

    The distance moves no faster than the point, so a voxel near the centre of a block of
    3 x 3 x 3 whose centre is far from the walls (or deep inside them) is decided by the
    block's one distance; only the voxels of blocks near a wall are measured one by one.
    """
    grid = centres.reshape(*shape, 3)
    blocks = grid[1::3, 1::3, 1::3]
    near = caster.distance(blocks)
    reach = voxel * math.sqrt(3.0)  # from a block's centre to its farthest voxel

    def spread(decided: np.ndarray) -> np.ndarray:
        return np.repeat(np.repeat(np.repeat(decided, 3, 0), 3, 1), 3, 2)

    covered = tuple(slice(0, min(3 * b, n)) for b, n in zip(blocks.shape, shape, strict=False))
    free, measure = np.zeros(shape, bool), np.ones(shape, bool)  # past the blocks: measured
    free[covered] = spread(near >= radius + reach)[covered]
    measure[covered] = spread(np.abs(near - radius) <= reach)[covered]
    free[measure] = caster.distance(grid[measure]) >= radius
    return free.reshape(-1)


def _to_exit_plane(points: np.ndarray, exits: tuple[ExitPortal, ...]) -> np.ndarray:
    """``points`` cut where the last segment crosses the plane of the exit it reaches."""
    a, b = points[-2], points[-1]
    portal = min(exits, key=lambda p: abs(p.distance(b)))
    before, after = portal.distance(a), portal.distance(b)
    if before > 0.0 >= after:
        return np.vstack([points[:-1], a + before / (before - after) * (b - a)])
    return points


def shortest_path(
    scenario: Scenario,
    caster: RayCaster | None = None,
    radius_m: float = VehicleBody().bounding_radius,
    voxel_m: float = VOXEL_M,
) -> Geodesic:
    """The shortest path from ``scenario``'s start past one of its exits, keeping
    ``radius_m`` from every surface (the vehicle's bounding sphere by default).

    Raises:
        NoPath: the start is not free, or no free voxel past an exit joins it.
    """
    from scipy.sparse.csgraph import dijkstra

    if voxel_m >= 2 * radius_m:
        raise ValueError(f"a voxel of {voxel_m} m could step across a wall: keep it under 2 radii")
    caster, voxel = caster or RayCaster(scenario.mesh), voxel_m
    low, shape = _grid(scenario, voxel)
    axes = [low[k] + (np.arange(shape[k]) + 0.5) * voxel for k in range(3)]
    centres = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    free = _free(caster, centres, shape, voxel, radius_m)
    free &= ~_past(scenario.entrances, centres)  # out the way it came in is no way out
    start = np.asarray(scenario.start.position, np.float64)
    reach = np.linalg.norm(centres - start, axis=1)
    nearest = np.argpartition(reach, 26)[:27] if len(reach) > 27 else np.arange(len(reach))
    seed = next((int(k) for k in nearest[np.argsort(reach[nearest])] if free[k]), None)
    if seed is None:
        raise NoPath(f"{scenario.name}: no free voxel ({voxel:.2f} m) beside the start")
    graph = _graph(free.reshape(shape), voxel)
    node = int(np.count_nonzero(free[:seed]))  # its number among the free voxels
    distances, previous = dijkstra(graph, directed=False, indices=node, return_predecessors=True)
    free_centres = centres[free]
    goals = np.flatnonzero(_past(scenario.exits, free_centres) & np.isfinite(distances))
    if not len(goals):
        raise NoPath(f"{scenario.name}: no free path ({voxel:.2f} m voxels) reaches an exit")
    node, backwards = int(goals[np.argmin(distances[goals])]), []
    while node >= 0:
        backwards.append(free_centres[node])
        node = int(previous[node])
    route = np.vstack([start, *backwards[::-1]])
    points = _to_exit_plane(_taut(caster, route, radius_m, voxel / 4), scenario.exits)
    length = float(np.linalg.norm(np.diff(points, axis=0), axis=1).sum())
    return Geodesic(round(length, 4), points, voxel)


# Each cave's shortest path, or why there is none (asked again at every summary written).
_FOUND: weakref.WeakKeyDictionary[Scenario, Geodesic | NoPath] = weakref.WeakKeyDictionary()


def shortest_path_of(scenario: Scenario) -> Geodesic:
    """`shortest_path` of ``scenario``, found once per cave object (a sweep's worker keeps
    its caves, and a cave's every success needs it): on voxels of `VOXEL_M`, or of half
    that where a passage too narrow for them left no way (a 1 m squeeze can hold no
    voxel centre 0.31 m from both walls on a 0.4 m grid).

    Raises:
        NoPath: no way on either grid.
    """
    if scenario not in _FOUND:
        try:
            _FOUND[scenario] = shortest_path(scenario)
        except NoPath:
            try:
                _FOUND[scenario] = shortest_path(scenario, voxel_m=VOXEL_M / 2)
            except NoPath as none:
                _FOUND[scenario] = none
    found = _FOUND[scenario]
    if isinstance(found, NoPath):
        raise NoPath(str(found))  # a fresh one: the kept one's traceback would only grow
    return found
