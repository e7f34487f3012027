"""A map of the cave made only of what the vehicle saw: free space, surfaces, the path flown.

Each depth image is placed by dead reckoning on the actions the vehicle executed (never
the mesh, never the true pose; `cavenav.safety.reckoning`, as the safety shield's memory is) and
carved into a voxel grid: the cells a camera ray crossed count as seen free, the cell
where it met a surface as seen occupied. With the path flown, that is enough to tell a
way the vehicle came from a new one, to find openings it passed that are out of view
now, and to draw a top-down picture of what is known for a VLM pilot (``--map-image``).

It is a plain structure read by whoever needs it: the geometric pilot steers by it, the
VLM pilot can be shown its picture, and it reads the same observations the safety shield
does, so it works the same on a real vehicle (where dead reckoning drifts; the map's
cells are coarse for that reason).

Map frame: the vehicle's centre at the first observation is the origin, x its heading
then, y to its left, z up; metres. Body frame: (forward, left, up) from the centre.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

from cavenav.core.types import Action, Observation
from cavenav.safety.reckoning import DepthSamples, reckon, sampling_stride, to_body, to_map

__all__ = ["FREE", "OCCUPIED", "UNKNOWN", "CaveMap", "MapConfig", "Opening"]

UNKNOWN, FREE, OCCUPIED = 0, 1, 2


@dataclass(frozen=True)
class MapConfig:
    """Numbers of the map.

    Attributes:
        voxel_m: cell size; 0.4 m is finer than any passage the vehicle fits through and
            coarse enough that a few centimetres of dead-reckoning drift do not matter.
        max_range_m: depth beyond this carves free space up to here, but no surface.
        columns: rays per image row carved into the map (about 48 over a 53-degree view:
            one every 1.1 degrees, a cell apart at 20 m).
        visited_m: a point this close to the path flown counts as visited.
        recent_m: the last metres of the path are where the vehicle is, not where it has
            been: they do not make a point visited.
    """

    voxel_m: float = 0.4
    max_range_m: float = 16.0
    columns: int = 48
    visited_m: float = 2.0
    recent_m: float = 3.0


@dataclass(frozen=True)
class Opening:
    """A horizontal direction in which the map shows free space reaching far.

    Attributes:
        bearing_deg: relative to the current heading, left positive.
        free_m: how far the free space was seen to reach along it.
        visited: whether its far end lies on the path flown (the way back).
        end: (x, y, z) map-frame point where the free run ended.
    """

    bearing_deg: float
    free_m: float
    visited: bool
    end: tuple[float, float, float]


@numba.njit(cache=True, nogil=True)
def _carve(
    hits: np.ndarray,  # (X, Y, Z) uint16 times a surface was seen in each cell
    passes: np.ndarray,  # (X, Y, Z) uint16 times a ray crossed each cell free
    start: np.ndarray,  # (3,) float64 the camera, in cell units from the grid's corner
    ends: np.ndarray,  # (n, 3) float64 where each ray stops, in cell units
    surface: np.ndarray,  # (n,) bool whether the ray met a surface there
) -> None:
    """Count every cell each ray crossed free (short of its end by half a cell) and the
    cell of each surface met: one pass, no temporaries."""
    nx, ny, nz = hits.shape
    for i in range(ends.shape[0]):
        dx, dy, dz = ends[i, 0] - start[0], ends[i, 1] - start[1], ends[i, 2] - start[2]
        length = math.sqrt(dx * dx + dy * dy + dz * dz)
        samples = int(2.0 * length)
        lx, ly, lz = -1, -1, -1
        for k in range(samples):
            t = (k + 0.5) / (2.0 * length) if length > 0 else 0.0
            if t * length > length - 0.5:
                break
            cx = int(math.floor(start[0] + t * dx))
            cy = int(math.floor(start[1] + t * dy))
            cz = int(math.floor(start[2] + t * dz))
            if (cx, cy, cz) == (lx, ly, lz):
                continue
            lx, ly, lz = cx, cy, cz
            if 0 <= cx < nx and 0 <= cy < ny and 0 <= cz < nz and passes[cx, cy, cz] < 65535:
                passes[cx, cy, cz] += 1
        if surface[i]:
            cx, cy, cz = (
                int(math.floor(ends[i, 0])),
                int(math.floor(ends[i, 1])),
                int(math.floor(ends[i, 2])),
            )
            if 0 <= cx < nx and 0 <= cy < ny and 0 <= cz < nz and hits[cx, cy, cz] < 65535:
                hits[cx, cy, cz] += 1


class CaveMap:
    """Dead-reckoned pose, voxel grid and path; see the module docstring."""

    def __init__(self, config: MapConfig | None = None):
        self.config = config or MapConfig()
        sampling_stride(640, None, self.config.columns)  # refuse a bad setting here
        self.reset()

    def reset(self) -> None:
        self.position = np.zeros(3)  # the vehicle's centre, map frame
        self.heading = 0.0  # radians from the map's x axis, left positive
        self.path: list[np.ndarray] = []  # centre positions at every observation
        self.travelled_m = 0.0
        self._corner = np.full(3, -16)  # grid index of the cell at the arrays' [0, 0, 0]
        self.hits = np.zeros((32, 32, 32), np.uint16)
        self.passes = np.zeros((32, 32, 32), np.uint16)
        self._started = False
        self._old = np.empty((0, 3))  # the path flown, less its last metres

    # ------------------------------------------------------------------ building
    def update(self, observation: Observation, moved_by: Action | None) -> None:
        """Move by the action executed since the last observation, then carve its depth."""
        if self._started and moved_by is not None:
            self.move(moved_by)
        self._started = True
        self.path.append(self.position.copy())
        self._old = self._old_path()
        if observation.has_depth:
            self._carve(observation)

    def move(self, action: Action) -> None:
        """Dead reckoning of SPEC section 5 in the map frame: turn, then translate."""
        before = self.position
        self.position, self.heading = reckon(self.position, self.heading, action)
        self.travelled_m += float(np.linalg.norm(self.position - before))

    def _carve(self, obs: Observation) -> None:
        s = sampling_stride(
            obs.depth_png.shape[1], None, self.config.columns, obs.depth_png.shape[0]
        )
        # One ray through the middle of every s x s block, carved as far as it reaches.
        seen = DepthSamples.of(obs, s, first=s // 2, dtype=np.float64)
        reach = np.minimum(seen.depth, self.config.max_range_m).astype(np.float64)
        surface = seen.surface & (seen.depth <= self.config.max_range_m)
        camera = np.array([obs.camera_offset_m, 0.0, 0.0])
        ranged = seen.ranged.reshape(-1)  # a guess is neither rock nor free water
        ends = seen.points(reach, ahead_m=obs.camera_offset_m).reshape(-1, 3)[ranged]
        surface = surface.reshape(-1)[ranged]
        # The sounders: free up to the ceiling and the floor, and a surface at each (a
        # reading that is not a number says nothing).
        sounded = np.array([[0.0, 0.0, obs.d_top], [0.0, 0.0, -obs.d_bottom]])
        sounded = sounded[np.isfinite(sounded[:, 2])]
        sounded_surface = np.abs(sounded[:, 2]) <= self.config.max_range_m
        sounded[:, 2] = np.clip(sounded[:, 2], -self.config.max_range_m, self.config.max_range_m)
        for origin, targets, met in (
            (camera, ends, surface),
            (np.zeros(3), sounded, sounded_surface),
        ):
            start = self._cells(self.to_map(origin[None]))
            stops = self._cells(self.to_map(targets))
            self._fit(np.vstack([start, stops]))
            corner = self._corner.astype(np.float64)
            _carve(self.hits, self.passes, start[0] - corner, stops - corner, met)

    def _cells(self, points: np.ndarray) -> np.ndarray:
        """Map-frame points in cell units (floor gives the cell's index)."""
        return np.asarray(points, np.float64) / self.config.voxel_m

    def _fit(self, cells: np.ndarray) -> None:
        """Grow the arrays (by at least 16 cells a side) until they hold ``cells``."""
        lo = np.floor(cells.min(axis=0)).astype(int) - 1
        hi = np.floor(cells.max(axis=0)).astype(int) + 2
        shape = np.array(self.hits.shape)
        below = np.maximum(self._corner - lo, 0)
        above = np.maximum(hi - (self._corner + shape), 0)
        if not (below.any() or above.any()):
            return
        below = np.where(below > 0, np.maximum(below, 16), 0)
        above = np.where(above > 0, np.maximum(above, 16), 0)
        pad = tuple(zip(below.tolist(), above.tolist(), strict=True))
        self.hits = np.pad(self.hits, pad)
        self.passes = np.pad(self.passes, pad)
        self._corner = self._corner - below

    # ------------------------------------------------------------------ reading
    def to_map(self, body_points: np.ndarray) -> np.ndarray:
        """(n, 3) body-frame points (forward, left, up) in the map frame."""
        return to_map(body_points, self.position, self.heading)

    def to_body(self, map_points: np.ndarray) -> np.ndarray:
        """(n, 3) map-frame points in the current body frame."""
        return to_body(map_points, self.position, self.heading)

    def state(self, map_points: np.ndarray) -> np.ndarray:
        """(n,) UNKNOWN, FREE or OCCUPIED for the cell of each map-frame point.

        A cell is occupied once a surface was seen in it at least a quarter as often as
        rays crossed it free (a wall seen from afar is grazed by rays to nearer points).
        """
        idx = np.floor(self._cells(map_points)).astype(int) - self._corner
        inside = np.all((idx >= 0) & (idx < np.array(self.hits.shape)), axis=1)
        out = np.full(len(idx), UNKNOWN, np.int8)
        i, j, k = idx[inside].T
        hits, passes = self.hits[i, j, k].astype(np.int32), self.passes[i, j, k].astype(np.int32)
        out[inside] = np.where(
            (hits > 0) & (4 * hits >= passes), OCCUPIED, np.where(passes > 0, FREE, UNKNOWN)
        )
        return out

    def visited(self, map_points: np.ndarray) -> np.ndarray:
        """(n,) whether each map-frame point lies within ``visited_m`` of the path flown,
        leaving out its last ``recent_m`` (where the vehicle is now)."""
        old = self._old
        if not len(old):
            return np.zeros(len(map_points), bool)
        gap = np.linalg.norm(np.asarray(map_points)[:, None, :] - old[None], axis=2)
        return gap.min(axis=1) < self.config.visited_m

    def _old_path(self) -> np.ndarray:
        if len(self.path) < 2:
            return np.empty((0, 3))
        path = np.array(self.path)
        back = np.concatenate(
            [[0.0], np.cumsum(np.linalg.norm(np.diff(path[::-1], axis=0), axis=1))]
        )
        return path[::-1][back > self.config.recent_m]

    def openings(
        self, step_deg: float = 15.0, min_free_m: float = 4.0, reach_m: float = 12.0
    ) -> list[Opening]:
        """Horizontal directions all around that lead into space not yet seen.

        Walks the grid from the centre along each bearing, a cell up or down allowed per
        cell ahead (a passage that climbs or dips still counts), while the cells are seen
        free. A bearing is an opening when that free run reaches ``min_free_m`` and then
        meets the unknown or goes on past ``reach_m``, not a wall: the long diagonal of a
        chamber already seen is none. Directions out of view now count, as they were
        seen before.
        """
        bearings = np.radians(np.arange(-180.0, 180.0, step_deg))
        step = self.config.voxel_m
        heads = np.stack([np.cos(bearings), np.sin(bearings), np.zeros_like(bearings)], 1) * step
        points = np.zeros((len(bearings), 3))
        free = np.zeros(len(bearings))
        open_end = np.zeros(len(bearings), bool)  # the run ended in the unknown or far
        walking = np.ones(len(bearings), bool)
        rises = np.array([0.0, step, -step])
        while walking.any():
            ahead = points[walking] + heads[walking]
            tries = ahead[:, None, :] + rises[None, :, None] * np.array([0.0, 0.0, 1.0])
            states = self.state(self.to_map(tries.reshape(-1, 3))).reshape(-1, 3)
            on = (states == FREE).any(axis=1)
            moving = np.flatnonzero(walking)
            chosen = tries[np.arange(len(tries)), np.argmax(states == FREE, axis=1)]
            points[moving[on]] = chosen[on]
            free[moving[on]] += step
            stopped = moving[~on]
            open_end[stopped] = (states[~on] == UNKNOWN).all(axis=1)
            walking[stopped] = False
            far = moving[on][free[moving[on]] >= reach_m]
            open_end[far] = True
            walking[far] = False
        found = open_end & (free >= min_free_m)
        ends = self.to_map(points[found])
        return [
            Opening(round(float(np.degrees(b)), 1), round(float(f), 2), bool(v), tuple(e))
            for b, f, v, e in zip(
                bearings[found], free[found], self.visited(ends), ends.tolist(), strict=True
            )
        ]

    # ------------------------------------------------------------------ picture
    def top_down(self, pixels: int = 256, span_m: float = 32.0) -> np.ndarray:
        """(pixels, pixels, 3) uint8 picture centred on the vehicle, heading up.

        Within 1.5 m of the vehicle's height: space seen free light (wherever some of the
        band was), surfaces seen dark, the unknown mid-grey, the path flown red, the
        vehicle a blue wedge pointing up.
        """
        half = span_m / 2
        metres = (np.arange(pixels) + 0.5) / pixels * span_m - half
        ahead, left = np.meshgrid(-metres, -metres, indexing="ij")  # rows: ahead on top
        seen_free = np.zeros((pixels, pixels), bool)
        seen_rock = np.zeros((pixels, pixels), bool)
        for dz in np.arange(-1.5, 1.51, self.config.voxel_m):
            body = np.stack([ahead.ravel(), left.ravel(), np.full(ahead.size, dz)], axis=1)
            state = self.state(self.to_map(body)).reshape(pixels, pixels)
            seen_free |= state == FREE
            seen_rock |= state == OCCUPIED
        # Free anywhere in the band wins: a low ceiling over a passage is no wall.
        image = np.full((pixels, pixels, 3), 128, np.uint8)
        image[seen_rock] = (40, 40, 40)
        image[seen_free] = (235, 235, 225)
        scale = pixels / span_m
        for point in self.to_body(np.array(self.path)) if self.path else ():
            row, col = int((half - point[0]) * scale), int((half - point[1]) * scale)
            if 0 <= row < pixels and 0 <= col < pixels:
                image[max(row - 1, 0) : row + 2, max(col - 1, 0) : col + 2] = (210, 30, 30)
        centre = pixels // 2
        for k in range(int(0.6 * scale)):  # the vehicle: a wedge, its point ahead
            width = k // 2
            image[centre - int(0.6 * scale) + k, centre - width : centre + width + 1] = (
                30,
                80,
                220,
            )
        return image

    def describe(self) -> str:
        """One line for a prompt: distance flown and the openings known, new or not."""
        openings = self.openings()
        new = sorted((o for o in openings if not o.visited), key=lambda o: abs(o.bearing_deg))
        words = ", ".join(f"{_side(o.bearing_deg)} ({o.free_m:.0f} m)" for o in new[:4])
        return (
            f"Flown {self.travelled_m:.1f} m. Unexplored openings seen: {words or 'none'}; "
            f"{len(openings) - len(new)} directions lead back along the path flown."
        )


def _side(bearing: float) -> str:
    if abs(bearing) < 1:
        return "ahead"
    if abs(bearing) >= 179:
        return "behind"
    return f"{abs(bearing):.0f} deg {'left' if bearing > 0 else 'right'}"
