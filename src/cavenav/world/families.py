"""The cave families: one builder per family, drawing a passage from a seed and knobs.

Each builder takes the family's generator (seeded by the cave seed and the family's
number, see `cavenav.world.scenario.SCENARIOS`), the cave seed and every knob of the
family resolved to a value, and returns the `Layout` of a passage before meshing: its
centre line and profiles, boulders and side branches, the start pose and a description.
S1-S5 are the SPEC's five topologies (section 6); crawl, maze and long are harder.
What the knobs mean and the ranges each family accepts are declared with
`cavenav.world.scenario.Difficulty` and the registry; the builders only read them.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.spatial import cKDTree

from cavenav.core.errors import ScenarioError
from cavenav.core.types import Pose
from cavenav.world.morphology import Boulder, Section, Speleothem, extent
from cavenav.world.procedural import (
    Branch,
    PassageSpec,
    along,
    arc_length,
    cpu_independent,
    gaussian_smooth,
    resample,
    rounded_corners,
)

__all__ = ["Layout", "crawl", "long", "maze", "s1", "s2", "s3", "s4", "s5"]


def _vec3(v: np.ndarray) -> tuple[float, float, float]:
    return float(v[0]), float(v[1]), float(v[2])


def _smooth_noise(s: np.ndarray, wavelength: float, rng: np.random.Generator) -> np.ndarray:
    """Smooth 1-D noise along arc length ``s``, roughly in [-1, 1]."""
    knots = np.arange(s[0] - wavelength, s[-1] + 2 * wavelength, wavelength)
    values = rng.uniform(-1.0, 1.0, len(knots))
    curve = np.interp(s, knots, values)
    step = float(s[1] - s[0])
    return gaussian_smooth(curve, 0.35 * wavelength / step) * 1.6


def _dips(s: np.ndarray, centres: list[float], depth: float, sigma: float = 1.6) -> np.ndarray:
    """Sum of Gaussian narrowings of ``depth`` metres centred at ``centres``."""
    out = np.zeros_like(s)
    for c in centres:
        out = np.maximum(out, depth * cpu_independent(math.exp, -0.5 * ((s - c) / sigma) ** 2))
    return out


def _dip_depth(half_width: float, narrowest_m: float) -> float:
    """How deep dips must be to narrow a passage of ``half_width`` to ``narrowest_m`` across.

    Rounded to the nanometre so that the decimal defaults give back the depths the families
    were written with bit for bit: 3.2 - 3.8 / 2 is 1.3000000000000003 in floating point.
    """
    return round(half_width - narrowest_m / 2, 9)


def _straighten_ends(
    s: np.ndarray, values: np.ndarray, length: float, margin: float = 6.0
) -> np.ndarray:
    """Hold a profile constant before s=2 and after s=length-margin: straight portals."""
    head = np.interp(2.0, s, values)
    tail = np.interp(length - margin, s, values)
    out = values.copy()
    out[s < 2.0] = head
    out[s > length - margin] = tail
    return gaussian_smooth(out, 4)


def _winding(s: np.ndarray, heading: np.ndarray, length: float) -> tuple[np.ndarray, np.ndarray]:
    """The plan (x, y) of a passage along -y that turns by ``heading`` (radians, positive
    to +x) at stations ``s``: straight near the start and, so that the exit runs along
    the axis the surface is opened across, over the last 8 m. The start is at the origin."""
    heading = _straighten_ends(s, heading, length)
    heading[s > length - 8] = 0.0
    heading = gaussian_smooth(heading, 6)
    heading[s > length - 3] = 0.0
    step = s[1] - s[0]
    x = np.cumsum(cpu_independent(math.sin, heading)) * step
    y = -np.cumsum(cpu_independent(math.cos, heading)) * step
    return x - np.interp(0.0, s, x), y - np.interp(0.0, s, y)


def _scaled(radii: tuple[float, float, float], scale: float) -> tuple[float, float, float]:
    """Semi-axes times ``obstacle_scale`` (exact at the default 1.0)."""
    return radii[0] * scale, radii[1] * scale, radii[2] * scale


def _window(u: np.ndarray, start: float, end: float) -> np.ndarray:
    """1 between stations ``start`` and ``end``, 0 outside, eased over about 2 m."""
    box = ((u >= start) & (u <= end)).astype(float)
    return gaussian_smooth(box, 2.0 / (u[1] - u[0]))


# ------------------------------------------------------------------ morphologies
#
# What turns a family's tube into a cave (`cavenav.world.morphology`): each helper draws
# one feature from ``shapes``, a child of the family's generator (`Generator.spawn`), so
# that the shapes draw the same numbers whatever the knobs drew before them and a knob
# changes only what it governs. Widths and heights are metres; stations are metres along
# the passage.

# Scallops 0.6-0.9 m across (and an eighth as deep): the size slow flows of a few cm/s
# dissolve into the walls of large phreatic conduits (Curl 1974).
SCALLOPS_M = (0.6, 0.9)
# A sharp bend's centre line turns along an arc of this radius (`rounded_corners`):
# within the 2.6-3.8 m half-width of the passages that turn there, so the inside of the
# bend stays a sharp edge of rock, while the sections' frames turn by 6 degrees from one
# 0.25 m sample to the next. At a right angle the arc leaves each leg 2.5 m before the
# corner.
BEND_RADIUS_M = 2.5


def _stretch(
    shapes: np.random.Generator, start: float, end: float, length: tuple[float, float]
) -> np.ndarray:
    """(2,) a stretch of ``length`` metres (drawn) lying between stations ``start`` and ``end``."""
    metres = shapes.uniform(*length)
    first = shapes.uniform(start, max(start, end - metres))
    return np.array([first, first + metres])


def _ceiling_channel(
    shapes: np.random.Generator, s: np.ndarray, section: Section, start: float, end: float
) -> Section:
    """A half-tube 0.9-1.3 m across dissolved into the ceiling, meandering up to 0.8 m
    either side of the axis, between stations ``start`` and ``end``."""
    window = _window(s, start, end)
    return replace(
        section,
        ceiling_channel=section.ceiling_channel + shapes.uniform(0.45, 0.65) * window,
        channel_offset=section.channel_offset + 0.8 * _smooth_noise(s, 10.0, shapes) * window,
    )


def _notch(
    shapes: np.random.Generator, s: np.ndarray, section: Section, start: float, end: float
) -> Section:
    """A notch 0.6-1.0 m deep undercutting one wall for 5-10 m, at about the axis's height
    or below (where a still water table once stood)."""
    return _on_a_wall(
        shapes, s, section, (start, end), "notch", (5.0, 10.0), (-0.5, 0.1), (0.6, 1.0)
    )


def _ledge(
    shapes: np.random.Generator, s: np.ndarray, section: Section, start: float, end: float
) -> Section:
    """A shelf of rock jutting 0.5-0.8 m from one wall for 5-9 m, its top 30-60 % of the
    half-height above the axis: what lies on it is hidden from below."""
    return _on_a_wall(shapes, s, section, (start, end), "ledge", (5.0, 9.0), (0.3, 0.6), (0.5, 0.8))


def _on_a_wall(
    shapes: np.random.Generator,
    s: np.ndarray,
    section: Section,
    between: tuple[float, float],
    feature: str,
    length: tuple[float, float],
    height: tuple[float, float],
    size: tuple[float, float],
) -> Section:
    """``section`` with a ``feature`` (a `Section` field with a ``_height`` companion) on
    one wall, drawn in this order: a stretch of ``length`` metres ``between`` two
    stations, a side, a height (fraction of the half-height) and a size (metres)."""
    window = _window(s, *_stretch(shapes, *between, length))
    side = 1.0 if shapes.random() < 0.5 else -1.0
    level = shapes.uniform(*height)
    heights = getattr(section, f"{feature}_height")
    return replace(
        section,
        **{
            feature: getattr(section, feature) + side * shapes.uniform(*size) * window,
            f"{feature}_height": np.where(window > 0.01, level, heights),
        },
    )


def _keyhole(
    shapes: np.random.Generator, s: np.ndarray, section: Section, start: float, end: float
) -> Section:
    """A canyon 1.6-2.2 m wide cut 1.2-2.0 m below the tube's floor for 10-16 m: a keyhole."""
    window = _window(s, *_stretch(shapes, start, end, (10.0, 16.0)))
    return replace(
        section,
        canyon_width=section.canyon_width + shapes.uniform(0.8, 1.1) * window,
        canyon_depth=section.canyon_depth + shapes.uniform(1.2, 2.0) * window,
    )


def _speleothems(
    shapes: np.random.Generator,
    s: np.ndarray,
    points: np.ndarray,
    half_w: np.ndarray,
    half_h: np.ndarray,
    section: Section,
    stations: Sequence[float],
    kinds: Sequence[str],
) -> list[Speleothem]:
    """One speleothem at each station, of each kind: a ``stalactite`` 0.5-1.2 m long
    hanging anywhere over the middle 60 % of the width, a ``stalagmite`` 0.4-1.0 m tall,
    or a ``column`` 0.7-1.0 m thick (waisted where its halves met) standing near a wall.
    Stalactites and stalagmites stop 0.8 m short of the axis's height, so that they
    stand in the way of a change of depth, not of level flight along the axis. Their far
    ends reach a metre into the rock, beyond the wall's noise."""
    out = []
    for at, kind in zip(stations, kinds, strict=True):
        i = int(np.searchsorted(s, at))
        forward, left = _heading_left(points[min(i + 1, len(s) - 1)] - points[max(i - 1, 0)])
        reach = shapes.uniform(0.65, 0.75) if kind == "column" else shapes.uniform(-0.6, 0.6)
        across = reach * half_w[i] * (1.0 if kind != "column" or shapes.random() < 0.5 else -1.0)
        x, y = points[i, :2] + across * left[:2]
        height = float(extent(half_h[i], across / half_w[i], section.squareness[i]))
        ceiling, floor = points[i, 2] + height, points[i, 2] - height + section.sediment[i]
        room = height - 0.8  # from the roof (or the floor) to 0.8 m off the axis's height
        if kind == "stalactite":
            length = min(shapes.uniform(0.5, 1.2), room)
            out.append(
                Speleothem(x, y, ceiling - length, ceiling + 1.0, 0.03, shapes.uniform(0.25, 0.4))
            )
        elif kind == "stalagmite":
            tall = min(shapes.uniform(0.4, 1.0), room - section.sediment[i])
            out.append(Speleothem(x, y, floor - 1.0, floor + tall, shapes.uniform(0.3, 0.45), 0.05))
        else:
            waist, foot = shapes.uniform(0.3, 0.4), shapes.uniform(0.45, 0.6)
            middle = (ceiling + floor) / 2 + shapes.uniform(-0.3, 0.3)
            # The halves overlap by 0.2 m: two cones that only touched would leave a
            # seam of water one voxel thick where their fields are both zero.
            out.append(Speleothem(x, y, floor - 1.0, middle + 0.2, foot, waist))
            out.append(Speleothem(x, y, middle - 0.2, ceiling + 1.0, waist, foot))
    return out


def _breakdown(
    shapes: np.random.Generator,
    s: np.ndarray,
    points: np.ndarray,
    half_w: np.ndarray,
    half_h: np.ndarray,
    section: Section,
    stations: Sequence[float] | np.ndarray,
    below: float,
) -> list[Boulder]:
    """Angular blocks 0.4-2.3 m across fallen into a chamber (``section``'s floor,
    flatter than an ellipse's), one near each station, each dropped from ``below`` metres
    under the axis, or from its own size over the floor where that is lower: they come to
    rest on the floor and on each other (`cavenav.world.procedural.settled_blocks`), a
    pile in the chamber's extra depth."""
    out = []
    for at in stations:
        i = int(np.searchsorted(s, at + shapes.uniform(-1.0, 1.0)))
        _, left = _heading_left(points[min(i + 1, len(s) - 1)] - points[max(i - 1, 0)])
        r = shapes.uniform(0.4, 1.0)
        across = shapes.uniform(-0.7, 0.7) * half_w[i]
        floor = -float(extent(half_h[i], across / half_w[i], section.squareness[i]))
        drop = min(floor + r, -below)  # from just over the floor: it falls to rest
        centre = points[i] + across * left + np.array([0.0, 0.0, drop])
        radii = (
            r * shapes.uniform(0.8, 1.3),
            r * shapes.uniform(0.8, 1.3),
            r * shapes.uniform(0.5, 0.8),
        )
        out.append(Boulder(_vec3(centre), radii, angular=int(shapes.integers(2**31))))
    return out


@dataclass(frozen=True)
class Layout:
    """A generated passage before meshing: spec plus where the vehicle starts.

    ``step_budget`` is `Scenario.step_budget`: None for S1-S5, which the SPEC's 150
    steps fit. ``optics`` is `Scenario.optics`: the family's own defaults, as a scenario
    file's [optics] table (the crawl's silt floor silts out).
    """

    spec: PassageSpec
    start: Pose
    description: str
    step_budget: int | None = None
    optics: Mapping[str, object] = field(default_factory=dict)

    @property
    def exit_plane(self) -> tuple[tuple[float, float, float], tuple[float, float, float], float]:
        """Point, outward normal and radius of the exit portal: across the passage at the
        exit station, along the centre line there, 1.5 m wider than the widest profile so
        that no part of the passage's end lies outside it."""
        spec = self.spec
        tangent = spec.centreline[spec.exit_index + 1] - spec.centreline[spec.exit_index - 1]
        tangent /= np.linalg.norm(tangent)
        radius = float(max(spec.half_width.max(), spec.half_height.max()) + 1.5)
        return _vec3(spec.centreline[spec.exit_index]), _vec3(tangent), radius


def _layout_from_profiles(
    s: np.ndarray,
    points: np.ndarray,
    half_width: np.ndarray,
    half_height: np.ndarray,
    length: float,
    seed: int,
    *,
    roughness: float,
    boulders: tuple[Boulder, ...] = (),
    branches: tuple[Branch, ...] = (),
    section: Section | None = None,
    breakdown: tuple[Boulder, ...] = (),
    speleothems: tuple[Speleothem, ...] = (),
    scallops: float = 0.0,
    start_offset: tuple[float, float, float] = (0.0, 0.0, 0.0),
    steps_per_m: float | None = None,
    description: str = "",
    optics: Mapping[str, object] | None = None,
) -> Layout:
    """The layout of a passage sampled at stations ``s`` (0 at the start, ``length`` at
    the exit); ``steps_per_m`` gives a step budget for that many steps per metre of
    centre-line from the start to the exit, rounded up to a multiple of 10."""
    exit_index = int(np.searchsorted(s, length))
    start_index = int(np.searchsorted(s, 0.0))
    heading = points[start_index + 1] - points[start_index]
    start = Pose.facing(points[start_index] + np.asarray(start_offset), heading)
    spec = PassageSpec(
        points,
        half_width,
        half_height,
        boulders,
        exit_index,
        roughness=roughness,
        seed=seed,
        branches=branches,
        section=section,
        breakdown=breakdown,
        speleothems=speleothems,
        scallops=scallops,
    )
    budget = None
    if steps_per_m is not None:
        passage = np.linalg.norm(np.diff(points[start_index : exit_index + 1], axis=0), axis=1)
        budget = 10 * math.ceil(steps_per_m * float(passage.sum()) / 10)
    return Layout(spec, start, description, budget, dict(optics or {}))


def s1(rng: np.random.Generator, seed: int, knobs: Mapping[str, float]) -> Layout:
    """S1, constrictions: a gently winding passage narrowed in three places."""
    length = 55.0
    s = np.arange(-4.0, length + 4.0, 0.25)
    phase = 2 * np.pi * s / rng.uniform(26, 34) + rng.uniform(0, 6.3)
    x = _straighten_ends(s, 1.6 * cpu_independent(math.sin, phase), length)
    z = _straighten_ends(s, 0.5 * _smooth_noise(s, 12.0, rng), length)
    points = np.stack([x, -s, z], axis=1)
    necks = [c + rng.uniform(-2, 2) for c in (15.0, 29.0, 42.0)]
    half_w = 3.5 - _dips(s, necks, _dip_depth(3.5, knobs["constriction_m"]))
    half_h = 3.0 - _dips(s, necks[1:2], 1.0)
    # A phreatic tube: scalloped, a half-tube in the ceiling, a notch in a wall, silt.
    shapes = rng.spawn(1)[0]
    section = replace(Section.plain(len(s)), sediment=np.full(len(s), 0.4))
    section = _ceiling_channel(shapes, s, section, *_stretch(shapes, 4.0, length - 6, (20.0, 35.0)))
    section = _notch(shapes, s, section, 4.0, length - 6)
    return _layout_from_profiles(
        s,
        points,
        half_w,
        half_h,
        length,
        seed,
        roughness=knobs["roughness_m"],
        section=section,
        scallops=shapes.uniform(*SCALLOPS_M),
        description="narrow phreatic passage with three constrictions to about "
        f"{knobs['constriction_m']:.1f} m",
    )


def s2(rng: np.random.Generator, seed: int, knobs: Mapping[str, float]) -> Layout:
    """S2, undulations: a passage rising and falling, narrowed on two of its slopes."""
    length = 55.0
    s = np.arange(-4.0, length + 4.0, 0.25)
    x = _straighten_ends(s, 1.0 * _smooth_noise(s, 15.0, rng), length)
    # Slopes of at most atan(2 pi amplitude / 30): 23 degrees at the default 4 m peak to
    # peak; larger undulations are steeper (see Difficulty).
    period = rng.uniform(30, 34)
    amplitude = knobs["undulation_m"] / 2
    z = _straighten_ends(s, amplitude * cpu_independent(math.sin, 2 * np.pi * s / period), length)
    points = np.stack([x, -s, z], axis=1)
    # Constrictions on the slopes, between a crest and a trough.
    necks = [period * (k / 2 + 0.5) + rng.uniform(-1.5, 1.5) for k in (0, 1)]
    half_w = 3.2 - _dips(s, necks, _dip_depth(3.2, knobs["constriction_m"]))
    half_h = 2.9 - _dips(s, necks, 0.8)
    # Keyhole sections (a canyon cut below the tube) on a stretch of each half.
    shapes = rng.spawn(1)[0]
    section = _keyhole(shapes, s, Section.plain(len(s)), 3.0, length / 2)
    section = _keyhole(shapes, s, section, length / 2, length - 6)
    return _layout_from_profiles(
        s,
        points,
        half_w,
        half_h,
        length,
        seed,
        roughness=knobs["roughness_m"],
        section=section,
        scallops=shapes.uniform(*SCALLOPS_M),
        description=f"narrow passage with vertical undulations of about "
        f"{knobs['undulation_m']:g} m and two constrictions",
    )


def _pile(shapes: np.random.Generator, x: float, y: float, scale: float) -> list[Boulder]:
    """A frontal obstacle: a block of breakdown 2.2-2.9 m across (times ``scale``)
    fallen near (``x``, ``y``), and a smaller one, 1.3-1.6 m, fallen onto it, the pile
    about 3 m high: up past the axis of a 6 m passage whose floor is silted."""
    base = Boulder((x, y, -1.0), _scaled((1.6, 1.5, 1.2), scale), int(shapes.integers(2**31)))
    dx, dy = shapes.uniform(-0.4, 0.4, 2)  # on the base whatever its scale
    top = Boulder(
        (x + dx, y + dy, 1.5), _scaled((0.9, 0.8, 0.7), scale), int(shapes.integers(2**31))
    )
    return [base, top]


def _wall_block(shapes: np.random.Generator, x: float, y: float, scale: float) -> Boulder:
    """A lateral obstacle: a block of breakdown 2.7-2.9 m across (times ``scale``)
    fallen near (``x``, ``y``), at the foot of a wall."""
    return Boulder((x, y, -1.0), _scaled((1.6, 1.5, 1.5), scale), int(shapes.integers(2**31)))


def s3(rng: np.random.Generator, seed: int, knobs: Mapping[str, float]) -> Layout:
    """S3, obstacles: a straight passage with boulders, alternately frontal and lateral."""
    length = 45.0
    s = np.arange(-4.0, length + 4.0, 0.25)
    points = np.stack([np.zeros_like(s), -s, np.zeros_like(s)], axis=1)
    half_w = np.full_like(s, 3.5)
    half_h = np.full_like(s, 3.0)
    wall_side = 1.0 if rng.random() < 0.5 else -1.0  # +x is the vehicle's left at psi = 0
    count, scale = int(knobs["obstacles"]), knobs["obstacle_scale"]
    # Stations from 14.5 m on, 29 m / count apart: the default two at 14.5 m and 29 m, and
    # the last of eight by 41 m, clear of the exit at 45 m. Each draws its place in turn.
    spacing = 29.0 / max(count, 1)
    shapes, stones = rng.spawn(2)  # the blocks' shapes apart: their count is a knob
    boulders = []
    for k in range(count):
        station = 14.5 + k * spacing
        if k % 2 == 0:  # frontal: up to the start height, in line with the start near the wall
            jitter = min(1.5, spacing / 4)
            y = -rng.uniform(station - jitter, station + jitter)
            boulders += _pile(stones, -wall_side * 0.9, y, scale)
        else:  # lateral: at the foot of the other wall
            jitter = min(2.0, spacing / 4)
            y = -rng.uniform(station - jitter, station + jitter)
            boulders.append(_wall_block(stones, wall_side * 2.2, y, scale))
    kinds = {
        0: "no obstacle",
        1: "a frontal pile of breakdown",
        2: "a frontal pile and a lateral block of breakdown",
    }
    obstacles = kinds.get(
        count, f"{count} piles and blocks of breakdown, alternately frontal and lateral"
    )
    start = "start near the wall at the frontal obstacle's height" if count else "start near a wall"
    # Breakdown blocks on a silted floor, and a ledge over the far part of the passage.
    section = replace(Section.plain(len(s)), sediment=np.full(len(s), 0.5))
    section = _ledge(shapes, s, section, 30.0, length - 4)
    return _layout_from_profiles(
        s,
        points,
        half_w,
        half_h,
        length,
        seed,
        roughness=knobs["roughness_m"],
        boulders=tuple(boulders),
        section=section,
        scallops=shapes.uniform(*SCALLOPS_M),
        start_offset=(-wall_side * 2.0, 0.0, 0.0),
        description=f"straight passage with {obstacles}; {start}",
    )


def s4(rng: np.random.Generator, seed: int, knobs: Mapping[str, float]) -> Layout:
    """S4, bend: two straight legs meeting at a sharp turn, the centre line rounded by an
    arc of `BEND_RADIUS_M`."""
    leg = 30.0
    side = 1.0 if rng.random() < 0.5 else -1.0
    bend = knobs["bend_deg"]
    # The surface is opened across the exit direction, which must be an axis: the second leg
    # runs along side * x and the first leg is turned instead. ``back`` points from the
    # corner up the first leg: +y for 90 degrees, tilted toward the second leg for less.
    tilt = math.radians(bend - 90.0)
    back = np.array([side * math.sin(tilt), math.cos(tilt), 0.0])
    # A hairpin's first leg reaches back toward the exit plane: past about 130 degrees it
    # is shortened, to a whole number of 0.25 m samples, so that its closed end (4 m
    # behind the start, plus a wall) stays 7 m behind that plane.
    reach = -math.cos(math.radians(bend))
    first = leg if reach <= 0 else min(leg, math.floor(4 * ((leg - 7.0) / reach - 4.0)) / 4)
    corner = np.array([0.0, -leg, 0.0])
    corners = np.array(
        [corner + (first + 4.0) * back, corner, corner + np.array([side * (leg + 4.0), 0, 0])]
    )
    line = rounded_corners(corners, BEND_RADIUS_M)
    points, s = resample(line, 0.25)
    s = s - 4.0
    # The rounded line is shorter than the two legs: it passes the corner (the arc's
    # middle) half that sooner, and reaches the exit, which stays where the legs put it
    # (leg metres past the corner, to within a sample), all of it sooner.
    shortening = arc_length(corners)[-1] - arc_length(line)[-1]
    corner_at, length = first - 0.5 * shortening, first + leg - shortening
    half_w = 2.9 + 0.3 * _smooth_noise(s, 10.0, rng)
    half_h = 2.7 + 0.2 * _smooth_noise(s, 10.0, rng)
    # A tall first leg with flat walls turns into a wide one under a flat roof, with
    # stalactites over the turn and a silted floor. Walls, roof and silt stay as far from
    # the axis as the tube's were, beyond the SPEC's 2 m standoff, so that the turn stays
    # the task (a passage lower than that is a crawl, where the geometric pilot creeps).
    shapes = rng.spawn(1)[0]
    second = _window(s, corner_at + 3.0, length + 4.0)
    silt = 0.3
    half_w = half_w + 0.6 * second
    half_h = half_h + 0.6 * (1.0 - second) + silt
    section = replace(
        Section.plain(len(s)), squareness=np.full(len(s), 0.6), sediment=np.full(len(s), silt)
    )
    turn = corner_at + shapes.uniform(-6.0, -2.0) + np.arange(5) * shapes.uniform(1.5, 2.5)
    speleothems = _speleothems(shapes, s, points, half_w, half_h, section, turn, ["stalactite"] * 5)
    return _layout_from_profiles(
        s,
        points,
        half_w,
        half_h,
        length,
        seed,
        roughness=knobs["roughness_m"],
        section=section,
        speleothems=tuple(speleothems),
        scallops=shapes.uniform(*SCALLOPS_M),
        description=f"sharp {bend:g}-degree bend to the {'left' if side > 0 else 'right'}",
    )


def _rocks(
    rng: np.random.Generator,
    s: np.ndarray,
    stations: np.ndarray,
    points: np.ndarray,
    half_w: np.ndarray,
    half_h: np.ndarray,
    scale: float,
    shapes: np.random.Generator,
) -> list[Boulder]:
    """S5's rocks, one within 2 m of each station: every third in the middle of the
    floor, the others at the foot of a wall, angular blocks 1.4-2.5 m across times
    ``scale`` (their shapes drawn from ``shapes``), each falling from the passage's
    axis to where it rests."""
    tangent = np.gradient(points, axis=0)
    boulders = []
    for k, at in enumerate(stations):
        i = int(np.searchsorted(s, at + rng.uniform(-2, 2)))
        t = tangent[i] / np.linalg.norm(tangent[i])
        left = np.array([-t[1], t[0], 0.0]) / max(np.hypot(t[0], t[1]), 1e-9)
        r = rng.uniform(0.8, 1.25)
        if k % 3 == 2:  # a rock on the floor
            centre = points[i] + left * rng.uniform(-1.0, 1.0)
        else:  # a rock at the foot of a wall
            side = 1.0 if rng.random() < 0.5 else -1.0
            centre = points[i] + side * left * rng.uniform(0.45, 0.7) * half_w[i]
        radii = _scaled((r, r * 1.1, r * 0.9), scale)
        boulders.append(Boulder(_vec3(centre), radii, angular=int(shapes.integers(2**31))))
    return boulders


def s5(rng: np.random.Generator, seed: int, knobs: Mapping[str, float]) -> Layout:
    """S5, irregular: a winding passage of changing size with rocks spread along it."""
    length = 60.0
    s = np.arange(-4.0, length + 4.0, 0.25)
    x, y = _winding(s, 0.55 * _smooth_noise(s, 14.0, rng), length)
    z = _straighten_ends(s, 1.2 * _smooth_noise(s, 11.0, rng), length)
    points = np.stack([x, y, z], axis=1)
    half_w = 3.3 + 0.7 * _smooth_noise(s, 9.0, rng)
    half_h = 2.8 + 0.3 * _smooth_noise(s, 9.0, rng)
    count, scale = int(knobs["obstacles"]), knobs["obstacle_scale"]
    stations = np.linspace(9.0, length - 9.0, count)
    shapes, stones = rng.spawn(2)  # the rocks' shapes apart: their count is a knob
    boulders = _rocks(rng, s, stations, points, half_w, half_h, scale, stones)
    # A chamber where the roof collapsed: 1.5 m wider and 1.2 m higher on each side, its
    # floor heaped with breakdown to about the passage's own; speleothems beyond it.
    chamber = _stretch(shapes, 14.0, length - 14.0, (10.0, 14.0))
    grown = _window(s, *chamber)
    below = half_h.copy()
    half_w, half_h = half_w + 1.5 * grown, half_h + 1.2 * grown
    section = replace(Section.plain(len(s)), squareness=0.5 * grown)
    pile = np.linspace(chamber[0] + 1.0, chamber[1] - 1.0, 8)
    breakdown = _breakdown(shapes, s, points, half_w, half_h, section, pile, float(below.min()))
    others = [
        at for at in np.arange(6.0, length - 6.0, 4.0) if not chamber[0] - 2 < at < chamber[1] + 2
    ]
    picks = shapes.choice(len(others), size=4, replace=False)
    kinds = ["stalactite", "stalactite", "stalagmite", "column"]
    speleothems = _speleothems(
        shapes, s, points, half_w, half_h, section, [others[k] for k in sorted(picks)], kinds
    )
    return _layout_from_profiles(
        s,
        points,
        half_w,
        half_h,
        length,
        seed,
        roughness=knobs["roughness_m"],
        boulders=tuple(boulders),
        section=section,
        breakdown=tuple(breakdown),
        speleothems=tuple(speleothems),
        scallops=shapes.uniform(*SCALLOPS_M),
        description="irregular winding passage with blocks spread along it and a collapse chamber"
        if count
        else "irregular winding passage with a collapse chamber",
    )


# ------------------------------------------------------------------ harder families


def crawl(rng: np.random.Generator, seed: int, knobs: Mapping[str, float]) -> Layout:
    """crawl: a winding crawlway too narrow for any standoff, pinched in three places."""
    length = float(rng.integers(42, 59))  # whole metres
    s = np.arange(-4.0, length + 4.0, 0.25)
    # Meanders every 18-26 m, made irregular: the heading swings some 25 degrees either
    # way and never reaches 90 (at most 65), so the passage never doubles back on itself.
    meander = 0.45 * cpu_independent(
        math.sin, 2 * np.pi * s / rng.uniform(18.0, 26.0) + rng.uniform(0, 2 * np.pi)
    )
    x, y = _winding(s, meander + 0.4 * _smooth_noise(s, 12.0, rng), length)
    z = _straighten_ends(s, 0.7 * _smooth_noise(s, 14.0, rng), length)
    points = np.stack([x, y, z], axis=1)
    narrowest = knobs["constriction_m"]
    # 1.7-2.5 m across between the pinches, never under the pinches' width; each pinch
    # centred on a sample, so that the narrowest width is the knob's to the millimetre.
    # 1.5-2.2 m high: with 1.5 m at the pinches and 0.08 m of wall noise, the vehicle's
    # 0.30 m half-diagonal keeps 0.2 m from the walls even where they bulge 3 standard
    # deviations in from both sides.
    width = np.maximum(np.clip(2.1 + 0.3 * _smooth_noise(s, 8.0, rng), 1.7, 2.5), narrowest)
    pinches = [round(4 * (length * k / 4 + rng.uniform(-3, 3))) / 4 for k in (1, 2, 3)]
    half_w = 0.5 * (width - _dips(s, pinches, 1.0, sigma=1.2) * (width - narrowest))
    half_h = 0.5 * np.clip(1.8 + 0.3 * _smooth_noise(s, 10.0, rng), 1.5, 2.2)
    # A bedding-plane crawl: flat roof and floor, a silt floor 0.3 m deep. The tube is
    # made 0.15 m higher on each side, so the silt leaves the height above and keeps
    # the free height: the floor comes 0.15 m nearer the axis.
    shapes = rng.spawn(1)[0]
    silt = 0.3
    half_h = half_h + silt / 2
    section = replace(
        Section.plain(len(s)), squareness=np.full(len(s), 0.7), sediment=np.full(len(s), silt)
    )
    return _layout_from_profiles(
        s,
        points,
        half_w,
        half_h,
        length,
        seed,
        roughness=knobs["roughness_m"],
        section=section,
        scallops=shapes.uniform(0.4, 0.6),
        steps_per_m=7.0,
        optics={"silt_out": True},  # a crawl over silt is where divers silt out
        description=f"crawlway: a {length:.0f} m winding bedding plane 1.7-2.5 m across and "
        f"1.5-2.2 m high over silt, pinched to {narrowest:.1f} m across in three places",
    )


def _heading_left(tangent: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Horizontal unit forward and left vectors of a (3,) tangent."""
    forward = np.array([tangent[0], tangent[1], 0.0])
    forward /= np.linalg.norm(forward)
    return forward, np.array([-forward[1], forward[0], 0.0])


def _blind_tube(
    rng: np.random.Generator,
    junction: np.ndarray,
    forward: np.ndarray,
    left: np.ndarray,
    angle: float,
    length: float,
    half_width: float,
    half_height: float,
) -> Branch:
    """A blind passage from ``junction``, ``angle`` radians to the left of ``forward``
    (negative: right), curving up to 25 degrees farther away as it goes, ending closed."""
    t = np.arange(0.0, length + 1e-9, 0.25)
    bend = math.copysign(rng.uniform(0.0, math.radians(25)), angle) * (t / length) ** 2
    heading = angle + bend
    step = np.stack([cpu_independent(f, heading) for f in (math.cos, math.sin)], axis=1) * 0.25
    ahead, aside = np.vstack([np.zeros(2), np.cumsum(step, axis=0)[:-1]]).T
    points = junction + ahead[:, None] * forward + aside[:, None] * left
    points[:, 2] += rng.uniform(-1.0, 1.0) * t / length  # a gentle slope up or down
    return Branch(points, np.full(len(t), half_width), np.full(len(t), half_height))


def _own_part(branch: Branch, clear_from: float) -> np.ndarray:
    """The branch's points past ``clear_from`` metres: out of the passage it leaves."""
    return branch.centreline[int(math.ceil(clear_from / 0.25)) :]


def _keeps_rock(
    points: np.ndarray,
    half_width: float,
    tubes: Sequence[tuple[np.ndarray, np.ndarray]],
    gap: float,
) -> bool:
    """Whether a tube of ``points`` and ``half_width`` keeps ``gap`` metres of rock from
    each of ``tubes``, given as ((m, 3) points, (m,) half-widths)."""
    for other, other_hw in tubes:
        if len(points) == 0 or len(other) == 0:
            continue
        dist, i = cKDTree(other).query(points)
        if np.any(dist < half_width + other_hw[i] + gap):
            return False
    return True


@dataclass(frozen=True)
class _Junction:
    """Where a side branch of the maze leaves the passage, and the branch's size.

    Attributes:
        point: (3,) the passage's centre line at the junction.
        forward: (3,) horizontal unit vector along the passage.
        left: (3,) horizontal unit vector to the passage's left.
        passage_half_width: the passage's half-width there, metres.
        half_width: the branch's half-width, metres.
        half_height: the branch's half-height, metres.
        side: +1 when the branch leaves to the left, -1 to the right.
    """

    point: np.ndarray
    forward: np.ndarray
    left: np.ndarray
    passage_half_width: float
    half_width: float
    half_height: float
    side: float


def _side_branch(
    rng: np.random.Generator,
    at: _Junction,
    shallow: bool,
    tubes: Sequence[tuple[np.ndarray, np.ndarray]],
    gap: float,
    exit_y: float,
) -> tuple[Branch, np.ndarray] | None:
    """A blind branch from ``at`` and its own part (past the passage it leaves), keeping
    ``gap`` metres of rock from each of ``tubes`` (the passage and the branches placed so
    far) and clear of the exit plane at ``exit_y``; None when 200 tries find no room.

    A ``shallow`` branch leaves at 24-38 degrees, in view as the vehicle comes up to the
    junction; the others leave steeply, at 35-90; after 100 tries, at any angle.
    """
    hw, hh = at.half_width, at.half_height
    for attempt in range(200):
        low, high = (24.0, 38.0) if shallow else (35.0, 90.0)
        angle = math.radians(rng.uniform(low, high) if attempt < 100 else rng.uniform(24, 90))
        clear_from = (at.passage_half_width + hw + gap) / math.sin(angle)
        blind = rng.uniform(max(6.0, clear_from + 2.0), max(15.0, clear_from + 2.0))
        branch = _blind_tube(rng, at.point, at.forward, at.left, at.side * angle, blind, hw, hh)
        own = _own_part(branch, clear_from)
        if (
            _keeps_rock(own, hw, tubes, gap)
            and branch.centreline[:, 1].min() > exit_y + hw + gap + 1.5
        ):
            return branch, own
    return None


def maze(rng: np.random.Generator, seed: int, knobs: Mapping[str, float]) -> Layout:
    """maze: a passage with blind side branches, the tempting ones as wide as the way on."""
    count = int(knobs["branches"])
    length = float(rng.integers(48, 56) + 3 * count)  # 60-67 m with the default 4 branches
    s = np.arange(-4.0, length + 4.0, 0.25)
    x = _straighten_ends(s, 1.5 * _smooth_noise(s, 18.0, rng), length)
    z = _straighten_ends(s, 0.6 * _smooth_noise(s, 14.0, rng), length)
    points = np.stack([x, -s, z], axis=1)
    half_w = 2.9 + 0.3 * _smooth_noise(s, 10.0, rng)
    half_h = 2.7 + 0.2 * _smooth_noise(s, 10.0, rng)
    roughness = knobs["roughness_m"]
    gap = 1.0 + 3.0 * roughness  # rock between two passages, against 3 sigma of wall noise
    exit_y = -length
    main = (points, half_w)
    placed: list[tuple[np.ndarray, np.ndarray]] = []  # each branch's own part
    branches: list[Branch] = []
    side = 1.0 if rng.random() < 0.5 else -1.0
    # Junctions spread from 10 m to 22 m before the exit (a single one halfway along).
    stations = np.linspace(10.0, length - 22.0, count) if count > 1 else [length / 2 - 6] * count
    for k, station in enumerate(stations):
        j = int(np.searchsorted(s, station + rng.uniform(-1.5, 1.5)))
        forward, left = _heading_left(points[j + 1] - points[j - 1])
        # Every other branch as wide as the passage or wider: the tempting ones.
        factor = rng.uniform(1.0, 1.2) if k % 2 == 0 else rng.uniform(0.7, 0.95)
        hw, hh = factor * half_w[j], rng.uniform(0.85, 1.05) * half_h[j]
        junction = _Junction(points[j], forward, left, half_w[j], hw, hh, side)
        # The third of up to 4 (a wide one) leaves at a shallow angle, the real temptation
        # (with 5, the junctions are too close for its length).
        found = _side_branch(rng, junction, k == 2 and count <= 4, [main, *placed], gap, exit_y)
        if found is None:  # not met in seeds 0-399 and 1000-1399 at 4 or 5 branches, 0.3 or 0.6 m
            raise ScenarioError(
                f"maze seed {seed}: no room for side branch {k + 1} of {count}; "
                "try fewer branches or smoother walls"
            )
        branch, own = found
        branches.append(branch)
        placed.append((own, np.full(len(own), hw)))
        side = -side
    # A ceiling half-tube and a notch, on stretches blind to the junctions: no clue.
    shapes = rng.spawn(1)[0]
    channel = _stretch(shapes, 2.0, length - 4.0, (15.0, 30.0))
    section = _notch(
        shapes, s, _ceiling_channel(shapes, s, Section.plain(len(s)), *channel), 4.0, length - 6.0
    )
    return _layout_from_profiles(
        s,
        points,
        half_w,
        half_h,
        length,
        seed,
        roughness=roughness,
        branches=tuple(branches),
        section=section,
        scallops=shapes.uniform(*SCALLOPS_M),
        steps_per_m=4.0,
        description=f"a {length:.0f} m phreatic passage with {count} blind side branches, "
        "every other one as wide as the way on or wider; one exit",
    )


# The long cave's plan (metres along the passage): leg A runs along -y with constrictions
# (S1, 0-35), a rise and fall with two more (S2, from 35 on) and a frontal and a lateral
# boulder (S3, 70-100). Two sharp 90-degree bends 16 m apart turn it around (S4), and leg
# B winds back along +y among rocks (S5) to an exit 12 m of passage beyond the start's
# closed end (14 m in y: the rounded bends save 2 m), which keeps that end behind the exit
# plane. Folded so, 228 m fit a grid of about
# 30 x 120 x 15 m: 7 M voxels, which mesh in seconds.
_LEG_A, _ACROSS, _PAST_START = 100.0, 16.0, 12.0
_LONG = _LEG_A + _ACROSS + (_LEG_A + _PAST_START)
_LEG_B = _LEG_A + _ACROSS  # where leg B begins


def _long_centreline(
    rng: np.random.Generator, u: np.ndarray, side: float, undulation: float
) -> tuple[np.ndarray, float]:
    """(n, 3) points at stations ``u``, turning toward ``side`` (+-x), and the period of
    the rise and fall (30-34 m, one full swing of ``undulation`` metres peak to peak)."""
    past = float(u[-1]) - _LEG_B + 10.0  # leg B, long enough for every station
    corners = np.array(
        [[0.0, -u[0], 0.0], [0.0, -_LEG_A, 0.0], [side * _ACROSS, -_LEG_A, 0.0],
         [side * _ACROSS, past - _LEG_A, 0.0]]
    )  # fmt: skip
    x, y, _ = along(rounded_corners(corners, BEND_RADIUS_M), u - u[0]).T
    x = x + 1.2 * _smooth_noise(u, 16.0, rng) * _window(u, 4.0, 62.0)
    leg_b = _window(u, _LEG_B + 6, _LONG - 8)  # straight out of the bend and to the exit
    x = x + side * 1.5 * _smooth_noise(u, 14.0, rng) * leg_b
    period = rng.uniform(30.0, 34.0)
    wave = cpu_independent(math.sin, 2 * np.pi * (u - 35) / period)
    swing = np.where((u >= 35.0) & (u <= 35.0 + period), wave, 0)
    z = undulation / 2 * gaussian_smooth(swing, 4)
    z = z + 1.0 * _smooth_noise(u, 11.0, rng) * leg_b
    return np.stack([x, y, z], axis=1), period


def long(rng: np.random.Generator, seed: int, knobs: Mapping[str, float]) -> Layout:
    """long: 228 m chaining the five topologies, folded back on itself by two bends."""
    u = np.arange(-4.0, _LONG + 4.0, 0.25)
    side = 1.0 if rng.random() < 0.5 else -1.0
    narrowest, undulation = knobs["constriction_m"], knobs["undulation_m"]
    points, period = _long_centreline(rng, u, side, undulation)
    # Each stretch as wide and high as its family, eased into the next over a few metres.
    stretches = [u < 35, u < 70, u <= _LEG_A, u < _LEG_B]
    base_w = gaussian_smooth(np.select(stretches, [3.5, 3.2, 3.5, 2.9], 3.3), 8)
    base_h = gaussian_smooth(np.select(stretches, [3.0, 2.9, 3.0, 2.7], 2.8), 8)
    base_w = base_w + 0.7 * _smooth_noise(u, 9.0, rng) * (u >= _LEG_B)
    base_h = base_h + 0.3 * _smooth_noise(u, 9.0, rng) * (u >= _LEG_B)
    # Necks on the 0.25 m grid, where the stretch is flat: the narrowest is the knob's.
    necks_1 = [round(4 * (c + rng.uniform(-2, 2))) / 4 for c in (9.0, 18.0, 27.0)]
    necks_2 = [round(4 * (35 + period * f + rng.uniform(-1.5, 1.5))) / 4 for f in (0.25, 0.75)]
    half_w = base_w - np.maximum(
        _dips(u, necks_1, _dip_depth(3.5, narrowest)),
        _dips(u, necks_2, _dip_depth(3.2, narrowest)),
    )
    half_h = base_h - np.maximum(_dips(u, necks_1[1:2], 1.0), _dips(u, necks_2, 0.8))

    scale = knobs["obstacle_scale"]
    wall = 1.0 if rng.random() < 0.5 else -1.0  # S3's: frontal off one wall, lateral from the other
    frontal_y, lateral_y = -rng.uniform(76, 80), -rng.uniform(86, 90)
    stations = np.linspace(_LEG_B + 9, _LONG - 9, 8)
    shapes = rng.spawn(1)[0]
    frontal = _pile(shapes, -wall * 0.9, frontal_y, scale)
    lateral = _wall_block(shapes, wall * 2.2, lateral_y, scale)
    rocks = _rocks(rng, u, stations, points, half_w, half_h, scale, shapes)
    # Each stretch shaped as its family's: a half-tube and a notch in the first, keyholes
    # in the second, a silted floor under the boulders and stalactites in leg B.
    section = _ceiling_channel(
        shapes, u, Section.plain(len(u)), *_stretch(shapes, 2.0, 33.0, (15.0, 25.0))
    )
    section = _notch(shapes, u, section, 2.0, 33.0)
    section = _keyhole(shapes, u, section, 37.0, 68.0)
    section = replace(section, sediment=0.5 * _window(u, 72.0, _LEG_A))
    hanging = shapes.uniform(_LEG_B + 10, _LONG - 10, 6)
    speleothems = _speleothems(
        shapes, u, points, half_w, half_h, section, sorted(hanging), ["stalactite"] * 6
    )
    return _layout_from_profiles(
        u,
        points,
        half_w,
        half_h,
        _LONG,
        seed,
        roughness=knobs["roughness_m"],
        boulders=(*frontal, lateral, *rocks),
        section=section,
        speleothems=tuple(speleothems),
        scallops=shapes.uniform(*SCALLOPS_M),
        steps_per_m=3.0,
        description=f"a {_LONG:.0f} m cave chaining the five: constrictions to about "
        f"{narrowest:.1f} m, a rise and fall of about {undulation:g} m, a frontal and a "
        "lateral boulder, two sharp 90-degree bends that turn it around, then a winding "
        "passage with rocks",
    )
