"""Scenarios: a cave mesh with a start pose and an exit portal.

The five topologies of SPEC section 6 are families of caves registered by name (S1-S5): a
seed draws one cave of the family, and a `Difficulty` turns its knobs (the width of the
constrictions, the angle of the bend, the number of boulders, ...). Three harder families
follow them: ``crawl`` (a crawlway too narrow for any standoff), ``maze`` (blind side
branches that look like the way on) and ``long`` (230 m chaining the five, with a
`Scenario.step_budget` to match). Seeds in
`HELD_OUT_SEEDS` are the test split. Any user mesh becomes a scenario through a small TOML
file, and so does a family at a chosen difficulty (see `load_scenario_file`).
"""

from __future__ import annotations

import hashlib
import json
import math
import numbers
import tomllib
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field, fields, replace
from functools import cached_property
from pathlib import Path
from typing import Annotated, Any, Literal, TypeVar

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator
from scipy.spatial import cKDTree

from cavenav.errors import ConfigError, MeshError, ScenarioError
from cavenav.types import Pose
from cavenav.world.collision import VehicleBody
from cavenav.world.mesh import CaveMesh, load_mesh, sphere_directions
from cavenav.world.procedural import (
    Boulder,
    Branch,
    PassageSpec,
    build_cave,
    cpu_independent,
    gaussian_smooth,
    resample,
)
from cavenav.world.raycast import RayCaster
from cavenav.world.units import check_units

__all__ = [
    "HELD_OUT_SEEDS",
    "KNOBS",
    "SCENARIOS",
    "Difficulty",
    "ExitPortal",
    "Scenario",
    "check_scenario",
    "difficulty_table",
    "load_scenario",
    "load_scenario_file",
    "parse_difficulty",
    "procedural_scenario",
    "validate_start",
]


@dataclass(frozen=True)
class ExitPortal:
    """A disc-bounded plane across a portal of the cave: an exit (the goal) or an entrance.

    The vehicle has passed it once its centre lies on the outer side of the plane through
    ``point`` with outward ``normal``, no farther than ``radius`` from ``point`` across it.
    """

    point: tuple[float, float, float]
    normal: tuple[float, float, float]
    radius: float

    def reached(self, position: np.ndarray) -> bool:
        p = np.asarray(position, np.float64) - np.asarray(self.point)
        n = np.asarray(self.normal, np.float64)
        n = n / np.linalg.norm(n)
        along = float(p @ n)
        across = float(np.linalg.norm(p - along * n))
        return along >= 0.0 and across <= self.radius

    def distance(self, position: np.ndarray) -> float:
        """Signed distance of ``position`` before the exit plane (positive = not there yet)."""
        n = np.asarray(self.normal, np.float64)
        return float(-(np.asarray(position) - np.asarray(self.point)) @ (n / np.linalg.norm(n)))


@dataclass(frozen=True, eq=False)
class Scenario:
    """A cave to fly: mesh (metres, z up), start pose and one or more exit portals.

    Attributes:
        centreline: (n, 3) points along the passage from the start to the exit, where
            known (procedural caves, mesh files that give one); progress is then
            measured along it.
        difficulty: the knobs a procedural cave was built with (``Difficulty()`` for the
            family's defaults); None for a cave read from a mesh.
        entrances: portals the vehicle came in by (normals pointing out of the cave):
            leaving through one is never success. Procedural caves are closed behind the
            start and have none.
        step_budget: the number of steps a fair episode of this cave gets, for a cave
            too long for the SPEC's 150 (the harder families: a few steps per metre of
            passage, see their builders); None leaves the caller's default of 150.
    """

    name: str
    mesh: CaveMesh
    start: Pose
    exits: tuple[ExitPortal, ...]
    description: str = ""
    seed: int | None = None
    optics: Mapping[str, Any] = field(default_factory=dict)  # the file's [optics] table
    centreline: np.ndarray | None = None
    difficulty: Difficulty | None = None
    sensors: Mapping[str, Any] = field(default_factory=dict)  # the file's [sensors] table
    entrances: tuple[ExitPortal, ...] = ()
    step_budget: int | None = None

    def exited(self, position: np.ndarray) -> bool:
        """Whether ``position`` lies past any exit portal."""
        return any(portal.reached(position) for portal in self.exits)

    def left_through_entrance(self, position: np.ndarray) -> bool:
        """Whether ``position`` lies past any entrance portal: out the way it came in."""
        return any(portal.reached(position) for portal in self.entrances)

    def exit_distance(self, position: np.ndarray) -> float:
        """Distance still to go before the nearest exit plane (negative once past it)."""
        return min(portal.distance(position) for portal in self.exits)

    def progress(self, position: np.ndarray) -> float:
        """Metres made good from the start toward the exit.

        Along the centre line where there is one (the arc length of the nearest point on
        it), so a bend counts what was flown around it; otherwise how much nearer the
        nearest exit plane is than from the start.
        """
        if self.centreline is None:
            return self.exit_distance(self.start.position) - self.exit_distance(position)
        return _arc_length_at(self.centreline, np.asarray(position, np.float64)) - self._start_arc

    @cached_property
    def _start_arc(self) -> float:
        """Arc length of the start along the centre line: asked for at every step."""
        assert self.centreline is not None
        return _arc_length_at(self.centreline, self.start.position)

    @property
    def passage_length_m(self) -> float:
        """Progress needed to reach the exit: the centre line's length, or the start's
        distance to the nearest exit plane."""
        if self.centreline is None:
            return self.exit_distance(self.start.position)
        return float(np.linalg.norm(np.diff(self.centreline, axis=0), axis=1).sum()) - (
            _arc_length_at(self.centreline, self.start.position)
        )


def _arc_length_at(polyline: np.ndarray, point: np.ndarray) -> float:
    """Arc length along ``polyline`` (n, 3) of its point nearest ``point`` (3,)."""
    a, b = polyline[:-1], polyline[1:]
    seg = b - a
    length2 = np.maximum((seg**2).sum(axis=1), 1e-12)
    t = np.clip(((point - a) * seg).sum(axis=1) / length2, 0.0, 1.0)
    gap = np.linalg.norm(a + t[:, None] * seg - point, axis=1)
    k = int(np.argmin(gap))
    lengths = np.sqrt(length2)
    return float(lengths[:k].sum() + t[k] * lengths[k])


# ------------------------------------------------------------------ difficulty

HELD_OUT_SEEDS = range(1000, 2000)
"""Cave seeds of the test split, which nobody tunes on.

Seeds 0-999 are for development: tuning prompts, pilots and thresholds, and training (the
Gymnasium environment draws its caves below ``cavenav.env.TRAINING_SEEDS``, which is 1000
for this reason). The numbers a report states come from seeds of this range, so they
measure caves no choice was fitted to. The split is the same for every family and every
difficulty: S1 at seed 1234 is held out however hard it is made.
"""


@dataclass(frozen=True)
class Difficulty:
    """Knobs that make a cave family harder or easier; ``None`` keeps the family's default.

    ``Difficulty()`` builds exactly the caves of the plain families, seed for seed and bit
    for bit. A knob belongs to some families only (a bend angle means nothing in a straight
    passage), and setting one that the family lacks is refused rather than ignored, so that
    a sweep never reports a difficulty it did not fly. Each cell gives the family's default
    and the values it accepts; '-' where the family has no such knob:

    | family | constriction_m | undulation_m | bend_deg | obstacles | obstacle_scale | branches | roughness_m |
    | --- | --- | --- | --- | --- | --- | --- | --- |
    | S1 | 3.6 [1, 7] | - | - | - | - | - | 0.3 [0, 1] |
    | S2 | 3.8 [1, 6.4] | 4 [0, 8] | - | - | - | - | 0.3 [0, 1] |
    | S3 | - | - | - | 2 [0, 8] | 1 (0, 1.5] | - | 0.3 [0, 1] |
    | S4 | - | - | 90 (0, 150] | - | - | - | 0.3 [0, 1] |
    | S5 | - | - | - | 7 [0, 20] | 1 (0, 1.5] | - | 0.3 [0, 1] |
    | crawl | 1.5 [1, 2.5] | - | - | - | - | - | 0.08 [0, 0.15] |
    | maze | - | - | - | - | - | 4 [0, 5] | 0.3 [0, 0.6] |
    | long | 3.6 [1, 6.4] | 4 [0, 8] | - | - | 1 (0, 1.5] | - | 0.3 [0, 1] |

    Why these limits: a constriction under 1 m leaves the 0.46 x 0.34 m vehicle too little
    room once the rough walls bulge into it, and one wider than the passage would be a
    bulge; undulations of more than 8 m peak to peak climb at over 40 degrees (slopes reach
    atan(pi * undulation_m / 30): 23 degrees at the default 4 m, 32 at 6 m); a bend past
    150 degrees folds the two legs into one chamber (beyond about 130 degrees the first leg
    is shortened so that its closed end stays behind the exit plane); S3 has room for 8
    boulders in its 45 m and S5 for 20 in its 60 m; boulders grown past 1.5 times close the
    passage. Above about 0.6 m of roughness the walls may pinch narrow constrictions shut.
    The crawl is 1.7-2.5 m across between its pinches, so its pinches stop at 2.5 m, and
    its walls stay smooth (at most 0.15 m of roughness: 3 standard deviations on both walls
    still leave a 1 m pinch 0.1 m); the maze has room for 5 branches along its 60-70 m,
    with at least 1 + 3 x roughness_m of rock around each, hence its 0.6 m of roughness.

    Attributes:
        constriction_m: width of the narrowest constrictions in metres (S1, S2, long's
            five): the dips are made as deep as it takes to leave this width (the height
            is unchanged). crawl: the width of its three pinches, the narrowest it gets.
        undulation_m: peak-to-peak height of the vertical undulations in metres (S2,
            long's rise and fall).
        bend_deg: the turn of the bend in degrees (S4): the second leg runs along x and
            the first comes in at this angle to it.
        obstacles: number of boulders. S3: alternately frontal (in line with the start)
            and lateral (from the other wall), spread from 13 m to 41 m. S5: rocks on the
            walls and floor, spread evenly.
        obstacle_scale: factor on every boulder's semi-axes, not on its centre (S3, S5,
            long).
        branches: number of blind side branches of the maze, alternately left and right,
            every other one as wide as the way on or wider.
        roughness_m: amplitude (standard deviation) of the wall noise in metres, every
            family: `PassageSpec.roughness`.
    """  # noqa: E501 - the table's header row, kept equal to difficulty_table()

    constriction_m: float | None = None
    undulation_m: float | None = None
    bend_deg: float | None = None
    obstacles: int | None = None
    obstacle_scale: float | None = None
    branches: int | None = None
    roughness_m: float | None = None

    def __post_init__(self) -> None:
        # Counts are stored as int and every other knob as float, so that 2 and 2.0 give
        # the same cave digest and the same summary.json.
        for name, value in self.to_dict().items():
            integer = name in _COUNT_KNOBS
            kind = numbers.Integral if integer else numbers.Real
            if isinstance(value, bool) or not isinstance(value, kind):
                what = "a whole number" if integer else "a number"
                raise ScenarioError(f"difficulty {name} must be {what}, not {value!r}")
            if not math.isfinite(value):
                raise ScenarioError(f"difficulty {name} must be finite, not {value!r}")
            object.__setattr__(self, name, int(value) if integer else float(value))

    def __repr__(self) -> str:  # the knobs that are set, as one would write them
        knobs = ", ".join(f"{k}={v!r}" for k, v in self.to_dict().items())
        return f"Difficulty({knobs})"

    def to_dict(self) -> dict[str, float]:
        """The knobs that are set, in table order: what summary.json and sweep.json record."""
        return {f.name: v for f in fields(self) if (v := getattr(self, f.name)) is not None}

    @classmethod
    def from_dict(cls, values: Mapping[str, Any]) -> Difficulty:
        """The inverse of `to_dict`, also reading a scenario file's ``[difficulty]`` table.

        Raises:
            ConfigError: a key that is no knob, naming it and the knobs there are.
            ScenarioError: a value of the wrong type.
        """
        for key in values:
            if key not in KNOBS:
                raise ConfigError(f"unknown difficulty knob '{key}'; the knobs are {_KNOB_LIST}")
        return cls(**values)

    def updated(self, other: Difficulty) -> Difficulty:
        """This difficulty with every knob that ``other`` sets taken from ``other``: a
        scenario file's knobs overridden from the command line."""
        return replace(self, **other.to_dict())

    @property
    def tag(self) -> str:
        """A short name for the knobs that are set ('' for none): keeps harder caves apart
        from the plain ones by mesh name, in the cache and in the run records."""
        if not self.to_dict():
            return ""
        text = json.dumps(self.to_dict(), sort_keys=True)
        return "d" + hashlib.sha256(text.encode()).hexdigest()[:8]


KNOBS: tuple[str, ...] = tuple(f.name for f in fields(Difficulty))
_KNOB_LIST = ", ".join(KNOBS)
_COUNT_KNOBS = frozenset({"obstacles", "branches"})  # whole numbers; the rest are real numbers


def parse_difficulty(items: Sequence[str]) -> Difficulty:
    """Read ``["constriction_m=3.0", "obstacles=4"]``, the command line's ``--difficulty``.

    Raises:
        ConfigError: an item that is not KEY=VALUE, an unknown key, a value that is not a
            number (a whole number for counts), or a key given twice; one line each.
    """
    values: dict[str, float] = {}
    for item in items:
        key, sep, text = (part.strip() for part in item.partition("="))
        if not sep or not key or not text:
            raise ConfigError(f"difficulty '{item}': write KEY=VALUE, e.g. constriction_m=2.4")
        if key not in KNOBS:
            raise ConfigError(f"unknown difficulty knob '{key}'; the knobs are {_KNOB_LIST}")
        if key in values:
            raise ConfigError(f"difficulty knob '{key}' is given twice")
        integer = key in _COUNT_KNOBS
        try:
            values[key] = int(text) if integer else float(text)
        except ValueError:
            what = "a whole number" if integer else "a number"
            raise ConfigError(f"difficulty {key}={text}: {key} takes {what}") from None
    return Difficulty.from_dict(values)


@dataclass(frozen=True)
class _Range:
    """A family's default for one knob and the values it accepts."""

    default: float
    low: float
    high: float
    low_open: bool = False  # (low, high] instead of [low, high]

    def admits(self, value: float) -> bool:
        return (value > self.low if self.low_open else value >= self.low) and value <= self.high

    def __str__(self) -> str:
        return f"{'(' if self.low_open else '['}{self.low:g}, {self.high:g}]"


def difficulty_table() -> str:
    """The knob table in Markdown: each family's default and range, '-' where it has none.

    The same table stands in `Difficulty`'s docstring and in the README, and a test keeps
    them equal to this one.
    """
    lines = ["| family | " + " | ".join(KNOBS) + " |", "|" + " --- |" * (len(KNOBS) + 1)]
    for name, family in SCENARIOS.items():
        cells = [
            f"{family.knobs[k].default:g} {family.knobs[k]}" if k in family.knobs else "-"
            for k in KNOBS
        ]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


# ------------------------------------------------------------------ procedural families


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
    the axis the grid is cut across, over the last 8 m. The start is at the origin."""
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


@dataclass(frozen=True)
class _Layout:
    """A generated passage before meshing: spec plus where the vehicle starts.

    ``step_budget`` is `Scenario.step_budget`: None for S1-S5, which the SPEC's 150
    steps fit.
    """

    spec: PassageSpec
    start: Pose
    description: str
    step_budget: int | None = None


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
    start_offset: tuple[float, float, float] = (0.0, 0.0, 0.0),
    steps_per_m: float | None = None,
    description: str = "",
) -> _Layout:
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
    )
    budget = None
    if steps_per_m is not None:
        passage = np.linalg.norm(np.diff(points[start_index : exit_index + 1], axis=0), axis=1)
        budget = 10 * math.ceil(steps_per_m * float(passage.sum()) / 10)
    return _Layout(spec, start, description, budget)


def _s1(rng: np.random.Generator, seed: int, knobs: Mapping[str, float]) -> _Layout:
    length = 55.0
    s = np.arange(-4.0, length + 4.0, 0.25)
    phase = 2 * np.pi * s / rng.uniform(26, 34) + rng.uniform(0, 6.3)
    x = _straighten_ends(s, 1.6 * cpu_independent(math.sin, phase), length)
    z = _straighten_ends(s, 0.5 * _smooth_noise(s, 12.0, rng), length)
    points = np.stack([x, -s, z], axis=1)
    necks = [c + rng.uniform(-2, 2) for c in (15.0, 29.0, 42.0)]
    half_w = 3.5 - _dips(s, necks, _dip_depth(3.5, knobs["constriction_m"]))
    half_h = 3.0 - _dips(s, necks[1:2], 1.0)
    return _layout_from_profiles(
        s,
        points,
        half_w,
        half_h,
        length,
        seed,
        roughness=knobs["roughness_m"],
        description="narrow passage with three constrictions to about "
        f"{knobs['constriction_m']:.1f} m",
    )


def _s2(rng: np.random.Generator, seed: int, knobs: Mapping[str, float]) -> _Layout:
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
    return _layout_from_profiles(
        s,
        points,
        half_w,
        half_h,
        length,
        seed,
        roughness=knobs["roughness_m"],
        description=f"narrow passage with vertical undulations of about "
        f"{knobs['undulation_m']:g} m and two constrictions",
    )


def _s3(rng: np.random.Generator, seed: int, knobs: Mapping[str, float]) -> _Layout:
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
    boulders = []
    for k in range(count):
        station = 14.5 + k * spacing
        if k % 2 == 0:  # frontal: at the start height, in line with the start near the wall
            jitter = min(1.5, spacing / 4)
            y = -rng.uniform(station - jitter, station + jitter)
            boulder = Boulder((-wall_side * 0.9, y, 0.0), _scaled((1.7, 1.5, 1.7), scale))
        else:  # lateral: jutting from the other wall
            jitter = min(2.0, spacing / 4)
            y = -rng.uniform(station - jitter, station + jitter)
            boulder = Boulder((wall_side * 3.6, y, -0.3), _scaled((2.3, 1.8, 1.9), scale))
        boulders.append(boulder)
    kinds = {0: "no obstacle", 1: "a frontal obstacle", 2: "a frontal and a lateral obstacle"}
    obstacles = kinds.get(count, f"{count} obstacles, alternately frontal and lateral")
    start = "start near the wall at the frontal obstacle's height" if count else "start near a wall"
    return _layout_from_profiles(
        s,
        points,
        half_w,
        half_h,
        length,
        seed,
        roughness=knobs["roughness_m"],
        boulders=tuple(boulders),
        start_offset=(-wall_side * 2.0, 0.0, 0.0),
        description=f"straight passage with {obstacles}; {start}",
    )


def _s4(rng: np.random.Generator, seed: int, knobs: Mapping[str, float]) -> _Layout:
    leg = 30.0
    side = 1.0 if rng.random() < 0.5 else -1.0
    bend = knobs["bend_deg"]
    # The grid is cut across the exit direction, which must be an axis: the second leg
    # runs along side * x and the first leg is turned instead. ``back`` points from the
    # corner up the first leg: +y for 90 degrees, tilted toward the second leg for less.
    tilt = math.radians(bend - 90.0)
    back = np.array([side * math.sin(tilt), math.cos(tilt), 0.0])
    # A hairpin's first leg reaches back toward the exit plane: past about 130 degrees it
    # is shortened so that its closed end (4 m behind the start, plus a wall) stays 7 m
    # behind that plane, and so on the 0.25 m grid, where the corner falls on a sample.
    reach = -math.cos(math.radians(bend))
    first = leg if reach <= 0 else min(leg, math.floor(4 * ((leg - 7.0) / reach - 4.0)) / 4)
    corner = np.array([0.0, -leg, 0.0])
    corners = np.array(
        [corner + (first + 4.0) * back, corner, corner + np.array([side * (leg + 4.0), 0, 0])]
    )
    points, s = resample(corners, 0.25)
    s = s - 4.0
    length = first + leg
    half_w = 2.9 + 0.3 * _smooth_noise(s, 10.0, rng)
    half_h = 2.7 + 0.2 * _smooth_noise(s, 10.0, rng)
    return _layout_from_profiles(
        s,
        points,
        half_w,
        half_h,
        length,
        seed,
        roughness=knobs["roughness_m"],
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
) -> list[Boulder]:
    """S5's rocks, one within 2 m of each station: every third on the floor, the others
    against a wall, 0.8-1.25 m across times ``scale``."""
    tangent = np.gradient(points, axis=0)
    boulders = []
    for k, at in enumerate(stations):
        i = int(np.searchsorted(s, at + rng.uniform(-2, 2)))
        t = tangent[i] / np.linalg.norm(tangent[i])
        left = np.array([-t[1], t[0], 0.0]) / max(np.hypot(t[0], t[1]), 1e-9)
        r = rng.uniform(0.8, 1.25)
        if k % 3 == 2:  # a rock on the floor
            centre = points[i] + np.array([0.0, 0.0, -half_h[i] + 0.3 * r])
            centre = centre + left * rng.uniform(-1.0, 1.0)
        else:  # a rock against a wall
            side = 1.0 if rng.random() < 0.5 else -1.0
            centre = points[i] + side * left * (half_w[i] - 0.2 * r)
            centre = centre + np.array([0.0, 0.0, rng.uniform(-0.8, 0.8)])
        boulders.append(Boulder(_vec3(centre), _scaled((r, r * 1.1, r * 0.9), scale)))
    return boulders


def _s5(rng: np.random.Generator, seed: int, knobs: Mapping[str, float]) -> _Layout:
    length = 60.0
    s = np.arange(-4.0, length + 4.0, 0.25)
    x, y = _winding(s, 0.55 * _smooth_noise(s, 14.0, rng), length)
    z = _straighten_ends(s, 1.2 * _smooth_noise(s, 11.0, rng), length)
    points = np.stack([x, y, z], axis=1)
    half_w = 3.3 + 0.7 * _smooth_noise(s, 9.0, rng)
    half_h = 2.8 + 0.3 * _smooth_noise(s, 9.0, rng)
    count, scale = int(knobs["obstacles"]), knobs["obstacle_scale"]
    stations = np.linspace(9.0, length - 9.0, count)
    boulders = _rocks(rng, s, stations, points, half_w, half_h, scale)
    return _layout_from_profiles(
        s,
        points,
        half_w,
        half_h,
        length,
        seed,
        roughness=knobs["roughness_m"],
        boulders=tuple(boulders),
        description="irregular winding passage with rocks spread along it"
        if count
        else "irregular winding passage",
    )


# ------------------------------------------------------------------ harder families


def _crawl(rng: np.random.Generator, seed: int, knobs: Mapping[str, float]) -> _Layout:
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
    return _layout_from_profiles(
        s,
        points,
        half_w,
        half_h,
        length,
        seed,
        roughness=knobs["roughness_m"],
        steps_per_m=7.0,
        description=f"crawlway: a {length:.0f} m winding passage 1.7-2.5 m across and "
        f"1.5-2.2 m high, pinched to {narrowest:.1f} m across in three places",
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


def _maze(rng: np.random.Generator, seed: int, knobs: Mapping[str, float]) -> _Layout:
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
        for attempt in range(200):
            # The third of up to 4 (a wide one) leaves at a shallow angle, in view as the
            # vehicle comes up to the junction: the real temptation (with 5, the junctions
            # are too close for its length). The others leave steeply; with no room, at
            # any angle.
            low, high = (24.0, 38.0) if k == 2 and count <= 4 else (35.0, 90.0)
            angle = math.radians(rng.uniform(low, high) if attempt < 100 else rng.uniform(24, 90))
            clear_from = (half_w[j] + hw + gap) / math.sin(angle)
            blind = rng.uniform(max(6.0, clear_from + 2.0), max(15.0, clear_from + 2.0))
            branch = _blind_tube(rng, points[j], forward, left, side * angle, blind, hw, hh)
            own = _own_part(branch, clear_from)
            if (
                _keeps_rock(own, hw, [main, *placed], gap)
                and branch.centreline[:, 1].min() > exit_y + hw + gap + 1.5
            ):
                break
        else:  # not met in seeds 0-399 and 1000-1399 at 4 or 5 branches and 0.3 or 0.6 m
            raise ScenarioError(
                f"maze seed {seed}: no room for side branch {k + 1} of {count}; "
                "try fewer branches or smoother walls"
            )
        branches.append(branch)
        placed.append((own, np.full(len(own), hw)))
        side = -side
    description = (
        f"a {length:.0f} m passage with {count} blind side branches, every other one as "
        "wide as the way on or wider; one exit"
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
        steps_per_m=4.0,
        description=description,
    )


def _window(u: np.ndarray, start: float, end: float) -> np.ndarray:
    """1 between stations ``start`` and ``end``, 0 outside, eased over about 2 m."""
    box = ((u >= start) & (u <= end)).astype(float)
    return gaussian_smooth(box, 2.0 / (u[1] - u[0]))


# The long cave's plan (metres along the passage): leg A runs along -y with constrictions
# (S1, 0-35), a rise and fall with two more (S2, from 35 on) and a frontal and a lateral
# boulder (S3, 70-100). Two sharp 90-degree bends 16 m apart turn it around (S4), and leg
# B winds back along +y among rocks (S5) to an exit 12 m beyond the start's closed end,
# which keeps that end behind the exit plane. Folded so, 228 m fit a grid of about
# 30 x 120 x 15 m: 7 M voxels, which mesh in seconds.
_LEG_A, _ACROSS, _PAST_START = 100.0, 16.0, 12.0
_LONG = _LEG_A + _ACROSS + (_LEG_A + _PAST_START)
_LEG_B = _LEG_A + _ACROSS  # where leg B begins


def _long_centreline(
    rng: np.random.Generator, u: np.ndarray, side: float, undulation: float
) -> tuple[np.ndarray, float]:
    """(n, 3) points at stations ``u``, turning toward ``side`` (+-x), and the period of
    the rise and fall (30-34 m, one full swing of ``undulation`` metres peak to peak)."""
    x = np.where(u <= _LEG_A, 0.0, side * np.minimum(u - _LEG_A, _ACROSS))
    y = np.where(u <= _LEG_A, -u, np.where(u < _LEG_B, -_LEG_A, u - _LEG_B - _LEG_A))
    x = x + 1.2 * _smooth_noise(u, 16.0, rng) * _window(u, 4.0, 62.0)
    leg_b = _window(u, _LEG_B + 6, _LONG - 8)  # straight out of the bend and to the exit
    x = x + side * 1.5 * _smooth_noise(u, 14.0, rng) * leg_b
    period = rng.uniform(30.0, 34.0)
    wave = cpu_independent(math.sin, 2 * np.pi * (u - 35) / period)
    swing = np.where((u >= 35.0) & (u <= 35.0 + period), wave, 0)
    z = undulation / 2 * gaussian_smooth(swing, 4)
    z = z + 1.0 * _smooth_noise(u, 11.0, rng) * leg_b
    return np.stack([x, y, z], axis=1), period


def _long(rng: np.random.Generator, seed: int, knobs: Mapping[str, float]) -> _Layout:
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
    frontal = Boulder((-wall * 0.9, -rng.uniform(76, 80), 0.0), _scaled((1.7, 1.5, 1.7), scale))
    lateral = Boulder((wall * 3.6, -rng.uniform(86, 90), -0.3), _scaled((2.3, 1.8, 1.9), scale))
    stations = np.linspace(_LEG_B + 9, _LONG - 9, 8)
    rocks = _rocks(rng, u, stations, points, half_w, half_h, scale)
    return _layout_from_profiles(
        u,
        points,
        half_w,
        half_h,
        _LONG,
        seed,
        roughness=knobs["roughness_m"],
        boulders=(frontal, lateral, *rocks),
        steps_per_m=3.0,
        description=f"a {_LONG:.0f} m cave chaining the five: constrictions to about "
        f"{narrowest:.1f} m, a rise and fall of about {undulation:g} m, a frontal and a "
        "lateral boulder, two sharp 90-degree bends that turn it around, then a winding "
        "passage with rocks",
    )


# Why each range ends where it does, for the message that refuses a value outside it.
_LIMITS = {
    "constriction_m": "under 1 m the 0.46 x 0.34 m vehicle has no room once the rough walls "
    "bulge in, and over the top a constriction would be wider than the passage",
    "undulation_m": "past 8 m peak to peak the slopes pass 40 degrees",
    "bend_deg": "past 150 degrees the two legs fold into one chamber",
    "obstacles": "counts start at 0, and more boulders do not fit along the passage",
    "obstacle_scale": "boulders grown past 1.5 times close the passage",
    "branches": "counts start at 0, and more branches do not fit along the passage",
    "roughness_m": "past 1 m the walls may close the passage (the crawl's past 0.15 m), and "
    "past 0.6 m the maze's branches would need more rock between them than there is room for",
}
_ROUGHNESS = _Range(0.3, 0.0, 1.0)  # PassageSpec.roughness: 0.3 m looks like rock
_OBSTACLE_SCALE = _Range(1.0, 0.0, 1.5, low_open=True)


@dataclass(frozen=True)
class _Factory:
    """One family: its builder, a line for listings, and its knobs with defaults and ranges.

    ``number`` seeds the family's generator with the cave seed: S1-S5 are 1-5, and a new
    family takes the next free number, so that no two families draw the same numbers.
    """

    name: str
    number: int
    build: Callable[[np.random.Generator, int, Mapping[str, float]], _Layout]
    summary: str
    knobs: Mapping[str, _Range]

    def resolve(self, difficulty: Difficulty | None = None) -> dict[str, float]:
        """Every knob of this family: ``difficulty``'s value where set, else the default.

        Raises:
            ScenarioError: a knob this family lacks, naming the families that have it, or
                a value outside the family's range, naming the range and why.
        """
        values = {key: knob.default for key, knob in self.knobs.items()}
        for key, value in (difficulty or Difficulty()).to_dict().items():
            if key not in self.knobs:
                owners = ", ".join(n for n, f in SCENARIOS.items() if key in f.knobs)
                raise ScenarioError(
                    f"difficulty knob {key} does not apply to {self.name} (it belongs to "
                    f"{owners}); {self.name} takes {', '.join(self.knobs)}"
                )
            if not self.knobs[key].admits(value):
                raise ScenarioError(
                    f"{self.name}: {key}={value:g} is outside {self.knobs[key]}: {_LIMITS[key]}"
                )
            values[key] = value
        return values

    def layout(self, seed: int, difficulty: Difficulty | None = None) -> _Layout:
        """The passage for ``seed`` before meshing (milliseconds; meshing takes seconds).

        The generator is seeded by the cave seed and the family's number alone, and the
        knobs add draws only after the plain family's, so ``Difficulty()`` gives the plain
        cave bit for bit.
        """
        knobs = self.resolve(difficulty)
        return self.build(np.random.default_rng([seed, self.number]), seed, knobs)


class _Families(Mapping[str, _Factory]):
    """The registered families by name, looked up whatever the case ("s1", "CRAWL").

    Iterates over the names as registered, in order: the SPEC's S1-S5, then the harder
    families.
    """

    def __init__(self, *families: _Factory) -> None:
        self._by_key = {family.name.casefold(): family for family in families}

    def __getitem__(self, name: str) -> _Factory:
        if not isinstance(name, str):
            raise KeyError(name)
        return self._by_key[name.casefold()]

    def __iter__(self) -> Iterator[str]:
        return (family.name for family in self._by_key.values())

    def __len__(self) -> int:
        return len(self._by_key)


SCENARIOS: Mapping[str, _Factory] = _Families(
    _Factory(
        "S1",
        1,
        _s1,
        "constrictions: narrow passage, clearance-aware planning",
        {"constriction_m": _Range(3.6, 1.0, 7.0), "roughness_m": _ROUGHNESS},
    ),
    _Factory(
        "S2",
        2,
        _s2,
        "undulations: narrow passage rising and falling, 3D manoeuvring",
        {
            "constriction_m": _Range(3.8, 1.0, 6.4),
            "undulation_m": _Range(4.0, 0.0, 8.0),
            "roughness_m": _ROUGHNESS,
        },
    ),
    _Factory(
        "S3",
        3,
        _s3,
        "obstacles: straight passage, frontal and lateral obstacle",
        {
            "obstacles": _Range(2, 0, 8),
            "obstacle_scale": _OBSTACLE_SCALE,
            "roughness_m": _ROUGHNESS,
        },
    ),
    _Factory(
        "S4",
        4,
        _s4,
        "bend: a sharp 90-degree turn",
        {"bend_deg": _Range(90.0, 0.0, 150.0, low_open=True), "roughness_m": _ROUGHNESS},
    ),
    _Factory(
        "S5",
        5,
        _s5,
        "irregular: winding passage with rocks spread along it",
        {
            "obstacles": _Range(7, 0, 20),
            "obstacle_scale": _OBSTACLE_SCALE,
            "roughness_m": _ROUGHNESS,
        },
    ),
    _Factory(
        "crawl",
        6,
        _crawl,
        "crawlway: 40-60 m winding passage 1.2-2.5 m across, no room for a standoff",
        {"constriction_m": _Range(1.5, 1.0, 2.5), "roughness_m": _Range(0.08, 0.0, 0.15)},
    ),
    _Factory(
        "maze",
        7,
        _maze,
        "maze: passage with blind side branches as wide as the way on; one exit",
        {"branches": _Range(4, 0, 5), "roughness_m": _Range(0.3, 0.0, 0.6)},
    ),
    _Factory(
        "long",
        8,
        _long,
        "long: 230 m chaining constrictions, undulations, boulders, bends and rocks",
        {
            "constriction_m": _Range(3.6, 1.0, 6.4),
            "undulation_m": _Range(4.0, 0.0, 8.0),
            "obstacle_scale": _OBSTACLE_SCALE,
            "roughness_m": _ROUGHNESS,
        },
    ),
)


def procedural_scenario(name: str, seed: int = 0, difficulty: Difficulty | None = None) -> Scenario:
    """Build a family of `SCENARIOS` (S1..S5, crawl, maze, long; any case) for ``seed`` at
    ``difficulty`` (None: the family's defaults).

    The same name, seed and difficulty always give the same cave, and the defaults give
    the plain family's. The scenario records the difficulty (``Difficulty()`` for the
    defaults); a harder cave's mesh name carries `Difficulty.tag`, and its mesh cache key
    differs anyway, since `PassageSpec.digest` hashes all the geometry.

    Raises:
        ScenarioError: an unknown name, a negative seed, or a knob the family lacks or
            outside its range.
    """
    if name not in SCENARIOS:
        raise ScenarioError(f"unknown scenario '{name}'; choose one of {', '.join(SCENARIOS)}")
    if not (isinstance(seed, int | np.integer) and seed >= 0):
        raise ScenarioError(f"seed {seed!r}: a cave's seed is a whole number, 0 or more")
    difficulty = Difficulty() if difficulty is None else difficulty
    family = SCENARIOS[name]
    key = family.name  # as registered: "S1", "crawl"
    layout = family.layout(seed, difficulty)
    spec = layout.spec
    tangent = spec.centreline[spec.exit_index + 1] - spec.centreline[spec.exit_index - 1]
    tangent /= np.linalg.norm(tangent)
    exit_ = ExitPortal(
        point=_vec3(spec.centreline[spec.exit_index]),
        normal=_vec3(tangent),
        radius=float(max(spec.half_width.max(), spec.half_height.max()) + 1.5),
    )
    mesh_name = f"{key}-seed{seed}" + (f"-{difficulty.tag}" if difficulty.tag else "")
    mesh = build_cave(spec, name=mesh_name)
    centreline = spec.centreline[: spec.exit_index + 1]
    return Scenario(
        key,
        mesh,
        layout.start,
        (exit_,),
        layout.description,
        seed,
        centreline=centreline,
        difficulty=difficulty,
        step_budget=layout.step_budget,
    )


# ------------------------------------------------------------------ scenario files


# Unknown keys are typos; NaN or inf in a position, angle or size is never meant.
_STRICT = ConfigDict(extra="forbid", allow_inf_nan=False)
# Every number is bounded by what a cave can hold, so that a typo (radius = 1e308) is
# refused here, naming its field, instead of overflowing the plots or the ray caster later.
# The bounds lie far beyond any real cave (README, "Bad input and faults").
_MAX_COORDINATE_M = 1e5  # 100 km from the origin, for positions, offsets, centre lines
_MAX_RADIUS_M = 1e4  # a portal 10 km across: the largest known chambers are under 1 km
_SCALE_RANGE = (1e-6, 1e3)  # metres per mesh unit: micrometres to kilometres
_MAX_STEP_BUDGET = 100_000  # more than a day of flight at a step a second
_MAX_PIXELS = 8192  # a camera 8192 px wide or high (8K video is 7680 x 4320)
# A pixel count: a TOML integer above 0 (strict: 160.0 and true are refused, not rounded).
_Pixels = Annotated[int, Field(strict=True, gt=0, le=_MAX_PIXELS)]
_Coordinate = Annotated[float, Field(ge=-_MAX_COORDINATE_M, le=_MAX_COORDINATE_M)]
_Point = tuple[_Coordinate, _Coordinate, _Coordinate]  # metres; also a normal's direction
_Yaw = Annotated[float, Field(ge=-360.0, le=360.0)]  # degrees: one turn either way
_Scale = Annotated[float, Field(ge=_SCALE_RANGE[0], le=_SCALE_RANGE[1])]


class _StartModel(BaseModel):
    model_config = _STRICT
    position: _Point
    yaw_deg: _Yaw = Field(0.0, description="0 heads along -y; positive turns left")


def _nonzero_normal(v: tuple[float, float, float], kind: str) -> tuple[float, float, float]:
    if math.hypot(*v) < 1e-9:
        raise ValueError(f"{kind} normal must not be the zero vector")
    return v


class _ExitModel(BaseModel):
    model_config = _STRICT
    point: _Point
    normal: _Point
    radius: float = Field(gt=0, le=_MAX_RADIUS_M)

    @field_validator("normal")
    @classmethod
    def _nonzero(cls, v: tuple[float, float, float]) -> tuple[float, float, float]:
        return _nonzero_normal(v, "exit")


class _EntranceModel(_ExitModel):
    """A portal the vehicle came in by: the same disc-bounded plane as an exit."""

    @field_validator("normal")
    @classmethod
    def _nonzero(cls, v: tuple[float, float, float]) -> tuple[float, float, float]:
        return _nonzero_normal(v, "entrance")


class _MeshPieceModel(BaseModel):
    """One piece of a chained cave: a mesh file, turned about the vertical, then moved."""

    model_config = _STRICT
    path: str = Field(description="relative to the scenario file")
    offset: _Point = Field((0.0, 0.0, 0.0), description="metres")
    yaw_deg: _Yaw = Field(0.0, description="about the vertical; positive turns +y toward -x")
    scale: _Scale | None = Field(None, description="metres per unit (default: the file's)")
    up_axis: Literal["x", "y", "z"] | None = None


class _SensorsModel(BaseModel):
    """A scenario file's [sensors] table: pixel counts; the lens stays the paper's."""

    model_config = _STRICT
    resolution: tuple[_Pixels, _Pixels] | None = Field(
        None, description="[width, height] of the forward camera (default [640, 480])"
    )
    sounder_resolution: tuple[_Pixels, _Pixels] | None = Field(
        None, description="[width, height] of each echo sounder's depth camera ([32, 24])"
    )


class _ScenarioFileModel(BaseModel):
    model_config = _STRICT
    name: str | None = None
    description: str = ""
    mesh: list[_MeshPieceModel] = Field(
        min_length=1, description='one file (mesh = "path") or [[mesh]] pieces to chain'
    )
    scale: _Scale | None = Field(None, description="metres per mesh unit, every piece")
    up_axis: Literal["x", "y", "z"] | None = None
    start: _StartModel
    exit: list[_ExitModel] = Field(description="one portal or a list of them")
    entrance: list[_EntranceModel] = Field(
        default_factory=list, description="the portals the vehicle came in by, if open"
    )
    centreline: list[_Point] | None = Field(
        None, min_length=2, description="[[x, y, z], ...] from the start to the exit"
    )
    step_budget: int | None = Field(
        None, strict=True, gt=0, le=_MAX_STEP_BUDGET, description="steps an episode gets (150)"
    )
    optics: dict[str, Any] = Field(
        default_factory=dict, description="water and light; see cavenav.sensors.optics"
    )
    sensors: _SensorsModel = Field(default_factory=_SensorsModel)

    @field_validator("exit", "entrance", mode="before")
    @classmethod
    def _as_list(cls, v: Any) -> Any:
        # One [exit] table or several [[exit]]: validated as a list either way, so that
        # an error names the field at fault, not "Input should be a valid dictionary".
        return [v] if isinstance(v, dict) else v

    @field_validator("mesh", mode="before")
    @classmethod
    def _as_pieces(cls, v: Any) -> Any:
        # mesh = "path" is one piece where the file's origin is the cave's.
        if isinstance(v, str):
            return [{"path": v}]
        if isinstance(v, dict):
            return [v]
        if not isinstance(v, list):
            raise ValueError('give mesh = "path", or [[mesh]] tables with path, offset, yaw_deg')
        return v

    @field_validator("centreline")
    @classmethod
    def _has_length(
        cls, v: list[tuple[float, float, float]] | None
    ) -> list[tuple[float, float, float]] | None:
        if v is not None and np.ptp(np.asarray(v), axis=0).max() < 1e-6:
            raise ValueError("the centre line's points all coincide: give the passage's")
        return v


class _FamilyFileModel(BaseModel):
    model_config = _STRICT
    name: str | None = None
    description: str = ""
    family: str = Field(
        description="a family (S1..S5, crawl, maze, long), built at the seed the file is given"
    )
    difficulty: dict[str, Any] = Field(default_factory=dict, description="see Difficulty")
    optics: dict[str, Any] = Field(
        default_factory=dict, description="water and light; see cavenav.sensors.optics"
    )
    sensors: _SensorsModel = Field(default_factory=_SensorsModel)

    @field_validator("family")
    @classmethod
    def _known(cls, v: str) -> str:
        if v not in SCENARIOS:
            raise ValueError(f"unknown family '{v}'; choose one of {', '.join(SCENARIOS)}")
        return SCENARIOS[v].name


def load_scenario_file(
    path: str | Path, seed: int = 0, difficulty: Difficulty | None = None
) -> Scenario:
    """Read a scenario TOML file: a mesh with its start and exits, or a cave family.

    A mesh file (its path relative to the file)::

        name = "my-cave"
        mesh = "meshes/cave.ply"
        scale = 1.0          # optional, metres per unit
        up_axis = "z"        # optional
        [start]
        position = [0.0, 8.0, 2.0]
        yaw_deg = 0.0        # 0 heads along -y
        [[exit]]                    # one or more portals
        point = [0.0, -10.0, 2.0]
        normal = [0.0, -1.0, 0.0]   # pointing out of the cave
        radius = 3.0
        [optics]                    # optional: how the cave looks
        water = "coastal"           # clear, ocean, coastal, turbid
        daylight = 0.5              # open-water brightness at the exits
        [sensors]                   # optional: pixel counts (flags override them)
        resolution = [160, 120]     # forward camera, default [640, 480]; the horizontal
                                    # field of view (53 deg) is kept at any size
        sounder_resolution = [32, 24]   # each echo sounder's depth camera
        [[entrance]]                # optional: the portal it came in by, if open;
        point = [0.0, 10.0, 2.0]    # leaving through it is never success
        normal = [0.0, 1.0, 0.0]    # pointing out of the cave
        radius = 3.0
        centreline = [[0.0, 10.0, 2.0], [0.0, -10.0, 2.0]]   # optional: progress is
                                    # measured along it (metres, from start to exit)

    A cave of several meshes lists them as pieces instead of ``mesh = "path"``; each is
    turned by ``yaw_deg`` about the vertical through its own origin (positive turns +y
    toward -x, as the start's yaw turns the vehicle left), then moved by ``offset``, and
    the rims where pieces meet are welded (`cavenav.world.mesh.join_meshes`). Start,
    exits, entrances and centre line are in the joined cave's coordinates::

        [[mesh]]
        path = "meshes/cave_straight_20m.dae"
        [[mesh]]
        path = "meshes/cave_L_20m.dae"
        offset = [0.0, -20.0, 0.0]  # metres, default [0, 0, 0]
        yaw_deg = 90.0              # default 0
        scale = 1.0                 # optional, per piece (default: the top-level scale)
        up_axis = "z"               # optional, per piece

    A family file names a procedural family instead of a mesh, start and exit, and is
    built at ``seed``: "hard S1" kept as a file, to sweep seeds over::

        name = "hard-s1"
        family = "S1"
        [difficulty]                # optional: knobs of `Difficulty`
        constriction_m = 2.4
        [optics]                    # optional, as above
        [sensors]                   # optional, as above

    Args:
        seed: which cave of a family file's family; a mesh file has one cave only.
        difficulty: knobs that override the family file's (a mesh file takes none).

    Raises:
        ConfigError: unreadable TOML or invalid fields, naming the field.
        MeshError: the mesh cannot be used.
        ScenarioError: ``difficulty`` given for a mesh file, or out of the family's range.
    """
    path = Path(path)
    model = _read_scenario_file(path, difficulty)
    if isinstance(model, _FamilyFileModel):
        return _family_scenario(path, model, seed, difficulty)
    return _mesh_scenario(path, model)


def _read_scenario_file(
    path: Path, difficulty: Difficulty | None
) -> _FamilyFileModel | _ScenarioFileModel:
    """The file's fields, validated, before any mesh is read or cave built (milliseconds).

    Raises:
        ConfigError: unreadable TOML or invalid fields, naming the field.
        ScenarioError: ``difficulty`` given for a mesh file.
    """
    if not path.is_file():
        raise ConfigError(f"scenario file not found: {path}")
    try:
        raw = tomllib.loads(path.read_text())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path}: not valid TOML ({exc})") from None
    if "mesh" in raw and "family" in raw:
        raise ConfigError(f"{path}: give either 'mesh' (a cave mesh) or 'family', not both")
    if "family" in raw:
        return _validated(_FamilyFileModel, raw, path)
    if "mesh" not in raw:
        raise ConfigError(
            f"{path}: give 'mesh' (a cave mesh file) or 'family' (one of {', '.join(SCENARIOS)})"
        )
    if difficulty is not None and difficulty.to_dict():
        raise ScenarioError(
            f"{path} is a mesh scenario, which has no difficulty knobs: they apply to the "
            f"procedural families ({', '.join(SCENARIOS)}, or a file naming one)"
        )
    return _validated(_ScenarioFileModel, raw, path)


_Model = TypeVar("_Model", bound=BaseModel)


def _validated(model: type[_Model], raw: dict[str, Any], path: Path) -> _Model:
    """``raw`` checked against ``model``; the first problem as a one-line ConfigError."""
    try:
        return model.model_validate(raw)
    except ValidationError as exc:
        first = exc.errors()[0]
        loc = list(first["loc"])
        if len(loc) > 1 and isinstance(loc[1], int) and not isinstance(raw.get(loc[0]), list):
            del loc[1]  # one [exit] table, validated as a list of one: no index to show
        parts = [str(p) for p in loc]
        where = ".".join(parts) or "(top level)"
        raise ConfigError(f"{path}: field '{where}': {first['msg']}") from None


def _mesh_scenario(path: Path, model: _ScenarioFileModel) -> Scenario:
    mesh = _chained_mesh(path, model)
    check_units(mesh, np.array(model.start.position))  # warns of a mesh in cm, mm, ...
    start = Pose(*model.start.position, psi=math.radians(model.start.yaw_deg))
    if not model.exit:
        raise ConfigError(f"{path}: give at least one [[exit]]")
    exits = tuple(ExitPortal(p.point, p.normal, p.radius) for p in model.exit)
    entrances = tuple(ExitPortal(p.point, p.normal, p.radius) for p in model.entrance)
    centreline = None if model.centreline is None else np.array(model.centreline, np.float64)
    return Scenario(
        model.name or path.stem,
        mesh,
        start,
        exits,
        model.description,
        optics=model.optics,
        centreline=centreline,
        sensors=model.sensors.model_dump(exclude_none=True),
        entrances=entrances,
        step_budget=model.step_budget,
    )


def _chained_mesh(path: Path, model: _ScenarioFileModel) -> CaveMesh:
    """The file's mesh, or its pieces placed and joined; a file used twice is read once."""
    from cavenav.world.mesh import join_meshes, place_mesh

    read: dict[tuple[Path, float | None, str | None], CaveMesh] = {}
    pieces: list[CaveMesh] = []
    for piece in model.mesh:
        scale = model.scale if piece.scale is None else piece.scale
        up_axis = piece.up_axis or model.up_axis
        key = (path.parent / piece.path, scale, up_axis)
        if key not in read:
            read[key] = load_mesh(key[0], scale=scale, up_axis=up_axis)
        moved = any(piece.offset) or piece.yaw_deg % 360.0 != 0.0
        pieces.append(place_mesh(read[key], piece.offset, piece.yaw_deg) if moved else read[key])
    return join_meshes(pieces)


def _family_scenario(
    path: Path, model: _FamilyFileModel, seed: int, override: Difficulty | None
) -> Scenario:
    """The file's family at ``seed``, with its knobs updated by ``override``."""
    cave = procedural_scenario(model.family, seed, _family_difficulty(path, model, override))
    return replace(
        cave,
        name=model.name or path.stem,
        description=model.description or cave.description,
        optics=model.optics,
        sensors=model.sensors.model_dump(exclude_none=True),
    )


def _family_difficulty(
    path: Path, model: _FamilyFileModel, override: Difficulty | None
) -> Difficulty:
    """The file's knobs updated by ``override``, each checked against the file's family.

    Raises:
        ConfigError: the file's own knobs are wrong (blamed on the file).
        ScenarioError: ``override`` sets a knob the family lacks, or one out of range.
    """
    try:
        difficulty = Difficulty.from_dict(model.difficulty)
        SCENARIOS[model.family].resolve(difficulty)  # the file's own knobs, blamed on it
    except (ConfigError, ScenarioError) as exc:
        raise ConfigError(f"{path}: [difficulty]: {exc}") from None
    if override is None:
        return difficulty
    difficulty = difficulty.updated(override)
    SCENARIOS[model.family].resolve(difficulty)
    return difficulty


def check_scenario(name_or_path: str, difficulty: Difficulty | None = None) -> None:
    """Refuse what `load_scenario` would refuse, without building the cave or reading a
    mesh: a sweep checks its whole grid this way in milliseconds (a cave takes seconds),
    so that bad input never becomes a sweep of errors.

    Raises:
        ConfigError: a scenario file that does not read or validate.
        MeshError: a mesh file the scenario file names is missing.
        ScenarioError: an unknown family, or a knob the family lacks or out of its range.
    """
    if name_or_path in SCENARIOS:
        SCENARIOS[name_or_path].resolve(difficulty)
        return
    path = Path(name_or_path)
    if not (path.suffix.lower() == ".toml" or path.exists()):
        raise _unknown(name_or_path)
    model = _read_scenario_file(path, difficulty)
    if isinstance(model, _FamilyFileModel):
        _family_difficulty(path, model, difficulty)
        return
    for piece in model.mesh:
        if not (path.parent / piece.path).is_file():
            raise MeshError(f"{path}: mesh file not found: {path.parent / piece.path}")


def load_scenario(
    name_or_path: str, seed: int = 0, difficulty: Difficulty | None = None
) -> Scenario:
    """A family by name (S1..S5, crawl, maze, long) or a scenario TOML file by path,
    built with ``seed`` and ``difficulty`` where it is a family (see `load_scenario_file`)."""
    if name_or_path in SCENARIOS:
        return procedural_scenario(name_or_path, seed, difficulty)
    path = Path(name_or_path)
    if path.suffix.lower() == ".toml" or path.exists():
        return load_scenario_file(path, seed, difficulty)
    raise _unknown(name_or_path)


def _unknown(name: str) -> ScenarioError:
    return ScenarioError(
        f"unknown scenario '{name}': give one of {', '.join(SCENARIOS)} "
        "or the path of a scenario .toml file"
    )


def validate_start(scenario: Scenario, caster: RayCaster, body: VehicleBody) -> None:
    """Check that the start pose lies inside the passage, clear of every wall.

    Open meshes cannot be tested for inside/outside by watertightness, so this casts rays
    in 64 directions and counts crossings: from inside a tube most rays that hit cross
    the wall an odd number of times (once, then out), from outside an even number.

    Raises:
        ScenarioError: naming the start position and what is wrong with it.
    """
    p = scenario.start.position
    where = f"start position {np.round(p, 2).tolist()}"
    directions = sphere_directions(64)
    crossings = caster.count_intersections(np.broadcast_to(p, directions.shape), directions)
    hitting = crossings > 0
    if hitting.sum() < 0.25 * len(directions):
        raise ScenarioError(
            f"{where} is outside the cave: {int(hitting.sum())} of 64 rays meet a wall"
        )
    odd = float((crossings[hitting] % 2 == 1).mean())
    if odd < 0.5:
        raise ScenarioError(f"{where} is outside the passage (inside the rock or beyond a wall)")
    gap = float(caster.distance(p[None])[0])
    if gap <= body.bounding_radius:
        raise ScenarioError(
            f"{where} is {gap:.2f} m from a wall, closer than the vehicle's "
            f"{body.bounding_radius:.2f} m half-diagonal"
        )
