"""Scenarios: a cave mesh with a start pose and an exit portal.

The five topologies of SPEC section 6 are seeded factories registered by name (S1-S5);
any user mesh becomes a scenario through a small TOML file (see `load_scenario_file`).
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator
from scipy.ndimage import gaussian_filter1d

from cavenav.errors import ConfigError, ScenarioError
from cavenav.types import Pose
from cavenav.world.collision import VehicleBody
from cavenav.world.mesh import CaveMesh, load_mesh
from cavenav.world.procedural import Boulder, PassageSpec, build_cave, resample
from cavenav.world.raycast import RayCaster

__all__ = [
    "SCENARIOS",
    "ExitPortal",
    "Scenario",
    "load_scenario",
    "load_scenario_file",
    "procedural_scenario",
    "validate_start",
]


@dataclass(frozen=True)
class ExitPortal:
    """The goal: a disc-bounded plane at the cave's exit.

    The vehicle has exited once its centre lies on the outer side of the plane through
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
            known (procedural caves); progress is then measured along it.
    """

    name: str
    mesh: CaveMesh
    start: Pose
    exits: tuple[ExitPortal, ...]
    description: str = ""
    seed: int | None = None
    optics: Mapping[str, Any] = field(default_factory=dict)  # the file's [optics] table
    centreline: np.ndarray | None = None

    def exited(self, position: np.ndarray) -> bool:
        """Whether ``position`` lies past any exit portal."""
        return any(portal.reached(position) for portal in self.exits)

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
        return _arc_length_at(self.centreline, np.asarray(position, np.float64)) - (
            _arc_length_at(self.centreline, self.start.position)
        )

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


# ------------------------------------------------------------------ procedural S1-S5


def _vec3(v: np.ndarray) -> tuple[float, float, float]:
    return float(v[0]), float(v[1]), float(v[2])


def _smooth_noise(s: np.ndarray, wavelength: float, rng: np.random.Generator) -> np.ndarray:
    """Smooth 1-D noise along arc length ``s``, roughly in [-1, 1]."""
    knots = np.arange(s[0] - wavelength, s[-1] + 2 * wavelength, wavelength)
    values = rng.uniform(-1.0, 1.0, len(knots))
    curve = np.interp(s, knots, values)
    step = float(s[1] - s[0])
    return gaussian_filter1d(curve, sigma=0.35 * wavelength / step, mode="nearest") * 1.6


def _dips(s: np.ndarray, centres: list[float], depth: float, sigma: float = 1.6) -> np.ndarray:
    """Sum of Gaussian narrowings of ``depth`` metres centred at ``centres``."""
    out = np.zeros_like(s)
    for c in centres:
        out = np.maximum(out, depth * np.exp(-0.5 * ((s - c) / sigma) ** 2))
    return out


def _straighten_ends(
    s: np.ndarray, values: np.ndarray, length: float, margin: float = 6.0
) -> np.ndarray:
    """Hold a profile constant before s=2 and after s=length-margin: straight portals."""
    head = np.interp(2.0, s, values)
    tail = np.interp(length - margin, s, values)
    out = values.copy()
    out[s < 2.0] = head
    out[s > length - margin] = tail
    return gaussian_filter1d(out, sigma=4, mode="nearest")


@dataclass(frozen=True)
class _Layout:
    """A generated passage before meshing: spec plus where the vehicle starts."""

    spec: PassageSpec
    start: Pose
    description: str


def _layout_from_profiles(
    s: np.ndarray,
    points: np.ndarray,
    half_width: np.ndarray,
    half_height: np.ndarray,
    length: float,
    seed: int,
    boulders: tuple[Boulder, ...] = (),
    start_offset: tuple[float, float, float] = (0.0, 0.0, 0.0),
    description: str = "",
) -> _Layout:
    exit_index = int(np.searchsorted(s, length))
    start_index = int(np.searchsorted(s, 0.0))
    heading = points[start_index + 1] - points[start_index]
    start = Pose.facing(points[start_index] + np.asarray(start_offset), heading)
    spec = PassageSpec(points, half_width, half_height, boulders, exit_index, seed=seed)
    return _Layout(spec, start, description)


def _s1(rng: np.random.Generator, seed: int) -> _Layout:
    length = 55.0
    s = np.arange(-4.0, length + 4.0, 0.25)
    x = _straighten_ends(
        s, 1.6 * np.sin(2 * np.pi * s / rng.uniform(26, 34) + rng.uniform(0, 6.3)), length
    )
    z = _straighten_ends(s, 0.5 * _smooth_noise(s, 12.0, rng), length)
    points = np.stack([x, -s, z], axis=1)
    necks = [c + rng.uniform(-2, 2) for c in (15.0, 29.0, 42.0)]
    half_w = 3.5 - _dips(s, necks, 1.7)
    half_h = 3.0 - _dips(s, necks[1:2], 1.0)
    return _layout_from_profiles(
        s,
        points,
        half_w,
        half_h,
        length,
        seed,
        description="narrow passage with three constrictions to about 3.6 m",
    )


def _s2(rng: np.random.Generator, seed: int) -> _Layout:
    length = 55.0
    s = np.arange(-4.0, length + 4.0, 0.25)
    x = _straighten_ends(s, 1.0 * _smooth_noise(s, 15.0, rng), length)
    period = rng.uniform(30, 34)  # slopes of at most 2 pi 2 / 30 = 23 degrees
    z = _straighten_ends(s, 2.0 * np.sin(2 * np.pi * s / period), length)
    points = np.stack([x, -s, z], axis=1)
    # Constrictions on the slopes, between a crest and a trough.
    necks = [period * (k / 2 + 0.5) + rng.uniform(-1.5, 1.5) for k in (0, 1)]
    half_w = 3.2 - _dips(s, necks, 1.3)
    half_h = 2.9 - _dips(s, necks, 0.8)
    return _layout_from_profiles(
        s,
        points,
        half_w,
        half_h,
        length,
        seed,
        description="narrow passage with vertical undulations of about 4 m and two constrictions",
    )


def _s3(rng: np.random.Generator, seed: int) -> _Layout:
    length = 45.0
    s = np.arange(-4.0, length + 4.0, 0.25)
    points = np.stack([np.zeros_like(s), -s, np.zeros_like(s)], axis=1)
    half_w = np.full_like(s, 3.5)
    half_h = np.full_like(s, 3.0)
    wall_side = 1.0 if rng.random() < 0.5 else -1.0  # +x is the vehicle's left at psi = 0
    front_y = -rng.uniform(13.0, 16.0)
    lateral_y = -rng.uniform(27.0, 31.0)
    boulders = (
        # Frontal obstacle at the start height, in line with the start near the wall.
        Boulder((-wall_side * 0.9, front_y, 0.0), (1.7, 1.5, 1.7)),
        # Lateral obstacle jutting from the other wall.
        Boulder((wall_side * 3.6, lateral_y, -0.3), (2.3, 1.8, 1.9)),
    )
    return _layout_from_profiles(
        s,
        points,
        half_w,
        half_h,
        length,
        seed,
        boulders,
        start_offset=(-wall_side * 2.0, 0.0, 0.0),
        description="straight passage with a frontal and a lateral obstacle; "
        "start near the wall at the frontal obstacle's height",
    )


def _s4(rng: np.random.Generator, seed: int) -> _Layout:
    leg = 30.0
    side = 1.0 if rng.random() < 0.5 else -1.0
    corners = np.array([[0.0, 4.0, 0.0], [0.0, -leg, 0.0], [side * (leg + 4.0), -leg, 0.0]])
    points, s = resample(corners, 0.25)
    s = s - 4.0
    length = 2 * leg
    half_w = 2.9 + 0.3 * _smooth_noise(s, 10.0, rng)
    half_h = 2.7 + 0.2 * _smooth_noise(s, 10.0, rng)
    return _layout_from_profiles(
        s,
        points,
        half_w,
        half_h,
        length,
        seed,
        description=f"sharp 90-degree bend to the {'left' if side > 0 else 'right'}",
    )


def _s5(rng: np.random.Generator, seed: int) -> _Layout:
    length = 60.0
    s = np.arange(-4.0, length + 4.0, 0.25)
    heading = _straighten_ends(s, 0.55 * _smooth_noise(s, 14.0, rng), length)
    heading[s > length - 8] = 0.0
    heading = gaussian_filter1d(heading, 6, mode="nearest")
    heading[s > length - 3] = 0.0
    step = s[1] - s[0]
    x = np.cumsum(np.sin(heading)) * step
    y = -np.cumsum(np.cos(heading)) * step
    x, y = x - np.interp(0.0, s, x), y - np.interp(0.0, s, y)
    z = _straighten_ends(s, 1.2 * _smooth_noise(s, 11.0, rng), length)
    points = np.stack([x, y, z], axis=1)
    half_w = 3.3 + 0.7 * _smooth_noise(s, 9.0, rng)
    half_h = 2.8 + 0.3 * _smooth_noise(s, 9.0, rng)
    tangent = np.gradient(points, axis=0)
    boulders = []
    for k, at in enumerate(np.linspace(9.0, length - 9.0, 7)):
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
        boulders.append(Boulder(_vec3(centre), (r, r * 1.1, r * 0.9)))
    return _layout_from_profiles(
        s,
        points,
        half_w,
        half_h,
        length,
        seed,
        tuple(boulders),
        description="irregular winding passage with rocks spread along it",
    )


@dataclass(frozen=True)
class _Factory:
    build: Callable[[np.random.Generator, int], _Layout]
    summary: str


SCENARIOS: dict[str, _Factory] = {
    "S1": _Factory(_s1, "constrictions: narrow passage, clearance-aware planning"),
    "S2": _Factory(_s2, "undulations: narrow passage rising and falling, 3D manoeuvring"),
    "S3": _Factory(_s3, "obstacles: straight passage, frontal and lateral obstacle"),
    "S4": _Factory(_s4, "bend: a sharp 90-degree turn"),
    "S5": _Factory(_s5, "irregular: winding passage with rocks spread along it"),
}


def procedural_scenario(name: str, seed: int = 0) -> Scenario:
    """Build S1..S5 for ``seed``; the same name and seed always give the same cave."""
    key = name.upper()
    if key not in SCENARIOS:
        raise ScenarioError(f"unknown scenario '{name}'; choose one of {', '.join(SCENARIOS)}")
    layout = SCENARIOS[key].build(np.random.default_rng([seed, int(key[1:])]), seed)
    spec = layout.spec
    tangent = spec.centreline[spec.exit_index + 1] - spec.centreline[spec.exit_index - 1]
    tangent /= np.linalg.norm(tangent)
    exit_ = ExitPortal(
        point=_vec3(spec.centreline[spec.exit_index]),
        normal=_vec3(tangent),
        radius=float(max(spec.half_width.max(), spec.half_height.max()) + 1.5),
    )
    mesh = build_cave(spec, name=f"{key}-seed{seed}")
    centreline = spec.centreline[: spec.exit_index + 1]
    return Scenario(
        key, mesh, layout.start, (exit_,), layout.description, seed, centreline=centreline
    )


# ------------------------------------------------------------------ scenario files


class _StartModel(BaseModel):
    model_config = ConfigDict(extra="forbid")
    position: tuple[float, float, float]
    yaw_deg: float = Field(0.0, description="0 heads along -y; positive turns left")


class _ExitModel(BaseModel):
    model_config = ConfigDict(extra="forbid")
    point: tuple[float, float, float]
    normal: tuple[float, float, float]
    radius: float = Field(gt=0)

    @field_validator("normal")
    @classmethod
    def _nonzero(cls, v: tuple[float, float, float]) -> tuple[float, float, float]:
        if math.hypot(*v) < 1e-9:
            raise ValueError("exit normal must not be the zero vector")
        return v


class _ScenarioFileModel(BaseModel):
    model_config = ConfigDict(extra="forbid")
    name: str | None = None
    description: str = ""
    mesh: str
    scale: float | None = Field(None, gt=0, description="metres per mesh unit")
    up_axis: Literal["x", "y", "z"] | None = None
    start: _StartModel
    exit: _ExitModel | list[_ExitModel] = Field(description="one portal or a list of them")
    optics: dict[str, Any] = Field(
        default_factory=dict, description="water and light; see cavenav.sensors.optics"
    )


def load_scenario_file(path: str | Path) -> Scenario:
    """Read a scenario TOML file; the mesh path is relative to the file.

    Example::

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

    Raises:
        ConfigError: unreadable TOML or invalid fields, naming the field.
        MeshError: the mesh cannot be used.
    """
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"scenario file not found: {path}")
    try:
        raw = tomllib.loads(path.read_text())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path}: not valid TOML ({exc})") from None
    try:
        model = _ScenarioFileModel.model_validate(raw)
    except ValidationError as exc:
        first = exc.errors()[0]
        # Drop the class names pydantic inserts for union members ("exit._ExitModel.radius").
        parts = [str(p) for p in first["loc"] if not str(p).startswith(("_", "list["))]
        where = ".".join(parts) or "(top level)"
        raise ConfigError(f"{path}: field '{where}': {first['msg']}") from None
    mesh = load_mesh(path.parent / model.mesh, scale=model.scale, up_axis=model.up_axis)
    start = Pose(*model.start.position, psi=math.radians(model.start.yaw_deg))
    portals = model.exit if isinstance(model.exit, list) else [model.exit]
    if not portals:
        raise ConfigError(f"{path}: give at least one [[exit]]")
    exits = tuple(ExitPortal(p.point, p.normal, p.radius) for p in portals)
    return Scenario(
        model.name or path.stem, mesh, start, exits, model.description, optics=model.optics
    )


def load_scenario(name_or_path: str, seed: int = 0) -> Scenario:
    """S1..S5 by name (built with ``seed``), or a scenario TOML file by path."""
    if name_or_path.upper() in SCENARIOS:
        return procedural_scenario(name_or_path, seed)
    path = Path(name_or_path)
    if path.suffix.lower() == ".toml" or path.exists():
        return load_scenario_file(path)
    raise ScenarioError(
        f"unknown scenario '{name_or_path}': give one of {', '.join(SCENARIOS)} "
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
    directions = _sphere_directions(64)
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


def _sphere_directions(n: int) -> np.ndarray:
    """(n, 3) roughly uniform unit vectors (Fibonacci sphere), slightly irrational so rays
    never run exactly along mesh edges."""
    k = np.arange(n) + 0.5
    z = 1.0 - 2.0 * k / n
    phi = np.pi * (1.0 + 5**0.5) * k + 0.1234
    r = np.sqrt(1.0 - z**2)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)
