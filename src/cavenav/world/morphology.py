"""Passage morphologies: the shapes flooded caves take, as terms of the cave's signed field.

A tube of elliptical section is where every generated cave starts (`cavenav.world.procedural`);
real flooded caves depart from it in a few recurring ways, each a term here:

- `Section`, per centre-line sample, reshapes the section itself: a flat roof and floor
  (``squareness``: bedding planes and canyons), a slot below the tube (``canyon_*``: a
  keyhole), a half-tube dissolved into the ceiling, a notch undercutting one wall, a shelf
  of rock jutting from one wall (a ledge: what lies on it cannot be seen from the axis
  below it), and a sediment fill with ripples that flattens the floor.
- `carve_scallops`: the dish-shaped hollows that turbulent flow dissolves into limestone
  walls, as the cells of a jittered lattice (a Worley pattern) cut into the rock.
- `Boulder`: an ellipsoid of rock, or an angular block of breakdown (a box at any
  heading, tilted a little, its corners sheared off by random planes).
- `Speleothem`: a stalactite, stalagmite or a column's half, a vertical truncated cone.

Everything is built from +, -, *, /, sqrt, min and max, which IEEE rounds the same on
every CPU: no transcendental function runs per voxel, so a seed builds the same cave
whatever SIMD level numpy picks. The section's terms work in each sample's section
coordinates: ``a`` across (to the left), ``b`` up and ``c`` along the passage.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass, fields, replace

import numpy as np
from scipy.spatial import cKDTree

__all__ = [
    "BLOCK_CONTACT",
    "SILT_BURIAL",
    "STABLE_MARGIN_M",
    "Boulder",
    "Section",
    "Speleothem",
    "carve_scallops",
    "extent",
    "settle_block",
]

# Sediment ripples: crests across the passage every 0.9 m, 4 cm high (the long, low
# ripples of a cave's slow currents, which a 0.2 m grid can still carry).
RIPPLE_WAVELENGTH_M = 0.9
RIPPLE_AMPLITUDE_M = 0.04


@dataclass(frozen=True, eq=False)
class Section:
    """How each centre-line sample's section departs from an ellipse: (n,) arrays, one
    value per sample, metres unless said; 0 means the feature is absent there.

    Attributes:
        squareness: 0 an ellipse, 1 a superellipse of power 4 (flat roof, floor and walls
            with rounded corners): bedding planes, canyons, collapse chambers.
        canyon_width: half-width of a slot cut below the tube (a keyhole section).
        canyon_depth: how far that slot reaches below the tube's lowest point.
        ceiling_channel: radius of a half-tube dissolved into the ceiling.
        channel_offset: how far left of the axis that half-tube runs.
        notch: depth of a notch undercutting the wall, positive on the left wall and
            negative on the right.
        notch_height: height of the notch's middle, as a fraction of the half-height
            (negative: below the axis).
        ledge: how far a shelf of rock juts from the wall, positive on the left wall and
            negative on the right.
        ledge_height: height of the shelf's top, as a fraction of the half-height.
        sediment: thickness of the sediment fill over the section's lowest point; its
            flat, rippled top is the floor.
    """

    squareness: np.ndarray
    canyon_width: np.ndarray
    canyon_depth: np.ndarray
    ceiling_channel: np.ndarray
    channel_offset: np.ndarray
    notch: np.ndarray
    notch_height: np.ndarray
    ledge: np.ndarray
    ledge_height: np.ndarray
    sediment: np.ndarray

    @classmethod
    def plain(cls, n: int) -> Section:
        """An elliptical section at each of ``n`` samples: every feature absent."""
        return cls(*(np.zeros(n) for _ in fields(cls)))

    def arrays(self) -> tuple[np.ndarray, ...]:
        """Every attribute's array, in declaration order (for hashing)."""
        return tuple(getattr(self, f.name) for f in fields(self))

    def field(
        self,
        i: np.ndarray,
        a: np.ndarray,
        b: np.ndarray,
        c: np.ndarray,
        half_width: np.ndarray,
        half_height: np.ndarray,
        along: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray]:
        """The section's field around samples ``i`` at section coordinates (a, b, c).

        Args:
            i: (m,) sample index of each point.
            a: (m,) offset across (left), metres.
            b: (m,) offset up, metres.
            c: (m,) offset along, metres.
            half_width: (m,) the samples' half-widths.
            half_height: (m,) the samples' half-heights.
            along: (m,) arc length of each point along the passage (sample's plus c).

        Returns:
            ((m,) water field: negative in water, about the distance to the wall near it;
            (m,) sediment field: positive below the sediment's top, -inf where none).
        """
        square = self.squareness[i]
        water = _superellipse(a, b, c, half_width, half_height, square)
        for hollow in self._hollows(i, a, b, half_width, half_height, square):
            water = np.minimum(water, hollow)
        ledge = self.ledge[i]
        if np.any(ledge != 0):
            shelf = self._shelf(i, a, b, half_width, half_height, square)
            water = np.where(ledge != 0, np.maximum(water, -shelf), water)
        return water, self._sediment(i, a, b, half_width, half_height, along)

    def _hollows(self, i, a, b, half_width, half_height, square) -> Iterator[np.ndarray]:  # noqa: ANN001
        """The water the keyhole's slot, the ceiling's half-tube and the wall's notch add:
        one field each where the feature is present (inf elsewhere)."""
        width = self.canyon_width[i]
        if np.any(width > 0):
            top, bottom = -0.3 * half_height, -half_height - self.canyon_depth[i]
            slot = _box(a, b - (top + bottom) / 2, width, (top - bottom) / 2)
            yield np.where(width > 0, slot, np.inf)
        channel = self.ceiling_channel[i]
        if np.any(channel > 0):
            across, up = a - self.channel_offset[i], b - half_height
            yield np.where(channel > 0, np.sqrt(across * across + up * up) - channel, np.inf)
        notch = self.notch[i]
        if np.any(notch != 0):
            depth = np.abs(notch)
            height = self.notch_height[i] * half_height
            into = np.sign(notch) * a - extent(half_width, self.notch_height[i], square)
            high = 0.35 + 0.1 * depth  # half-height of the notch, metres
            ellipse = np.sqrt((into / np.maximum(depth, 1e-6)) ** 2 + ((b - height) / high) ** 2)
            yield np.where(notch != 0, (ellipse - 1.0) * np.minimum(depth, high), np.inf)

    def _shelf(self, i, a, b, half_width, half_height, square) -> np.ndarray:  # noqa: ANN001
        """How far outside the ledge's shelf of rock each point lies: from ``ledge`` inside
        the wall to 2 m into the rock, its top at ``ledge_height``."""
        jut = np.abs(self.ledge[i])
        top = self.ledge_height[i] * half_height
        wall = extent(half_width, self.ledge_height[i], square)
        thickness = 0.25 + 0.3 * jut  # half-thickness of the shelf, metres
        inner, outer = wall - jut, wall + 2.0
        across = np.sign(self.ledge[i]) * a - (inner + outer) / 2
        return _box(across, b - (top - thickness), (outer - inner) / 2, thickness)

    def _sediment(self, i, a, b, half_width, half_height, along) -> np.ndarray:  # noqa: ANN001
        """Positive below the sediment's rippled top, -inf where there is none."""
        fill = self.sediment[i]
        if not np.any(fill > 0):
            return np.full(len(i), -np.inf)
        # Crests across the flow, bent into gentle sinuous lines: the phase drifts with a
        # smooth triangle wave of the position (no trigonometry: see the module's notes).
        drift = along / 6.1 + 0.17 * a
        wave = np.abs(2.0 * (drift - np.floor(drift)) - 1.0)
        phase = along / RIPPLE_WAVELENGTH_M + 0.8 * wave * wave * (3.0 - 2.0 * wave)
        arch = phase - np.floor(phase)
        ripple = RIPPLE_AMPLITUDE_M * (8.0 * arch * (1.0 - arch) - 1.0)
        top = -half_height + fill + ripple
        inside = (fill > 0) & (np.abs(a) < half_width + 1.0)
        return np.where(inside, top - b, -np.inf)


def _superellipse(a, b, c, half_width, half_height, square) -> np.ndarray:  # noqa: ANN001
    """The tube's own field: about the distance outside a section between an ellipse
    (``square`` 0) and a superellipse of power 4 (1), as procedural's tube has it."""
    x, y, z = a / half_width, b / half_height, c / half_width
    ellipse = np.sqrt(x * x + y * y + z * z)
    radius = ellipse
    if np.any(square > 0):
        x2, y2, z2 = x * x, y * y, z * z
        radius = ellipse + square * (np.sqrt(np.sqrt(x2 * x2 + y2 * y2 + z2 * z2)) - ellipse)
    length = np.sqrt(a * a + b * b + c * c)
    return length - length / np.maximum(radius, 1e-6)


def _box(x: np.ndarray, y: np.ndarray, half_x: np.ndarray, half_y: np.ndarray) -> np.ndarray:
    """Signed distance to a rectangle centred at the origin (negative inside)."""
    qx, qy = np.abs(x) - half_x, np.abs(y) - half_y
    outside = np.sqrt(np.maximum(qx, 0.0) ** 2 + np.maximum(qy, 0.0) ** 2)
    return outside + np.minimum(np.maximum(qx, qy), 0.0)


def extent(half_size: np.ndarray, fraction: np.ndarray, squareness: np.ndarray) -> np.ndarray:
    """How far from the axis a section's wall stands at ``fraction`` of the other half-size
    off it: the wall's distance at a height (``half_size`` the half-width, ``fraction`` of
    the half-height), or the roof's height at an offset (the other way round)."""
    y2 = np.minimum(fraction * fraction, 1.0)
    ellipse = np.sqrt(1.0 - y2)
    power4 = np.sqrt(np.sqrt(1.0 - y2 * y2))
    return half_size * (ellipse + squareness * (power4 - ellipse))


@dataclass(frozen=True)
class Boulder:
    """A boulder of rock: an ellipsoid, or an angular block of breakdown of about its size.

    Attributes:
        centre: (3,) metres.
        radii: (3,) semi-axes, metres.
        angular: None for a smooth ellipsoid; otherwise the seed of an angular block: a
            box of nine tenths of the semi-axes at any heading, tilted up to 20 degrees, its
            corners sheared off by seven random planes (each keeping 55-85 % of the box's
            reach in its direction), so that no two blocks share a shape.
    """

    centre: tuple[float, float, float]
    radii: tuple[float, float, float]
    angular: int | None = None

    @property
    def reach(self) -> float:
        """Radius of a sphere about the centre that holds the whole boulder, metres."""
        radii = np.asarray(self.radii, np.float64)
        return float(radii.max() if self.angular is None else 0.9 * np.sqrt(radii @ radii))

    def field(self, points: np.ndarray) -> np.ndarray:
        """(m,) about how far outside the boulder each of (m, 3) ``points`` lies (negative
        inside; a block's is exact inside and on its faces, short off edges and corners)."""
        rel = points - np.asarray(self.centre)
        radii = np.asarray(self.radii, np.float64)
        if self.angular is None:
            return (np.linalg.norm(rel / radii, axis=-1) - 1.0) * float(radii.min())
        # Term by term, not a matrix product: BLAS rounds differently from CPU to CPU.
        out = np.full(len(rel), -np.inf)
        for nx, ny, nz, offset in _block_planes(self.angular, 0.9 * radii):
            out = np.maximum(out, rel[:, 0] * nx + rel[:, 1] * ny + rel[:, 2] * nz - offset)
        return out

    def heights(self, dx: np.ndarray, dy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(bottom, top): the heights above the centre of an angular block's underside
        and top at horizontal offsets (``dx``, ``dy``) from its centre; bottom > top
        where the vertical there misses the block. A convex block is, along a vertical,
        above each face that looks down and below each that looks up."""
        if self.angular is None:
            raise ValueError("heights are those of an angular block")
        bottom, top = np.full(np.shape(dx), -np.inf), np.full(np.shape(dx), np.inf)
        for nx, ny, nz, offset in _block_planes(self.angular, 0.9 * np.asarray(self.radii)):
            rest = offset - nx * dx - ny * dy
            if nz < -1e-9:
                bottom = np.maximum(bottom, rest / nz)
            elif nz > 1e-9:
                top = np.minimum(top, rest / nz)
            else:  # a vertical face: the column is beside the block
                bottom = np.where(rest < 0.0, np.inf, bottom)
        return bottom, top


def _block_planes(seed: int, half: np.ndarray, cuts: int = 7) -> np.ndarray:
    """(6 + cuts, 4) the faces of an angular block, each (unit normal, offset): a box
    turned by any heading and tilted up to 20 degrees (a block at rest, so that its size
    across the passage stays about the ellipsoid's), corners sheared off."""
    rng = np.random.default_rng(seed)
    heading, tilt, tilt_axis = (
        rng.uniform(0, 2 * math.pi),
        rng.uniform(0, 0.35),
        rng.uniform(0, 2 * math.pi),
    )
    # Quaternions composed by hand: C library trigonometry on scalars, the same on any CPU.
    yaw = (math.cos(heading / 2), 0.0, 0.0, math.sin(heading / 2))
    lean = (
        math.cos(tilt / 2),
        math.sin(tilt / 2) * math.cos(tilt_axis),
        math.sin(tilt / 2) * math.sin(tilt_axis),
        0.0,
    )
    w = yaw[0] * lean[0] - yaw[3] * lean[3]
    x = yaw[0] * lean[1] - yaw[3] * lean[2]
    y = yaw[0] * lean[2] + yaw[3] * lean[1]
    z = yaw[0] * lean[3] + yaw[3] * lean[0]
    rotation = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )
    planes = [(*(sign * rotation[:, k]), half[k]) for k in range(3) for sign in (1.0, -1.0)]
    for _ in range(cuts):
        normal = rng.standard_normal(3)
        normal = normal / np.sqrt(normal @ normal)
        support = float(np.abs(rotation.T @ normal) @ half)  # the box's reach along it
        planes.append((*normal, support * rng.uniform(0.55, 0.85)))
    return np.array(planes)


# How a block comes to rest (`settle_block`): lowered until at least this share of its
# underside meets the rock or the blocks below, and its centre lies over what it meets;
# where that is silt, sunk by this share of its height more.
BLOCK_CONTACT = 0.25
# How far within what holds it a block's centre must lie: on the edge it would tip.
STABLE_MARGIN_M = 0.05
SILT_BURIAL = (0.1, 0.3)


def settle_block(
    block: Boulder,
    x: np.ndarray,
    y: np.ndarray,
    z: np.ndarray,
    rock: np.ndarray,
    silt: np.ndarray | None,
) -> tuple[Boulder, np.ndarray]:
    """``block`` moved up or down to where it rests, and the (k, 2) points it rests on
    or leans against.

    The columns at (``x``, ``y``) (n,) hold ``rock`` (n, m), the field at heights ``z``
    (m,) rising (rock where 0 or more), and ``silt`` (n, m), whether that rock is silt.
    A column that is rock at its top is wall, not floor: it is left out. The block drops
    until a quarter of its underside (`BLOCK_CONTACT`) meets what lies below, and on
    until its centre (of mass, the block being convex and even) lies within what it
    meets, or between that and the wall it leans on (the columns of wall under it): a
    block on a point, or on one edge of its underside, would topple. Where most
    of that is silt it sinks further, 10-30 % of its height (`SILT_BURIAL`), as a block
    that fell into mud does. A block that finds nothing below it (all wall) stays where
    it was.
    """
    cx, cy, _ = block.centre
    bottom, top = block.heights(x - cx, y - cy)
    solid = rock >= 0.0
    last = solid.shape[1] - 1 - np.argmax(solid[:, ::-1], axis=1)  # highest rock voxel
    under = bottom <= top  # the columns the block lies over
    floored = solid.any(axis=1) & ~solid[:, -1] & under
    if not floored.any():
        return block, np.empty((0, 2))
    n = np.flatnonzero(floored)
    k = last[n]
    low, high = rock[n, k], rock[n, k + 1]
    surface = z[k] + (z[k + 1] - z[k]) * low / (low - high)  # where the field crosses 0
    need = surface - bottom[n]  # the centre's height at which each column touches
    order = np.argsort(-need, kind="stable")
    wall = np.stack([x[under & ~floored], y[under & ~floored]], axis=1)
    count = _resting_count(np.stack([x[n], y[n]], axis=1)[order], wall, (cx, cy))
    at = float(need[order[count - 1]])
    touching = need >= at
    if silt is not None and silt[n[touching], k[touching]].mean() > 0.5:
        height = float(np.max(top[n] - bottom[n]))
        at -= height * np.random.default_rng(block.angular).uniform(*SILT_BURIAL)
    contact = np.concatenate([np.stack([x[n[touching]], y[n[touching]]], axis=1), wall])
    return replace(block, centre=(float(cx), float(cy), at)), contact


def _resting_count(points: np.ndarray, wall: np.ndarray, centre: tuple[float, float]) -> int:
    """How many of ``points`` (k, 2), taken in order, a block must meet to rest: a
    quarter of them (`BLOCK_CONTACT`) at least, and enough that ``centre`` lies within
    the convex hull of those and of the ``wall`` (j, 2) it leans on, by
    `STABLE_MARGIN_M` at least (all of them if it
    never does). The hull only grows as points are added, so the least such count is
    found by bisection."""
    from scipy.spatial import ConvexHull, QhullError

    def over(count: int) -> bool:
        try:
            hull = ConvexHull(np.concatenate([points[:count], wall]))
        except (QhullError, ValueError):  # too few, or all in a line
            return False
        return bool(np.all(hull.equations @ (*centre, 1.0) <= -STABLE_MARGIN_M))

    low = max(1, int(np.ceil(BLOCK_CONTACT * len(points))))
    if over(low) or not over(len(points)):
        return low if over(low) else len(points)
    high = len(points)  # over(high); not over(low)
    while high - low > 1:
        middle = (low + high) // 2
        low, high = (low, middle) if over(middle) else (middle, high)
    return high


@dataclass(frozen=True)
class Speleothem:
    """A vertical truncated cone of rock: a stalactite (narrow below), a stalagmite
    (narrow above) or a column (a stalactite and a stalagmite grown together).

    Attributes:
        x, y: its axis, metres.
        bottom, top: heights of its ends, metres (an end inside the rock is hidden).
        bottom_radius, top_radius: its radius at each end, metres.
    """

    x: float
    y: float
    bottom: float
    top: float
    bottom_radius: float
    top_radius: float

    @property
    def reach(self) -> float:
        return max(self.bottom_radius, self.top_radius)

    def field(self, points: np.ndarray) -> np.ndarray:
        """(m,) about how far outside the cone each of (m, 3) ``points`` lies."""
        dx, dy = points[:, 0] - self.x, points[:, 1] - self.y
        rho = np.sqrt(dx * dx + dy * dy)
        height = self.top - self.bottom
        t = np.clip((points[:, 2] - self.bottom) / height, 0.0, 1.0)
        radius = self.bottom_radius + t * (self.top_radius - self.bottom_radius)
        slope = (self.top_radius - self.bottom_radius) / height
        side = (rho - radius) / np.sqrt(1.0 + slope * slope)
        ends = np.maximum(self.bottom - points[:, 2], points[:, 2] - self.top)
        return np.maximum(side, ends)


def carve_scallops(
    phi: np.ndarray,
    lo: np.ndarray,
    voxel: float,
    size: float,
    depth: float,
    rng: np.random.Generator,
) -> None:
    """Cut scallops into the walls of ``phi`` (in place): dish-shaped hollows ``size``
    metres across and ``depth`` deep, meeting in sharp rims.

    The dishes are the cells of a jittered lattice of ``size`` spacing (each wall point
    belongs to its nearest lattice point, and lies deeper the nearer it is), so the
    rims are the cells' borders as the wall cuts them: the polygonal, cusped pattern of
    real scallops. Each lattice point lies anywhere in its cell: kept off the cell's
    edges, the points would leave the rims bunched near the lattice's planes, a ring of
    rims every ``size`` metres along a passage that runs along the lattice (and the
    lattice's own lines in every spectrum of the wall); jittered over the whole cell, the
    rims spread evenly. Only voxels within reach of the wall are touched.
    """
    if size <= 0 or depth <= 0:
        return
    near = np.nonzero(np.abs(phi) < depth + 2 * voxel)
    if len(near[0]) == 0:
        return
    points = lo + voxel * np.stack(near, axis=1)
    first = np.floor(points.min(axis=0) / size) - 1
    last = np.floor(points.max(axis=0) / size) + 2
    cells = np.stack(
        np.meshgrid(*(np.arange(first[k], last[k]) for k in range(3)), indexing="ij"), -1
    ).reshape(-1, 3)
    seeds = (cells + rng.uniform(0.0, 1.0, cells.shape)) * size
    distance, _ = cKDTree(seeds).query(points)
    reach = 0.8 * size
    closeness = 1.0 - np.minimum(distance / reach, 1.0) ** 2
    phi[near] -= (depth * closeness).astype(phi.dtype)
