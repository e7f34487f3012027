"""The cave line: a diver's guideline tied along a passage's way out (issue 49).

Flooded caves that divers visit carry a permanent guideline: a thin nylon line (2-4 mm,
white or yellow) run from the entrance along the main passage, tied off on rock every few
metres, along the floor or a little way up a wall, with line arrows (plastic triangles of
about 10 cm, clipped on it) pointing toward the nearest way out. A diver who loses the
way, or the visibility, follows it out; CavePI's vehicle follows one by segmenting it in
its camera frames.

`lay_guideline` lays one along a cave's centre line, from a metre behind the start to just
inside the exit, as a diver would tie it:

1. Stations every 3-6 m along the centre line (drawn from the cave's seed, on a stream of
   its own, so the cave itself is the same rock for rock with or without the line).
2. At each station the line is tied on rock: on the floor in the lowest channel near the
   middle (not on top of a boulder), or on a wall 0.5-1 m above that floor, around the
   knob that stands out most nearby, and never in the upper part of the passage, where
   divers and vehicles swim; a diver keeps to one side for a while and changes now and
   then. The tie is `TIE_OFFSET_M` off the rock, along its normal.
3. Each straight span between two ties must run clear of rock (a ray cast along it); a
   span that passes through a bulge of rock gets another tie between, on the side that
   clears it, split again until every span is clear; where the ties are too close to
   split, the line bends over the rock's edge, as a taut line lies over a block.
4. Arrows every 10-20 m along the line, one near each end and one at each junction (where
   a side passage leaves the way on), each pointing along the line toward the exit.

The line is a few millimetres across: it is no rock (it is never part of the mesh, and
collisions and clearance ignore it); the camera draws it at its true size
(`cavenav.sensors.guideline`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from cavenav.core.errors import ConfigError
from cavenav.world.mesh import CaveMesh
from cavenav.world.procedural import along, arc_length, arc_length_at
from cavenav.world.raycast import RayCaster

__all__ = [
    "ARROW_LENGTH_M",
    "ARROW_WIDTH_M",
    "GUIDELINE_COLOURS",
    "LINE_RADIUS_M",
    "Guideline",
    "GuidelineColour",
    "check_colour",
    "lay_guideline",
]

GuidelineColour = Literal["white", "yellow"]
# Diffuse albedo (R, G, B) of the line's nylon: white cave line is about as pale as paper;
# yellow reflects red and green and little blue.
GUIDELINE_COLOURS: dict[str, tuple[float, float, float]] = {
    "white": (0.8, 0.8, 0.8),
    "yellow": (0.8, 0.7, 0.1),
}
LINE_RADIUS_M = 0.0015  # a 3 mm line, the middle of the 2-4 mm divers use
TIE_OFFSET_M = 0.01  # how far off the rock a tie holds the line: a wrap around a knob
TIE_SPACING_M = (3.0, 6.0)  # between stations along the centre line
WALL_HEIGHT_M = (0.5, 1.0)  # a wall tie's height above the floor
SIDE_CHANGE = 0.2  # the chance that the next tie changes side (floor, left or right wall)
ARROW_SPACING_M = (10.0, 20.0)  # between arrows along the line
ARROW_LENGTH_M = 0.10  # a line arrow, tip to base
ARROW_WIDTH_M = 0.05  # across its base
BEHIND_START_M = 1.0  # where the line begins, behind the start along the centre line
BEFORE_EXIT_M = 0.5  # where it ends, before the exit
MIN_SPAN_M = 0.25  # stations closer than this are not split further
_SPLITS = 12  # how deep a span is split before the tie at its end is given up
_BISECTIONS = 10  # a line bent over an edge finds it to a thousandth of its lift
_REACH_M = 20.0  # no floor within this below the centre line: no tie there
_WALL_REACH_M = 5.0  # no wall this near across the passage (a side passage): tie on the floor
KNOB_REACH_M = 0.6  # how far along the passage a diver looks for a knob to tie to
CHANNEL_M = 0.2  # floor this near the lowest across the passage is still its channel
LOW = 0.7  # no tie higher than this share of the way from the floor to the centre line
_STREAM = 0x6C696E65  # "line": the line's own random stream beside the cave's
_STYLES = ("floor", "left", "right")
_UP = np.array([0.0, 0.0, 1.0])


def check_colour(colour: object, where: str = "guideline colour") -> GuidelineColour:
    """``colour`` if it is a guideline colour.

    Raises:
        ConfigError: another value, naming the colours there are.
    """
    if colour not in GUIDELINE_COLOURS:
        raise ConfigError(f"{where} {colour!r}: choose one of {', '.join(GUIDELINE_COLOURS)}")
    return colour  # type: ignore[return-value]


@dataclass(frozen=True, eq=False)
class Guideline:
    """A guideline in a cave: straight spans between tie-offs, and line arrows on it.

    Attributes:
        ties: (n, 3) float64 tie-off points from the start's end to the exit's, metres,
            and the edges the line bends over, each `TIE_OFFSET_M` off the rock; the
            line runs straight from each to the next.
        arrows: (a, 3) float64 where each arrow sits on the line.
        arrow_directions: (a, 3) float64 unit: along the line toward the exit.
        arrow_normals: (a, 3) float64 unit: the arrow's face, turned toward the middle of
            the passage (a diver clips it to be seen from there).
        colour: "white" or "yellow" (`GUIDELINE_COLOURS`).
        radius_m: the line's radius.
    """

    ties: np.ndarray
    arrows: np.ndarray
    arrow_directions: np.ndarray
    arrow_normals: np.ndarray
    colour: GuidelineColour = "white"
    radius_m: float = LINE_RADIUS_M

    @property
    def albedo(self) -> tuple[float, float, float]:
        """The line's and its arrows' diffuse albedo (R, G, B)."""
        return GUIDELINE_COLOURS[self.colour]

    @property
    def length_m(self) -> float:
        """The line's length from its first tie to its last."""
        return float(arc_length(self.ties)[-1])

    def arrow_triangles(self) -> np.ndarray:
        """(a, 3, 3) float64 each arrow as a triangle: its tip (toward the exit), then the
        two corners of its base, in the plane of the line and the arrow's face."""
        across = np.cross(self.arrow_normals, self.arrow_directions) * (ARROW_WIDTH_M / 2)
        tip = self.arrows + self.arrow_directions * (ARROW_LENGTH_M / 2)
        base = self.arrows - self.arrow_directions * (ARROW_LENGTH_M / 2)
        return np.stack([tip, base + across, base - across], axis=1)

    def to_dict(self) -> dict[str, Any]:
        """What summary.json records of the line."""
        return {
            "colour": self.colour,
            "ties": len(self.ties),
            "length_m": round(self.length_m, 2),
            "arrows": len(self.arrows),
        }


def lay_guideline(
    mesh: CaveMesh,
    centreline: np.ndarray,
    *,
    start_arc: float,
    seed: int,
    colour: str = "white",
    junctions: Sequence[float] = (),
) -> Guideline:
    """Lay a guideline along ``centreline`` (n, 3) from ``start_arc`` (the start's arc
    length along it) less `BEHIND_START_M` to its end, the exit (module docstring).

    Args:
        seed: the cave's seed: the same seed lays the same line.
        junctions: arc lengths along the centre line where side passages leave it; each
            gets an arrow.

    Raises:
        ConfigError: an unknown colour, or a passage with no rock to tie to.
    """
    colour = check_colour(colour)
    caster = RayCaster(mesh)
    path = np.asarray(centreline, np.float64)
    rng = np.random.default_rng([int(seed), _STREAM])
    first = max(float(start_arc) - BEHIND_START_M, 0.0)
    last = float(arc_length(path)[-1]) - BEFORE_EXIT_M
    stations = _stations(rng, first, last)
    plans = _plans(rng, len(stations))
    tied = (_Knot.tied(caster, path, s, p) for s, p in zip(stations, plans, strict=True))
    knots = [knot for knot in tied if knot is not None]
    if len(knots) < 2:
        raise ConfigError("no rock to tie a guideline to along this passage's centre line")
    knots = _clear(caster, path, knots)
    ties = np.array([knot.point for knot in knots])
    arrows, directions = _arrows(rng, ties, path, junctions)
    return Guideline(ties, arrows, directions, _facing(arrows, directions, path), colour)


def _stations(rng: np.random.Generator, first: float, last: float) -> list[float]:
    """Arc lengths of the stations: the first and last, and every 3-6 m between."""
    stations = [first]
    while (next_ := stations[-1] + rng.uniform(*TIE_SPACING_M)) < last - TIE_SPACING_M[0] / 2:
        stations.append(next_)
    return [*stations, last]


def _plans(rng: np.random.Generator, count: int) -> list[tuple[str, float]]:
    """Each station's side and wall height: a diver keeps to one side, changing now and
    then (`SIDE_CHANGE`). Two draws per station, whatever is drawn."""
    plans, style = [], _STYLES[int(rng.integers(3))]
    for _ in range(count):
        change, height = rng.uniform(), rng.uniform(*WALL_HEIGHT_M)
        if change < SIDE_CHANGE:
            other = 1 + int(2 * change / SIDE_CHANGE)  # either of the other two, evenly
            style = _STYLES[(_STYLES.index(style) + other) % 3]
        plans.append((style, float(height)))
    return plans


@dataclass(frozen=True)
class _Knot:
    """A tie-off: where along the centre line, how it was planned, and the point."""

    station: float
    plan: tuple[str, float]
    point: np.ndarray

    @classmethod
    def tied(
        cls, caster: RayCaster, path: np.ndarray, station: float, plan: tuple[str, float]
    ) -> _Knot | None:
        """The tie at ``station`` as ``plan`` says (a floor tie where a wall is out of
        reach); None where the rays find no rock."""
        point = _tie(caster, path, station, plan)
        if point is None and plan[0] != "floor":
            point = _tie(caster, path, station, ("floor", plan[1]))
        return None if point is None else cls(station, plan, point)


def _frame(path: np.ndarray, station: float) -> tuple[np.ndarray, np.ndarray]:
    """The centre-line point at ``station`` and the horizontal unit vector to its left."""
    ahead, behind = along(path, np.array([station + 0.25, station - 0.25]))
    tangent = ahead - behind
    left = np.array([-tangent[1], tangent[0], 0.0])
    norm = np.linalg.norm(left)
    left = left / norm if norm > 1e-9 else np.array([1.0, 0.0, 0.0])
    return along(path, np.array([station]))[0], left


def _tie(
    caster: RayCaster, path: np.ndarray, station: float, plan: tuple[str, float]
) -> np.ndarray | None:
    """The tie-off point ``plan`` puts at ``station``, around the knob of rock that stands
    out most within `KNOB_REACH_M` along the passage, as a diver picks one to tie to: on
    the floor where it lies lowest across the passage (the channel a line runs along, not
    the top of a boulder), or on the wall to the left or right at the plan's height above
    that floor (at most 0.4 of the way to the ceiling). None where no rock is found, or
    the tie would sit in the upper part of the passage (`LOW`): a line keeps out of the
    middle, where divers and vehicles swim."""
    centre, left = _frame(path, station)
    channel = _channel(caster, centre, left)
    floor = None if channel is None else _knob(caster, path, station, channel, -_UP, _REACH_M)
    if channel is None or floor is None:
        return None
    tie: np.ndarray | None = floor
    if plan[0] != "floor":
        ceiling = _hit(caster, centre, _UP, _REACH_M)
        room = (0.0 if ceiling is None else float(ceiling[2] - floor[2])) or _REACH_M
        base = channel + _UP * (floor[2] - channel[2] + min(plan[1], 0.4 * room))
        side = left if plan[0] == "left" else -left
        tie = _knob(caster, path, station, base, side, _WALL_REACH_M)
    low = floor[2] + LOW * (centre[2] - floor[2])
    return tie if tie is not None and tie[2] <= low else None


def _channel(caster: RayCaster, centre: np.ndarray, left: np.ndarray) -> np.ndarray | None:
    """The point at the height of ``centre`` above the lowest floor within 1.2 m of it
    across the passage (along ``left``; in the water, not through a wall), the nearest
    the middle of those within `CHANNEL_M` of the lowest; None where no floor is found."""
    starts = centre + np.outer([0.0, -0.6, 0.6, -1.2, 1.2], left)
    hits = _hits_from(caster, centre, starts, -_UP, _REACH_M)
    found = [(float(hit[2]), start) for start, hit in hits]
    if not found:
        return None
    lowest = min(z for z, _ in found)
    return next(start for z, start in found if z <= lowest + CHANNEL_M)


def _knob(
    caster: RayCaster,
    path: np.ndarray,
    station: float,
    origin: np.ndarray,
    direction: np.ndarray,
    reach: float,
) -> np.ndarray | None:
    """The tie (`_hit`) on the rock that stands out most toward ``origin`` among rays
    cast along ``direction`` from ``origin`` and from the same place moved along the
    centre line by up to `KNOB_REACH_M` either way (in the water, never past the exit)."""
    stations = station + KNOB_REACH_M * np.array([0.0, -0.5, 0.5, -1.0, 1.0])
    end = float(arc_length(path)[-1]) - BEFORE_EXIT_M / 2  # no knob past the exit
    shifts = along(path, np.clip(stations, 0.0, max(end, station)))
    starts = origin + shifts - shifts[0]
    found = [
        (float((hit - start) @ direction), hit)
        for start, hit in _hits_from(caster, origin, starts, direction, reach)
    ]
    return min(found, key=lambda pair: pair[0])[1] if found else None


def _hits_from(
    caster: RayCaster, origin: np.ndarray, starts: np.ndarray, direction: np.ndarray, reach: float
) -> list[tuple[np.ndarray, np.ndarray]]:
    """(start, `_hit`) for each of ``starts`` (k, 3) that the water reaches from ``origin``
    (no rock between) and whose ray along ``direction`` meets rock within ``reach``."""
    found = []
    for start in starts:
        hit = None if _blocked(caster, origin, start) else _hit(caster, start, direction, reach)
        if hit is not None:
            found.append((start, hit))
    return found


def _hit(
    caster: RayCaster, origin: np.ndarray, direction: np.ndarray, reach: float
) -> np.ndarray | None:
    """The point `TIE_OFFSET_M` off the rock the ray meets, along the rock's normal turned
    back toward the ray; None when no rock lies within ``reach``."""
    rays = np.concatenate([origin, direction]).astype(np.float32)[None]
    cast = caster.cast_raw_rays(np.ascontiguousarray(rays))
    distance = float(cast["t_hit"][0])
    if not distance < reach:
        return None
    normal = cast["primitive_normals"][0].astype(np.float64)
    if normal @ direction > 0:
        normal = -normal
    return origin + distance * direction + TIE_OFFSET_M * normal


def _blocked(caster: RayCaster, a: np.ndarray, b: np.ndarray) -> bool:
    """Whether rock lies on the straight span from ``a`` to ``b``."""
    span = b - a
    length = float(np.linalg.norm(span))
    if length < 1e-6:
        return False
    return bool(caster.first_hit(a, span / length) < length)


def _clear(caster: RayCaster, path: np.ndarray, knots: list[_Knot]) -> list[_Knot]:
    """``knots`` joined by spans clear of rock (`_joined`); a tie that no span reaches
    clear is left out, and so is one within `MIN_SPAN_M` of the tie before it where the
    line runs clear without it."""
    done = [knots[0]]
    for knot in knots[1:]:
        joined = _joined(caster, path, done[-1], knot)
        if not joined and len(done) > 1:  # stuck in a pocket: try from the tie before
            joined = _joined(caster, path, done[-2], knot)
            if joined:
                done.pop()
        done.extend(joined)
    kept = [done[0]]
    for k, knot in enumerate(done[1:-1], 1):
        close = np.linalg.norm(knot.point - kept[-1].point) < MIN_SPAN_M
        if not (close and not _blocked(caster, kept[-1].point, done[k + 1].point)):
            kept.append(knot)
    return [*kept, done[-1]] if len(done) > 1 else kept


def _joined(caster: RayCaster, path: np.ndarray, a: _Knot, b: _Knot, depth: int = 0) -> list[_Knot]:
    """The ties after ``a`` up to ``b`` whose spans are clear of rock: ``b`` alone where
    the span from ``a`` is, else with ties between (`_between`), split in halves again
    until each span is clear (at most `_SPLITS` deep). What cannot be reached clear is
    left out: ``b``, or all."""
    if not _blocked(caster, a.point, b.point):
        return [b]
    middle = None if depth >= _SPLITS else _between(caster, path, a, b)
    if middle is None:
        return []
    first = _joined(caster, path, a, middle, depth + 1)  # ends at the middle, or before it
    if not first:
        return []
    return first + _joined(caster, path, first[-1], b, depth + 1)


def _between(caster: RayCaster, path: np.ndarray, a: _Knot, b: _Knot) -> _Knot | None:
    """A tie between ``a`` and ``b``: along the centre line on ``a``'s side, then ``b``'s,
    then the other, at the first of a few stations from half-way outward that clears both
    halves of the span, else one (the line then follows that wall or floor around the
    bulge); else, or where they are too close to split (`MIN_SPAN_M`), on the edge of the
    rock the span meets (`_on_edge`), over which a taut line would lie."""
    if b.station - a.station < 2 * MIN_SPAN_M:
        return _on_edge(caster, path, a, b)
    height = 0.5 * (a.plan[1] + b.plan[1])
    stations = a.station + (b.station - a.station) * np.array([0.5, 0.35, 0.65, 0.2, 0.8])
    found: list[_Knot] = []
    for style in dict.fromkeys([a.plan[0], b.plan[0], *_STYLES]):
        for station in stations:
            knot = _Knot.tied(caster, path, float(station), (style, height))
            if knot is None:
                continue
            halves = _blocked(caster, a.point, knot.point) + _blocked(caster, knot.point, b.point)
            if halves == 0:
                return knot
            if halves == 1:
                found.append(knot)
        if found:
            return found[0]
    return _on_edge(caster, path, a, b)


def _on_edge(caster: RayCaster, path: np.ndarray, a: _Knot, b: _Knot) -> _Knot | None:
    """The point where a taut line from ``a`` to ``b`` bends over the rock between them,
    `TIE_OFFSET_M` off its edge; None where none is found.

    Their midpoint is lifted toward the centre line, by bisection, just far enough that
    both halves run clear; the line then grazes the rock somewhere along them, and the
    bend is moved there, to the rock nearest the two halves.
    """
    station = 0.5 * (a.station + b.station)
    centre = along(path, np.array([station]))[0]
    middle = 0.5 * (a.point + b.point)

    def clear(point: np.ndarray) -> bool:
        return not (_blocked(caster, a.point, point) or _blocked(caster, point, b.point))

    low, high = 0.0, 1.0  # shares of the way from the midpoint to the centre line
    for _ in range(_BISECTIONS):
        half = (low + high) / 2
        point = middle + half * (centre - middle)
        low, high = (low, half) if clear(point) and not _blocked(caster, centre, point) else (half, high)  # fmt: skip  # noqa: E501
    bend = middle + high * (centre - middle)
    if not clear(bend):
        return None
    share = np.linspace(0.0, 1.0, 33)[:, None]
    samples = np.concatenate([a.point + share * (bend - a.point), bend + share * (b.point - bend)])
    nearest = samples[int(np.argmin(caster.distance(samples)))]
    rock = caster.closest_points(nearest[None])[0].astype(np.float64)
    away = nearest - rock
    edge = rock + TIE_OFFSET_M * away / max(float(np.linalg.norm(away)), 1e-9)
    return _Knot(station, a.plan, edge)  # its spans split further where still blocked


def _arrows(
    rng: np.random.Generator, ties: np.ndarray, path: np.ndarray, junctions: Sequence[float]
) -> tuple[np.ndarray, np.ndarray]:
    """The arrows' points on the line and their directions toward the exit: near each
    end, every 10-20 m between, and at the point of the line nearest each junction."""
    line = arc_length(ties)
    total = float(line[-1])
    places = [min(2.0, total / 4)]
    while (next_ := places[-1] + rng.uniform(*ARROW_SPACING_M)) < total - 1.5:
        places.append(next_)
    places.append(max(total - 1.5, places[0]))
    for station in junctions:
        centre = along(path, np.array([float(station)]))[0]
        places.append(arc_length_at(ties, centre))
    places = sorted(places)
    kept = [p for k, p in enumerate(places) if k == 0 or p - places[k - 1] > 1.0]
    span = np.clip(np.searchsorted(line, kept, side="right") - 1, 0, len(ties) - 2)
    directions = ties[span + 1] - ties[span]
    directions /= np.maximum(np.linalg.norm(directions, axis=1, keepdims=True), 1e-12)
    return along(ties, np.array(kept)), directions


def _facing(arrows: np.ndarray, directions: np.ndarray, path: np.ndarray) -> np.ndarray:
    """(a, 3) each arrow's face normal: toward the nearest centre-line point, across the
    line (up, or along x where the line runs straight up, where it runs toward it)."""
    dense = along(path, np.arange(0.0, float(arc_length(path)[-1]), 0.25))
    nearest = dense[np.argmin(((arrows[:, None] - dense[None]) ** 2).sum(axis=2), axis=1)]
    toward = nearest - arrows
    toward -= (toward * directions).sum(axis=1, keepdims=True) * directions
    norm = np.linalg.norm(toward, axis=1, keepdims=True)
    upright = _UP - directions[:, 2:3] * directions
    size = np.linalg.norm(upright, axis=1, keepdims=True)
    upright = np.where(size > 1e-6, upright / np.maximum(size, 1e-12), [1.0, 0.0, 0.0])
    return np.where(norm > 1e-6, toward / np.maximum(norm, 1e-12), upright)
