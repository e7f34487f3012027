"""Scenario files: any user mesh, or a family at a chosen difficulty, as a small TOML file.

This module holds the file's schema, its loader, the check a sweep makes of its grid
before building any cave (`check_scenario`), the front door that takes a family's name
or a file's path (`load_scenario`), and the check that a start lies inside the passage
(`validate_start`).

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
    depth_source = "stereo"     # exact (default), stereo or none
    sonar = "ping360"           # an imaging sonar: ping360, multibeam or none (default)
    dvl = true                  # a Doppler velocity log (default false)
    [water]                     # optional: the flow (--discharge, --gusts override it)
    discharge_m3s = 2.0         # from the exit toward the start; default 0, still
    gusts = 0.2                 # RMS of the slow gusts, a fraction of the mean speed
    [[entrance]]                # optional: the portal it came in by, if open;
    point = [0.0, 10.0, 2.0]    # leaving through it is never success
    normal = [0.0, 1.0, 0.0]    # pointing out of the cave
    radius = 3.0
    centreline = [[0.0, 10.0, 2.0], [0.0, -10.0, 2.0]]   # optional: progress is
                                # measured along it (metres, from start to exit)
    guideline = true            # optional: a diver's guideline tied along the centre
                                # line (true: white, or "yellow"); needs the centreline

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
    guideline = "yellow"        # optional, as above (default false: no line)
    [optics]                    # optional, as above
    [sensors]                   # optional, as above
    [water]                     # optional, as above
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import replace
from pathlib import Path
from typing import Annotated, Any, Literal, TypeVar

import numpy as np
from pydantic import (
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    StrictBool,
    ValidationError,
    ValidationInfo,
    field_validator,
)
from pydantic_core import InitErrorDetails

from cavenav.core.errors import ConfigError, MeshError, ScenarioError, invalid_field
from cavenav.core.types import Pose
from cavenav.world.collision import VehicleBody
from cavenav.world.guideline import GUIDELINE_COLOURS, GuidelineColour
from cavenav.world.mesh import CaveMesh, join_meshes, load_mesh, place_mesh, sphere_directions
from cavenav.world.raycast import RayCaster
from cavenav.world.scenario import (
    GUIDELINE_NEEDS_CENTRELINE,
    SCENARIOS,
    Difficulty,
    ExitPortal,
    Scenario,
    procedural_scenario,
)
from cavenav.world.units import check_units

__all__ = ["check_scenario", "load_scenario", "load_scenario_file", "validate_start"]


# Unknown keys are typos; NaN or inf in a position, angle or size is never meant.
_STRICT = ConfigDict(extra="forbid", allow_inf_nan=False)
# Every number is bounded by what a cave can hold, so that a typo (radius = 1e308) is
# refused here, naming its field, instead of overflowing the plots or the ray caster later.
# The bounds lie far beyond any real cave (docs/guides/faults.md).
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


def _guideline_value(v: Any) -> Any:
    """A file's ``guideline`` as written: true, false or a colour, else refused by name."""
    if isinstance(v, bool) or (isinstance(v, str) and v in GUIDELINE_COLOURS):
        return v
    colours = " or ".join(f'"{name}"' for name in GUIDELINE_COLOURS)
    raise ValueError(f"give true, false or the line's colour ({colours}), not {v!r}")


# A guideline: true (white), false (none) or its colour (`cavenav.world.guideline`).
_Guideline = Annotated[
    StrictBool | GuidelineColour,
    BeforeValidator(_guideline_value),
    Field(description="a diver's guideline: true (white), its colour, or false"),
]


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
    """A scenario file's [sensors] table: pixel counts (the lens stays the paper's), and
    the acoustic instruments the vehicle carries."""

    model_config = _STRICT
    resolution: tuple[_Pixels, _Pixels] | None = Field(
        None, description="[width, height] of the forward camera (default [640, 480])"
    )
    sounder_resolution: tuple[_Pixels, _Pixels] | None = Field(
        None, description="[width, height] of each echo sounder's depth camera ([32, 24])"
    )
    depth_source: Literal["exact", "stereo", "none"] | None = Field(
        None, description="what makes the depth image (default exact)"
    )
    sonar: Literal["ping360", "multibeam", "none"] | None = Field(
        None, description="the imaging sonar (default none)"
    )
    dvl: bool | None = Field(None, strict=True, description="a Doppler velocity log (false)")


class _WaterModel(BaseModel):
    """A scenario file's [water] table: the cave's flow (`cavenav.world.current.Current`)."""

    model_config = _STRICT
    # strict: TOML's `true` is no number of m³/s (lax, it would fly at 1 m³/s)
    discharge_m3s: float | None = Field(
        None, ge=-1e4, le=1e4, strict=True, description="m³/s from the exit toward the start (0)"
    )
    gusts: float | None = Field(
        None, ge=0, le=1, strict=True, description="gusts, a fraction of the speed"
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
    water: _WaterModel = Field(default_factory=_WaterModel)
    guideline: _Guideline = False

    @field_validator("guideline")
    @classmethod
    def _laid_along_a_centreline(cls, v: bool | str, info: ValidationInfo) -> bool | str:
        if v is not False and info.data.get("centreline") is None:
            raise ValueError(GUIDELINE_NEEDS_CENTRELINE)
        return v

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
    water: _WaterModel = Field(default_factory=_WaterModel)
    guideline: _Guideline = False

    @field_validator("family")
    @classmethod
    def _known(cls, v: str) -> str:
        if v not in SCENARIOS:
            raise ValueError(f"unknown family '{v}'; choose one of {', '.join(SCENARIOS)}")
        return SCENARIOS[v].name


def load_scenario_file(
    path: str | Path, seed: int = 0, difficulty: Difficulty | None = None
) -> Scenario:
    """Read a scenario TOML file: a mesh with its start and exits, or a cave family (the
    format is in this module's docstring).

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
        raise invalid_field(_as_written(exc, raw), str(path)) from None


def _as_written(error: ValidationError, raw: dict[str, Any]) -> ValidationError:
    """``error`` with its first problem's field named as the file writes it: one [exit]
    table (or ``mesh = "path"``) is validated as a list of one, and has no index to show."""
    first = error.errors()[0]
    loc = first["loc"]
    if len(loc) < 2 or not isinstance(loc[1], int) or isinstance(raw.get(str(loc[0])), list):
        return error
    line: InitErrorDetails = {
        "type": first["type"],
        "loc": (loc[0], *loc[2:]),
        "input": first["input"],
    }
    if "ctx" in first:
        line["ctx"] = first["ctx"]
    return ValidationError.from_exception_data(error.title, [line])


def _mesh_scenario(path: Path, model: _ScenarioFileModel) -> Scenario:
    mesh = _chained_mesh(path, model)
    check_units(mesh, np.array(model.start.position))  # warns of a mesh in cm, mm, ...
    start = Pose(*model.start.position, psi=math.radians(model.start.yaw_deg))
    if not model.exit:
        raise ConfigError(f"{path}: give at least one [[exit]]")
    exits = tuple(ExitPortal(p.point, p.normal, p.radius) for p in model.exit)
    entrances = tuple(ExitPortal(p.point, p.normal, p.radius) for p in model.entrance)
    centreline = None if model.centreline is None else np.array(model.centreline, np.float64)
    cave = Scenario(
        model.name or path.stem,
        mesh,
        start,
        exits,
        model.description,
        optics=model.optics,
        centreline=centreline,
        sensors=model.sensors.model_dump(exclude_none=True),
        water=model.water.model_dump(exclude_none=True),
        entrances=entrances,
        step_budget=model.step_budget,
    )
    return _guided(cave, model.guideline)


def _chained_mesh(path: Path, model: _ScenarioFileModel) -> CaveMesh:
    """The file's mesh, or its pieces placed and joined; a file used twice is read once."""
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
    cave = replace(
        cave,
        name=model.name or path.stem,
        description=model.description or cave.description,
        optics=model.optics,
        sensors=model.sensors.model_dump(exclude_none=True),
        water=model.water.model_dump(exclude_none=True) or cave.water,
    )
    return _guided(cave, model.guideline)


def _guided(cave: Scenario, guideline: bool | str) -> Scenario:
    """``cave`` with the guideline a file's ``guideline`` key asks for: none for false,
    a white one for true, else one of that colour."""
    if guideline is False:
        return cave
    return cave.with_guideline("white" if guideline is True else str(guideline))


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


def check_scenario(
    name_or_path: str, difficulty: Difficulty | None = None, guideline: bool = False
) -> None:
    """Refuse what `load_scenario` would refuse, without building the cave or reading a
    mesh: a sweep checks its whole grid this way in milliseconds (a cave takes seconds),
    so that bad input never becomes a sweep of errors. ``guideline``: the episodes lay a
    guideline, which needs a centre line.

    Raises:
        ConfigError: a scenario file that does not read or validate.
        MeshError: a mesh file the scenario file names is missing.
        ScenarioError: an unknown family, a knob the family lacks or out of its range, or
            a guideline asked of a mesh file that gives no centre line.
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
    if guideline and model.centreline is None:
        raise ScenarioError(f"{path}: {GUIDELINE_NEEDS_CENTRELINE}")


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
