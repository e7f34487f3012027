"""The plain values that flow around the loop: pose, action, observation, decision, usage,
and the two sets of numbers every layer must agree on: the vehicle's size and the
strategy's distances.

This module is a leaf: it imports nothing from cavenav, so every layer can use it.

Conventions (SPEC section 5): metres and radians in world frame, z up; yaw ``psi = 0``
heads along the world's -y axis and a positive yaw turn is counter-clockwise seen from
above, i.e. to the left.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field, fields
from functools import cached_property
from typing import Any

import numpy as np

__all__ = [
    "DEFAULT_RULES",
    "STEP_BUDGET",
    "Action",
    "Cruise",
    "Decision",
    "DvlReading",
    "Observation",
    "Pose",
    "Rules",
    "SonarImage",
    "Usage",
    "VehicleBody",
]


@dataclass(frozen=True)
class Pose:
    """Vehicle pose: position in metres and yaw ``psi`` in radians (0 = heading -y)."""

    x: float
    y: float
    z: float
    psi: float = 0.0

    @property
    def position(self) -> np.ndarray:
        """(3,) float64 position."""
        return np.array([self.x, self.y, self.z], dtype=np.float64)

    @property
    def forward(self) -> np.ndarray:
        """(3,) unit heading vector; the kinematics move along it for a forward command."""
        return np.array([math.sin(self.psi), -math.cos(self.psi), 0.0])

    @property
    def right(self) -> np.ndarray:
        """(3,) unit vector to the vehicle's right, as a positive ``dr`` moves it."""
        return np.array([-math.cos(self.psi), -math.sin(self.psi), 0.0])

    @property
    def yaw_deg(self) -> float:
        return math.degrees(self.psi)

    @classmethod
    def facing(cls, position: np.ndarray, direction: np.ndarray) -> Pose:
        """A pose at ``position`` heading along the horizontal part of ``direction``."""
        dx, dy = float(direction[0]), float(direction[1])
        x, y, z = (float(v) for v in position)
        return cls(x, y, z, psi=math.atan2(dx, -dy))

    def to_dict(self) -> dict[str, float]:
        return {
            "x": round(self.x, 4),
            "y": round(self.y, 4),
            "z": round(self.z, 4),
            "yaw_deg": round(self.yaw_deg, 3),
        }

    @classmethod
    def from_dict(cls, pose: Mapping[str, float]) -> Pose:
        """The pose `to_dict` wrote (a run folder's ``pose``)."""
        return cls(pose["x"], pose["y"], pose["z"], math.radians(pose["yaw_deg"]))


@dataclass(frozen=True)
class Action:
    """One increment ``a = (df, dr, dz, dpsi)`` in the body frame.

    Attributes:
        forward: df in metres, positive ahead.
        right: dr in metres, positive to the vehicle's right.
        up: dz in metres, positive up.
        yaw_deg: dpsi in degrees, positive to the left (counter-clockwise from above).
    """

    forward: float = 0.0
    right: float = 0.0
    up: float = 0.0
    yaw_deg: float = 0.0

    @property
    def is_hold(self) -> bool:
        return self.forward == 0 and self.right == 0 and self.up == 0 and self.yaw_deg == 0


@dataclass(frozen=True)
class Rules:
    """The strategy's distances (SPEC section 3), set once here.

    The prompt states them, the geometric pilot and the safety shield enforce them, and
    the metrics count the steps below the standoff, all from one `Rules` value.

    Attributes:
        standoff_m: desired distance to walls, ceiling and floor.
        no_forward_within_m: an obstacle ahead closer than this forbids forward motion.
        slow_forward_m: the forward range allowed inside the standoff; its upper end
            is the largest forward step there.
    """

    standoff_m: float = 2.0
    no_forward_within_m: float = 1.5
    slow_forward_m: tuple[float, float] = (0.1, 0.2)


DEFAULT_RULES = Rules()

# The steps an episode gets (SPEC's budget) where nothing names another: a scenario's
# own, --steps, or the registered environments' TimeLimit.
STEP_BUDGET = 150


@dataclass(frozen=True)
class Cruise:
    """How fast the vehicle flies a move through the water: what a move lasts, and so how
    far a current carries it and what the move costs in energy (`cavenav.motion.energy`).

    Chosen, not measured: a third of a BlueROV2's published top speed of 1.5 m/s, a pace
    for a confined cave, and a turn of 30 degrees a second.

    Attributes:
        speed_m_s: speed along the straight move of SPEC section 5.
        yaw_deg_s: rate of the turn in place before it.
    """

    speed_m_s: float = 0.5
    yaw_deg_s: float = 30.0


@dataclass(frozen=True)
class VehicleBody:
    """A box the size of a BlueROV2: 0.46 m long, 0.34 m wide, 0.25 m high."""

    length: float = 0.46
    width: float = 0.34
    height: float = 0.25

    @property
    def bounding_radius(self) -> float:
        """Radius of the sphere around the box: farther than this from walls is always safe."""
        return 0.5 * math.sqrt(self.length**2 + self.width**2 + self.height**2)

    @property
    def turn_radius(self) -> float:
        """How far the box's corners reach from its centre when it turns in place (0.29 m)."""
        return 0.5 * math.hypot(self.length, self.width)

    @property
    def section_radius(self) -> float:
        """Half-diagonal of its cross-section (0.21 m): a corridor along its heading must
        be at least this wide either side of the axis."""
        return 0.5 * math.hypot(self.width, self.height)

    @cached_property
    def hull_points(self) -> np.ndarray:
        """(27, 3) body-frame points (forward, right, up): corners, edge and face centres."""
        h = np.array([self.length, self.width, self.height]) / 2.0
        g = np.array(np.meshgrid([-1, 0, 1], [-1, 0, 1], [-1, 0, 1], indexing="ij"))
        return g.reshape(3, -1).T * h

    def world_points(self, pose: Pose) -> np.ndarray:
        """(27, 3) hull points in world coordinates at ``pose``."""
        rot = np.stack([pose.forward, pose.right, np.array([0.0, 0.0, 1.0])], axis=1)
        return pose.position + self.hull_points @ rot.T


def _same_fields(one: object, other: object) -> bool:
    """Field by field, arrays by value and NaN equal to NaN: two renderings of one step are
    equal, so an environment's ``info`` that carries them can be compared."""
    pairs = ((getattr(one, f.name), getattr(other, f.name)) for f in fields(one))  # type: ignore[arg-type]
    return all(
        np.array_equal(a, b, equal_nan=True)
        if isinstance(a, np.ndarray) or isinstance(b, np.ndarray)
        else a == b or (a != a and b != b)
        for a, b in pairs
    )


@dataclass(frozen=True, eq=False)
class SonarImage:
    """What an imaging sonar shows at one step (`cavenav.sensors.sonar`).

    Attributes:
        kind: "ping360" (a scanning sonar's disc) or "multibeam" (a forward fan).
        echoes: (beams, bins) uint8 echo strength, nearest bin first, over 0-``range_m``.
        bearings_deg: (beams,) each beam's bearing, right of ahead positive.
        range_m: the range the bins span.
        fan: (H, W) uint8 the image as the device's software draws it, heading up.
        age_s: (beams,) seconds since each beam was pinged: 0 for those pinged since the
            previous observation (all of a multibeam's; the part of its sector a scanning
            head swept), ``inf`` for those never pinged; the disc shows the rest as they
            were.
        turned_deg: (beams,) how far the vehicle has turned (left positive, as its gyro
            knows) since each beam was pinged: such a beam now lies ``turned_deg`` further
            right than its bearing says.
        moved_m: (beams,) how far the vehicle has moved since each beam was pinged (its
            odometry): an echo that old may be that much nearer now.
        frequency_khz: the carrier.
        beam_width_deg, aperture_deg: one beam's horizontal width and vertical aperture.
    """

    kind: str
    echoes: np.ndarray
    bearings_deg: np.ndarray
    range_m: float
    fan: np.ndarray
    age_s: np.ndarray
    frequency_khz: float
    beam_width_deg: float = 0.0
    aperture_deg: float = 0.0
    turned_deg: np.ndarray | None = None
    moved_m: np.ndarray | None = None

    def __eq__(self, other: object) -> bool:
        return isinstance(other, SonarImage) and _same_fields(self, other)

    @property
    def bin_m(self) -> float:
        return self.range_m / self.echoes.shape[1]

    @property
    def fresh(self) -> np.ndarray:
        """(beams,) bool, the beams pinged since the previous observation."""
        return self.age_s == 0


@dataclass(frozen=True, eq=False)
class DvlReading:
    """What a Doppler velocity log measured over the move just made
    (`cavenav.sensors.dvl`).

    Attributes:
        velocity_m_s: (3,) mean velocity over the ground in the body frame after the
            move's turn (forward, left, up); NaN without bottom lock.
        locked: whether enough beams found a surface in range (bottom lock).
        altitude_m: the vertical distance to what the beams hit; NaN without a lock.
        beam_ranges_m: (4,) each beam's slant range, ``inf`` where it found nothing.
        seconds: the time the velocity is the mean over (the move's duration).
        sigma_m_s: the velocity's standard error per axis (the device's figure of merit).
    """

    velocity_m_s: np.ndarray
    locked: bool
    altitude_m: float
    beam_ranges_m: np.ndarray
    seconds: float
    sigma_m_s: float

    def __eq__(self, other: object) -> bool:
        return isinstance(other, DvlReading) and _same_fields(self, other)


@dataclass(frozen=True)
class Observation:
    """What a pilot may see at one step; never the mesh, never the pose.

    Besides the images it carries what a real vehicle's calibration says about them
    (depth range, field of view, where the camera sits), so every reader interprets
    them with the numbers of the camera that took them.

    Attributes:
        rgb: (H, W, 3) uint8 forward colour image.
        depth_m: (H, W) float32 planar depth in metres; ``inf`` where no surface is hit.
        depth_png: (H, W) uint8 normalised depth (dark near, bright far) as sent to a VLM.
        d_top: range to the ceiling from the upward echo sounder, metres.
        d_bottom: range to the floor from the downward echo sounder, metres.
        depth_range: (D_min, D_max) in metres used for ``depth_png``.
        hfov_deg: horizontal field of view of both forward images, degrees.
        camera_offset_m: how far ahead of the vehicle's centre the camera sits.
        step: index of the step at which this was observed.
        previous_action: the action the vehicle executed since the previous
            observation (after any safety shield), as its own command log knows it;
            None at the start of an episode or when the source does not say.
        has_depth: False when no depth camera took part (a photograph given to
            ``cavenav ask`` alone). The VLM pilot then sends no depth image and says so;
            ``depth_m`` is NaN and ``depth_png`` 0 (near) everywhere, so that a reader
            that misses this flag sees no free space rather than open water.
        energy_left_wh: what the battery has left, as a BlueROV2 reports it (a budget
            given to the environment, else the full pack); None when the source does not
            say.
        depth_source: what made the depth image: "exact" (the simulator's ray depth),
            "stereo" (a stereo camera's, `cavenav.sensors.stereo`: NaN in ``depth_m`` and
            0, near, in ``depth_png`` where it found no match), "monocular" (a model's,
            from a vehicle's colour image) or "none".
        sonar: the imaging sonar's image, when the vehicle carries one.
        dvl: the Doppler velocity log's reading, when the vehicle carries one.
        guideline: the colour of the diver's guideline tied along this cave ("white" or
            "yellow"), which the colour image may show; None where there is none. What
            a diver is told before a dive, not a reading: the VLM pilot's prompt says it
            (`cavenav.pilots.prompt.Instruments`).
    """

    rgb: np.ndarray
    depth_m: np.ndarray
    depth_png: np.ndarray
    d_top: float
    d_bottom: float
    depth_range: tuple[float, float]
    hfov_deg: float
    camera_offset_m: float = 0.0
    step: int = 0
    previous_action: Action | None = None
    has_depth: bool = True
    energy_left_wh: float | None = None
    depth_source: str = "exact"
    sonar: SonarImage | None = None
    dvl: DvlReading | None = None
    guideline: str | None = None

    def __eq__(self, other: object) -> bool:
        """Field by field, the images by value (NaN equal to NaN)."""
        if not isinstance(other, Observation):
            return NotImplemented
        return _same_fields(self, other)

    def arrays(self, depth_max_m: float, sounder_max_m: float) -> dict[str, np.ndarray]:
        """The observation as `cavenav.sim.env.CaveNavEnv` gives it to a learner (and a
        learned pilot takes it back): depths with a channel axis, ``depth_m`` and the
        sounders' ranges clipped at the sensors' limits, each range a (1,) vector."""
        limit = np.float32(sounder_max_m)
        return {
            "rgb": self.rgb,
            "depth": self.depth_png[..., None],
            "depth_m": np.minimum(self.depth_m, np.float32(depth_max_m))[..., None],
            "d_top": np.array([min(self.d_top, limit)], np.float32),
            "d_bottom": np.array([min(self.d_bottom, limit)], np.float32),
            **self._acoustic_arrays(),
        }

    def _acoustic_arrays(self) -> dict[str, np.ndarray]:
        """The sonar's echoes (beams, bins, 1) and the DVL's (velocity forward, left, up,
        altitude, lock), zeros in place of NaN, when the vehicle carries them."""
        found = {}
        if self.sonar is not None:
            found["sonar"] = self.sonar.echoes[..., None]
        if self.dvl is not None:
            dvl = self.dvl
            values = [*dvl.velocity_m_s, dvl.altitude_m, float(dvl.locked)]
            found["dvl"] = np.nan_to_num(np.array(values, np.float32), nan=0.0)
        return found


@dataclass(frozen=True)
class Usage:
    """What one step of a model pilot cost: tokens, time, re-queries, retries, money.

    Pilots without a model report none. Totals are taken with `Usage.total`, the one
    place where usage is summed.

    Attributes:
        prompt_tokens, completion_tokens: token counts over every request of the step.
        latency_s: time spent waiting for the model, seconds.
        model_s: the part of it the model server took, apart from the time the request
            spent in this process (`cavenav.pilots.backends.Completion.model_s`); None
            where a request of the step was not measured (cached, failed).
        requeries: replies rejected and asked again.
        transport_retries: requests repeated after transport faults.
        cached: every reply came from the reply cache.
        cost_usd: estimated cost, when prices were given.
    """

    prompt_tokens: int = 0
    completion_tokens: int = 0
    latency_s: float = 0.0
    requeries: int = 0
    transport_retries: int = 0
    cached: bool = False
    cost_usd: float | None = None
    model_s: float | None = None

    def to_dict(self) -> dict[str, Any]:
        """The per-step record written to steps.jsonl under ``vlm``."""
        return {
            "prompt_tokens": self.prompt_tokens,
            "completion_tokens": self.completion_tokens,
            "latency_s": round(self.latency_s, 4),
            "model_s": None if self.model_s is None else round(self.model_s, 4),
            "requeries": self.requeries,
            "transport_retries": self.transport_retries,
            "cached": self.cached,
            "cost_usd": self.cost_usd,
        }

    @staticmethod
    def total(steps: Iterable[Usage]) -> dict[str, Any] | None:
        """Episode totals (summary.json's ``usage``); None for pilots without a model."""
        steps = list(steps)
        if not steps:
            return None
        costs = [s.cost_usd for s in steps if s.cost_usd is not None]
        return {
            "model_steps": len(steps),
            "prompt_tokens": sum(s.prompt_tokens for s in steps),
            "completion_tokens": sum(s.completion_tokens for s in steps),
            "requeries": sum(s.requeries for s in steps),
            "transport_retries": sum(s.transport_retries for s in steps),
            "mean_latency_s": round(sum(s.latency_s for s in steps) / len(steps), 4),
            "cost_usd": round(sum(costs), 6) if costs else None,
            **model_time_percentiles([s.model_s for s in steps if not s.cached]),
        }


def model_time_percentiles(times: Iterable[float | None]) -> dict[str, float | None]:
    """p50 and p95 of the model server's time per step (``model_p50_s``,
    ``model_p95_s``), over the steps where it was measured; None where none was."""
    known = [t for t in times if t is not None]
    if not known:
        return {"model_p50_s": None, "model_p95_s": None}
    p50, p95 = np.percentile(known, [50, 95])
    return {"model_p50_s": round(float(p50), 4), "model_p95_s": round(float(p95), 4)}


@dataclass(frozen=True)
class Decision:
    """A pilot's answer: the action, its string form, the justification and the raw text.

    Attributes:
        raw: the complete reply (reasoning included), so a run can be audited.
        usage: what the step cost a model pilot; None for pilots without a model.
        exchanges: the model requests and replies behind the decision, as plain JSON
            records (``messages`` with image data URLs, ``reply``, ``rejected``, ...);
            the run folder stores them without knowing any backend.
        extra: other per-step fields a pilot wants in steps.jsonl.
    """

    action: Action
    action_text: str
    justification: str
    raw: str = ""
    usage: Usage | None = None
    exchanges: tuple[Mapping[str, Any], ...] = ()
    extra: dict[str, object] = field(default_factory=dict)
