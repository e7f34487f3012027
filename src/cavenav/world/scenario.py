"""Scenarios: a cave mesh with a start pose and exit portals, and the families by name.

The five topologies of SPEC section 6 are families of caves registered by name (S1-S5): a
seed draws one cave of the family, and a `Difficulty` turns its knobs (the width of the
constrictions, the angle of the bend, the number of boulders, ...). Three harder families
follow them: ``crawl`` (a crawlway too narrow for any standoff), ``maze`` (blind side
branches that look like the way on) and ``long`` (230 m chaining the five, with a
`Scenario.step_budget` to match). Seeds in `HELD_OUT_SEEDS` are the test split.

Each knob is declared once, as a field of `Difficulty` with its meaning and why its
ranges end where they do (`KNOB_FACTS`), and each family once, in `SCENARIOS`, with its
builder (`cavenav.world.families`) and the default and range of every knob it has.
The command line's ``--difficulty`` (`parse_difficulty`), a scenario file's
``[difficulty]`` table (`cavenav.world.scenario_file`) and the table in the docs
(`difficulty_table`) all read these two declarations.
"""

from __future__ import annotations

import hashlib
import json
import math
import numbers
import textwrap
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field, fields, replace
from functools import cached_property
from typing import Any

import numpy as np

from cavenav.core.errors import ConfigError, ScenarioError
from cavenav.core.types import Pose
from cavenav.world import families
from cavenav.world.families import Layout
from cavenav.world.guideline import Guideline, lay_guideline
from cavenav.world.mesh import CaveMesh
from cavenav.world.procedural import arc_length_at, build_cave

__all__ = [
    "GUIDELINE_NEEDS_CENTRELINE",
    "HELD_OUT_SEEDS",
    "KNOBS",
    "KNOB_FACTS",
    "SCENARIOS",
    "Difficulty",
    "ExitPortal",
    "Knob",
    "Scenario",
    "difficulty_table",
    "parse_difficulty",
    "procedural_scenario",
]

# Why a cave with no centre line takes no guideline, and what its file should give.
GUIDELINE_NEEDS_CENTRELINE = (
    "a guideline is laid along the passage's centre line, and this cave gives none; add "
    "centreline = [[x, y, z], ...] from the start to the exit to its scenario file"
)


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
        return bool(self.passed(position))

    def passed(self, points: np.ndarray) -> np.ndarray:
        """Which of ``points`` (..., 3) lie past the portal: `reached`, for many at once
        (the shortest path's goal is the episode's own)."""
        p = np.asarray(points, np.float64) - np.asarray(self.point)
        n = np.asarray(self.normal, np.float64)
        n = n / np.linalg.norm(n)
        along = p @ n
        across = np.linalg.norm(p - np.multiply.outer(along, n), axis=-1)
        return (along >= 0.0) & (across <= self.radius)

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
        water: the flow the cave has unless an episode says otherwise (a scenario file's
            [water] table: ``discharge_m3s``, ``gusts``; `cavenav.world.current.Current`).
            The families are still water (SPEC section 5); empty: still.
        guideline: a diver's guideline tied along the passage to the exit
            (`cavenav.world.guideline`; `with_guideline`), which the camera sees; None:
            none, as in the paper's caves.
        junctions: arc lengths along the centre line where side passages leave the way
            on (the maze's branches): a guideline gets an arrow at each.
    """

    name: str
    mesh: CaveMesh
    start: Pose
    exits: tuple[ExitPortal, ...]
    description: str = ""
    seed: int | None = None
    optics: Mapping[str, Any] = field(default_factory=dict)  # a file's [optics], a family's own
    centreline: np.ndarray | None = None
    difficulty: Difficulty | None = None
    sensors: Mapping[str, Any] = field(default_factory=dict)  # the file's [sensors] table
    entrances: tuple[ExitPortal, ...] = ()
    step_budget: int | None = None
    water: Mapping[str, Any] = field(default_factory=dict)  # a file's [water], a family's own
    guideline: Guideline | None = None
    junctions: tuple[float, ...] = ()

    def with_guideline(self, colour: str = "white") -> Scenario:
        """This cave with a guideline laid along its centre line (`lay_guideline`, seeded
        by the cave's seed): the same rock, start and exits, plus the line. A cave that
        has a line of that colour already is returned as it is.

        Raises:
            ScenarioError: the cave has no centre line to lay it along.
            ConfigError: an unknown colour.
        """
        if self.guideline is not None and self.guideline.colour == colour:
            return self
        if self.centreline is None:
            raise ScenarioError(f"{self.name}: {GUIDELINE_NEEDS_CENTRELINE}")
        line = lay_guideline(
            self.mesh, self.centreline, start_arc=self._start_arc, seed=self.seed or 0,
            colour=colour, junctions=self.junctions,
        )  # fmt: skip
        return replace(self, guideline=line)

    def without_guideline(self) -> Scenario:
        """This cave with no guideline."""
        return self if self.guideline is None else replace(self, guideline=None)

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
        return arc_length_at(self.centreline, np.asarray(position, np.float64)) - self._start_arc

    @cached_property
    def _start_arc(self) -> float:
        """Arc length of the start along the centre line: asked for at every step."""
        assert self.centreline is not None
        return arc_length_at(self.centreline, self.start.position)

    @property
    def passage_length_m(self) -> float:
        """Progress needed to reach the exit: the centre line's length, or the start's
        distance to the nearest exit plane."""
        if self.centreline is None:
            return self.exit_distance(self.start.position)
        return float(np.linalg.norm(np.diff(self.centreline, axis=0), axis=1).sum()) - (
            arc_length_at(self.centreline, self.start.position)
        )


# ------------------------------------------------------------------ difficulty


HELD_OUT_SEEDS = range(1000, 2000)
"""Cave seeds of the test split, which nobody tunes on.

Seeds 0-999 are for development: tuning prompts, pilots and thresholds, and training (the
Gymnasium environment draws its caves below ``cavenav.sim.env.TRAINING_SEEDS``, which is 1000
for this reason). The numbers a report states come from seeds of this range, so they
measure caves no choice was fitted to. The split is the same for every family and every
difficulty: S1 at seed 1234 is held out however hard it is made.
"""


@dataclass(frozen=True)
class Knob:
    """What one difficulty knob means, whichever family has it.

    Attributes:
        meaning: what it changes, for the docs.
        limits: why the families' ranges end where they do, for the message that refuses
            a value outside one.
        count: whether it takes whole numbers (a number of boulders); the others take
            real numbers.
    """

    meaning: str
    limits: str
    count: bool = False


def _knob(meaning: str, limits: str, *, count: bool = False) -> Any:
    """A `Difficulty` field, unset by default, carrying its `Knob`."""
    return field(default=None, metadata={"knob": Knob(meaning, limits, count)})


@dataclass(frozen=True)
class Difficulty:
    """Knobs that make a cave family harder or easier; ``None`` keeps the family's default.

    ``Difficulty()`` builds exactly the caves of the plain families, seed for seed and bit
    for bit. A knob belongs to some families only (a bend angle means nothing in a straight
    passage), and setting one that the family lacks is refused rather than ignored, so that
    a sweep never reports a difficulty it did not fly. Each field declares its knob once:
    what it means and why its ranges end where they do (`KNOB_FACTS`); each family's
    default and range are declared with the family, in `SCENARIOS`. The table of those
    and the meaning of each knob are appended below from these declarations.
    """

    # Under 1 m the 0.46 x 0.34 m vehicle has too little room once the rough walls bulge
    # into it, and one wider than the passage would be a bulge. The crawl is 1.7-2.5 m
    # across between its pinches, so its pinches stop at 2.5 m.
    constriction_m: float | None = _knob(
        "width of the narrowest constrictions in metres (S1, S2, long's five): the dips "
        "are made as deep as it takes to leave this width (the height is unchanged). "
        "crawl: the width of its three pinches, the narrowest it gets.",
        "under 1 m the 0.46 x 0.34 m vehicle has no room once the rough walls bulge in, "
        "and over the top a constriction would be wider than the passage",
    )
    # Slopes reach atan(pi * undulation_m / 30): 23 degrees at the default 4 m, 32 at 6 m.
    undulation_m: float | None = _knob(
        "peak-to-peak height of the vertical undulations in metres (S2, long's rise and fall).",
        "past 8 m peak to peak the slopes pass 40 degrees",
    )
    # Beyond about 130 degrees the first leg is shortened so that its closed end stays
    # behind the exit plane.
    bend_deg: float | None = _knob(
        "the turn of the bend in degrees (S4): the second leg runs along x and the first "
        "comes in at this angle to it.",
        "past 150 degrees the two legs fold into one chamber",
    )
    # S3 has room for 8 boulders in its 45 m and S5 for 20 in its 60 m.
    obstacles: int | None = _knob(
        "number of boulders. S3: alternately frontal (in line with the start) and lateral "
        "(from the other wall), spread from 13 m to 41 m. S5: rocks on the walls and "
        "floor, spread evenly.",
        "counts start at 0, and more boulders do not fit along the passage",
        count=True,
    )
    obstacle_scale: float | None = _knob(
        "factor on every boulder's semi-axes, not on its centre (S3, S5, long).",
        "boulders grown past 1.5 times close the passage",
    )
    # The maze has room for 5 branches along its 60-70 m.
    branches: int | None = _knob(
        "number of blind side branches of the maze, alternately left and right, every "
        "other one as wide as the way on or wider.",
        "counts start at 0, and more branches do not fit along the passage",
        count=True,
    )
    # Above about 0.6 m the walls may pinch narrow constrictions shut. The crawl's walls
    # stay smooth (3 standard deviations of 0.15 m on both walls still leave a 1 m pinch
    # 0.1 m), and the maze keeps 1 + 3 x roughness_m of rock around each branch.
    roughness_m: float | None = _knob(
        "amplitude (standard deviation) of the wall noise in metres, every family: "
        "`PassageSpec.roughness`.",
        "past 1 m the walls may close the passage (the crawl's past 0.15 m), and past "
        "0.6 m the maze's branches would need more rock between them than there is room for",
    )

    def __post_init__(self) -> None:
        # Counts are stored as int and every other knob as float, so that 2 and 2.0 give
        # the same cave digest and the same summary.json.
        for name, value in self.to_dict().items():
            integer = KNOB_FACTS[name].count
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
        return replace(self, **other.to_dict())  # type: ignore[arg-type]  # each knob its own

    @property
    def tag(self) -> str:
        """A short name for the knobs that are set ('' for none): keeps harder caves apart
        from the plain ones by mesh name, in the cache and in the run records."""
        if not self.to_dict():
            return ""
        text = json.dumps(self.to_dict(), sort_keys=True)
        return "d" + hashlib.sha256(text.encode()).hexdigest()[:8]


KNOB_FACTS: Mapping[str, Knob] = {f.name: f.metadata["knob"] for f in fields(Difficulty)}
"""Each knob's meaning and limits by name, in table order: `Difficulty`'s declarations."""
KNOBS: tuple[str, ...] = tuple(KNOB_FACTS)
_KNOB_LIST = ", ".join(KNOBS)


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
        integer = KNOB_FACTS[key].count
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

    `Difficulty`'s docstring is given it at import, and docs/guides/scenarios.md holds a
    copy that a test keeps equal to it.
    """
    lines = ["| family | " + " | ".join(KNOBS) + " |", "|" + " --- |" * (len(KNOBS) + 1)]
    for name, family in SCENARIOS.items():
        cells = [
            f"{family.knobs[k].default:g} {family.knobs[k]}" if k in family.knobs else "-"
            for k in KNOBS
        ]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


# ------------------------------------------------------------------ the families by name


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
    build: Callable[[np.random.Generator, int, Mapping[str, float]], Layout]
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
                why = KNOB_FACTS[key].limits
                raise ScenarioError(
                    f"{self.name}: {key}={value:g} is outside {self.knobs[key]}: {why}"
                )
            values[key] = value
        return values

    def layout(self, seed: int, difficulty: Difficulty | None = None) -> Layout:
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
        families.s1,
        "constrictions: narrow passage, clearance-aware planning",
        {"constriction_m": _Range(3.6, 1.0, 7.0), "roughness_m": _ROUGHNESS},
    ),
    _Factory(
        "S2",
        2,
        families.s2,
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
        families.s3,
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
        families.s4,
        "bend: a sharp 90-degree turn",
        {"bend_deg": _Range(90.0, 0.0, 150.0, low_open=True), "roughness_m": _ROUGHNESS},
    ),
    _Factory(
        "S5",
        5,
        families.s5,
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
        families.crawl,
        "crawlway: 40-60 m winding passage 1.2-2.5 m across, no room for a standoff",
        {"constriction_m": _Range(1.5, 1.0, 2.5), "roughness_m": _Range(0.08, 0.0, 0.15)},
    ),
    _Factory(
        "maze",
        7,
        families.maze,
        "maze: passage with blind side branches as wide as the way on; one exit",
        {"branches": _Range(4, 0, 5), "roughness_m": _Range(0.3, 0.0, 0.6)},
    ),
    _Factory(
        "long",
        8,
        families.long,
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
    exit_ = ExitPortal(*layout.exit_plane)
    mesh_name = f"{key}-seed{seed}" + (f"-{difficulty.tag}" if difficulty.tag else "")
    mesh = build_cave(spec, name=mesh_name)
    centreline = spec.centreline[: spec.exit_index + 1]
    junctions = tuple(arc_length_at(centreline, branch.centreline[0]) for branch in spec.branches)
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
        optics=layout.optics,
        junctions=junctions,
    )


def _knob_docs() -> str:
    """The knob table and what each knob means, in Markdown, for `Difficulty`'s docstring."""
    meanings = [f"- ``{name}``: {knob.meaning}" for name, knob in KNOB_FACTS.items()]
    return "\n\n".join([difficulty_table(), "\n".join(meanings)])


# The table and the knobs' meanings are the declarations' own, so `help(Difficulty)` and
# the API docs show them without a copy in the source to keep in step.
Difficulty.__doc__ = f"{Difficulty.__doc__}\n{textwrap.indent(_knob_docs(), '    ')}\n"
