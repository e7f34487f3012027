"""The Gymnasium environment: the one place where a pose is sensed, moved and checked.

Every driver steps the vehicle through `CaveNavEnv`: the episode loop behind
`cavenav run`, reinforcement-learning code, evaluation sweeps and the safety shield
(`cavenav.sim.wrappers.SafetyShield`). It is registered as ``cavenav/CaveNav-v0`` on
``import cavenav`` with a budget of 150 steps (Gymnasium's ``TimeLimit`` truncation)::

    import cavenav, gymnasium
    env = gymnasium.make("cavenav/CaveNav-v0", scenario="S3")
    obs, info = env.reset(seed=0)
    obs, reward, terminated, truncated, info = env.step("forward 0.5 m, turn left 15 deg")

Learners take ``cavenav/CaveNav-vector-v0``: actions as four numbers, 84 x 84 images
and `LEARNER_REWARD`, ready for Stable-Baselines3's ``MultiInputPolicy``.
"""

from __future__ import annotations

import math
import string
import time
from collections.abc import Mapping, MutableMapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Literal

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from cavenav.core.errors import ActionError, ConfigError
from cavenav.core.types import DEFAULT_RULES, Action, Cruise, Observation, Pose, Rules, VehicleBody
from cavenav.motion.actions import (
    DEFAULT_SPACE,
    ActionSpace,
    action_bounds,
    format_action,
    parse_action,
    snap_action,
)
from cavenav.motion.energy import BATTERY_WH, PowerModel, checked_budget, lamp_watts
from cavenav.motion.kinematics import Drift, Kinematic, Motion, carried
from cavenav.sensors.camera import pixel_size
from cavenav.sensors.dvl import DopplerLog
from cavenav.sensors.rig import SensorConfig, SensorRig
from cavenav.sensors.sonar import SONARS, Sonar
from cavenav.world.collision import clearance, swept_collision
from cavenav.world.current import Current, CurrentField, carry
from cavenav.world.geodesic import NoPath, shortest_path_of
from cavenav.world.guideline import check_colour
from cavenav.world.raycast import RayCaster
from cavenav.world.scenarios import SCENARIOS, Scenario, load_scenario, validate_start
from cavenav.world.silt import SiltCloud

__all__ = [
    "ACTION_CHARSET",
    "LEARNER_REWARD",
    "ActionText",
    "TRAINING_SEEDS",
    "CaveNavEnv",
    "Reward",
    "Timings",
    "learner_env",
    "read_action",
    "snap_action",
]

# Every character the action grammar needs: words of both cases, numbers, units, signs.
ACTION_CHARSET = string.ascii_letters + string.digits + " .,-+°"
# Cave seeds drawn for training when no seed is fixed; seeds from here up are held out.
TRAINING_SEEDS = 1000


def read_action(
    action: object, space: ActionSpace, action_format: Literal["text", "vector"] = "text"
) -> tuple[Action, str | None]:
    """The action ``action`` asks for and, when it is not admissible, why (then hold).

    What `CaveNavEnv.step` accepts: an action string, an action vector (with
    ``action_format="vector"``) or an `Action`; anything else holds, saying why. A
    wrapper that judges actions before the environment (`cavenav.sim.wrappers.SafetyShield`)
    reads them the same way.
    """
    try:
        if isinstance(action, Action):
            return space.validate(action), None
        if action_format == "vector" and not isinstance(action, str):
            return snap_action(action, space), None
        return parse_action(action, space), None
    except ActionError as exc:
        return Action(), str(exc)


def _drift(motion: Motion, pose: Pose, action: Action, reached: Pose) -> Drift | None:
    """What ``motion`` reports of its drift; a Motion written before `Motion.drift`
    existed (only ``start`` and ``move``) is measured against the kinematics, as the
    environment then did for every Motion but `Kinematic`."""
    if hasattr(motion, "drift"):
        return motion.drift(pose, action, reached)
    return Drift.of(pose, action, reached)


def _vehicle_move(motion: Motion) -> dict[str, Any] | None:
    """How a vehicle flew the last move (`cavenav.vehicle.control.MoveReport`): asked and
    flown, how it ended and how far off; None for a Motion that keeps no such report."""
    report = getattr(motion, "last_move", None)
    return None if report is None else report.to_dict()


def _water(motion: Motion | None, current: Current | None) -> Current:
    """The current the simulated vehicle flies in; refused with a vehicle's own motion."""
    current = current or Current()
    if motion is not None and not current.still:
        raise ConfigError(
            "a current is simulated water for the simulated vehicle; a vehicle over "
            "MAVLink meets its own (the fake one has its own current)"
        )
    return current


def _check_modes(render_mode: str | None, action_format: str) -> None:
    if render_mode not in (None, "rgb_array"):
        raise ConfigError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
    if action_format not in ("text", "vector"):
        raise ConfigError(f"action_format must be 'text' or 'vector', got {action_format!r}")


def _sized(sensors: SensorConfig, resolution: tuple[int, int] | None) -> SensorConfig:
    """``sensors`` with the forward camera at ``resolution`` where given."""
    if resolution is None:
        return sensors
    return sensors.with_resolution(*pixel_size(resolution, "resolution"))


def _penalty(collision_penalty: float | None) -> dict[str, float]:
    """`Reward`'s collision term as the keyword before `Reward` sets it."""
    return {} if collision_penalty is None else {"collision": collision_penalty}


def _power(sensors: SensorConfig, body: VehicleBody) -> PowerModel:
    """What the vehicle draws, with the lamps ``sensors`` light the cave with."""
    optics = sensors.optics
    lamps_on = optics.light_power is None or optics.light_power > 0
    lamps_w = lamp_watts(optics.lamp_count, optics.lamp_lumens) if lamps_on else 0.0
    return PowerModel(lamps_w=lamps_w, body=body)


def _observation_space(sensors: SensorConfig) -> spaces.Dict:
    """The ``Dict`` of images and sounder ranges that ``sensors`` produce, shaped as
    learning libraries expect: every image with a channel axis last, so that a uint8 one
    is an image to them (Stable-Baselines3 gives it a CNN), and each range a vector."""
    camera, d_max = sensors.camera, float(sensors.depth_max_m)
    sounder = float(sensors.sounder_max_range_m)
    image = (camera.height, camera.width)
    return spaces.Dict(
        {
            "rgb": spaces.Box(0, 255, (*image, 3), np.uint8),
            "depth": spaces.Box(0, 255, (*image, 1), np.uint8),
            "depth_m": spaces.Box(0.0, d_max, (*image, 1), np.float32),
            "d_top": spaces.Box(0.0, sounder, (1,), np.float32),
            "d_bottom": spaces.Box(0.0, sounder, (1,), np.float32),
            **_acoustic_space(sensors),
        }
    )


def _acoustic_space(sensors: SensorConfig) -> dict[str, spaces.Box]:
    """The sonar's (beams, bins, 1) echoes and the DVL's (velocity forward, left, up in
    m/s, altitude in m, lock 0 or 1), for the instruments ``sensors`` carry."""
    found: dict[str, spaces.Box] = {}
    if sensors.sonar is not None:
        sonar = SONARS[sensors.sonar]
        beams = len(sonar.bearings_deg())
        found["sonar"] = spaces.Box(0, 255, (beams, sonar.samples, 1), np.uint8)
    if sensors.dvl:
        found["dvl"] = spaces.Box(-np.inf, np.inf, (5,), np.float32)
    return found


@dataclass(frozen=True)
class Reward:
    """What a step earns, term by term (``info["reward_terms"]``; the reward is their sum).

    Attributes:
        progress: per metre made good toward the exit (along the passage's centre line
            where the cave has one); a step moves at most 2 m, so this term is within
            +-2 a step at the default. Turning in place earns nothing; backing up costs
            what it loses.
        collision: subtracted once, on the step that touches a surface (which ends the
            episode).
        standoff: per step, per metre by which the clearance (the distance from the
            vehicle's centre to the nearest surface) falls short of the standoff
            (`Rules.standoff_m`, 2 m): at 0.5, a step 1 m from a wall costs 0.5. In a
            passage narrower than twice the standoff it cannot be avoided, only made
            smaller by keeping to the middle.
        exit: added on the step that passes an exit portal.
    """

    progress: float = 1.0
    collision: float = 10.0
    standoff: float = 0.0
    exit: float = 0.0


# For learners: keep off the walls, and finishing is worth a collision's cost.
LEARNER_REWARD = Reward(standoff=0.5, exit=10.0)


class ActionText(spaces.Text):
    """Action strings over `ACTION_CHARSET`. Learning libraries refuse a text space, and
    say so with its repr: that names the space learners want instead."""

    def __repr__(self) -> str:
        return (
            f"{super().__repr__()} (action strings; a learner wants four numbers: "
            "gymnasium.make('cavenav/CaveNav-vector-v0'), or action_format='vector')"
        )


def _spaces(
    sensors: SensorConfig, action_format: str, space: ActionSpace
) -> tuple[spaces.Dict, spaces.Space]:
    """The observation and action spaces of an environment with these settings."""
    return _observation_space(sensors), _action_space(action_format, space)


def _action_space(action_format: str, space: ActionSpace) -> spaces.Space:
    """Action strings over `ACTION_CHARSET`, or a ``Box`` of the largest magnitudes."""
    if action_format == "text":
        return ActionText(300, charset=ACTION_CHARSET)
    high = action_bounds(space)
    return spaces.Box(-high, high, dtype=np.float32)


@dataclass(frozen=True)
class Timings:
    """How long a reset or a step took on this machine, in milliseconds.

    Any two compare equal (no field takes part in ``==``): the same step is the same
    step however fast the machine ran it, and ``info`` must compare equal across two runs
    of one seed and one action sequence (Gymnasium's determinism check), timings and all.

    Attributes:
        sense_ms: rendering the observation: camera, depth and echo sounders.
        physics_ms: reading the action, moving the vehicle and the swept collision check;
            None after a reset.
    """

    sense_ms: float = field(compare=False)
    physics_ms: float | None = field(default=None, compare=False)


@dataclass(frozen=True)
class Move:
    """What `CaveNavEnv.begin_step` did, for `CaveNavEnv.end_step` to report."""

    command: Action  # as carried out (a hold when inadmissible)
    invalid: str | None  # why the action was not admissible
    collision_pose: Pose | None  # where the body touched, if it did
    terms: dict[str, float]  # the reward's terms
    energy_wh: float
    seconds: float  # the move's duration through the water
    drift: Drift | None
    physics_ms: float  # how long the move and its checks took
    vehicle: dict[str, Any] | None = None  # how a vehicle flew it (`_vehicle_move`)


@dataclass(frozen=True)
class _World:
    """One cave ready to fly: scenario, ray caster and sensor rig."""

    key: tuple[str, int | None]
    scenario: Scenario
    caster: RayCaster
    rig: SensorRig
    sonar: Sonar | None = None
    dvl: DopplerLog | None = None

    def acoustic(
        self, observation: Observation, before: Pose | None, after: Pose, seconds: float,
        seed: int, silt: SiltCloud | None,
    ) -> Observation:  # fmt: skip
        """``observation`` with what the sonar and the DVL report after the move from
        ``before`` to ``after`` that lasted ``seconds`` (None: no move, the start, where
        the scanning sonar had ``seconds`` to sweep and the DVL has measured nothing)."""
        if self.sonar is None and self.dvl is None:
            return observation
        sonar = None if self.sonar is None else self.sonar.observe(after, seconds, seed, silt)
        dvl = None
        if self.dvl is not None:
            dvl = self.dvl.measure(before or after, after, 0.0 if before is None else seconds)
        return replace(observation, sonar=sonar, dvl=dvl)


class CaveNavEnv(gym.Env[dict[str, np.ndarray], str | np.ndarray]):
    """Fly a BlueROV2-sized vehicle through a cave, one action string at a time.

    Observation (a ``Dict``; H x W is 480 x 640 unless ``resolution`` or ``sensors``
    says otherwise): ``rgb`` (H, W, 3) uint8 forward colour image; ``depth``
    (H, W, 1) uint8 normalised depth, dark near, as a VLM sees it; ``depth_m`` (H, W, 1)
    float32 planar depth in metres, D_max where nothing is nearer; ``d_top`` and
    ``d_bottom`` float32 arrays of shape (1,) from the echo sounders, bounded by their
    range. (Until November 2026 the depths were (H, W) and the ranges of shape (): the
    channel axis and the vectors are what learning libraries expect of images and
    measurements.) The same observation, typed as a pilot receives it, with depth
    images (H, W) and ranges as floats, is ``info["observation"]``.

    Action: an action string of the grammar in `cavenav.motion.actions` (``spaces.Text`` over
    `ACTION_CHARSET`), or with ``action_format="vector"`` a ``Box`` of (df, dr, dz, dpsi
    in degrees) snapped to the admissible sets by `snap_action`. An unparseable or
    inadmissible action, of whatever type, does not raise: the vehicle holds,
    ``info["invalid_action"]`` says why, and the step counts toward the budget.

    Episode: ``terminated`` when the vehicle passes an exit portal, leaves through the
    cave's entrance (a mesh scenario's ``[entrance]``: a failure, never success) or
    touches a surface (the whole swept move is checked; after a collision the vehicle
    stays at its last safe pose), or when the moves have spent an energy budget
    (``battery_wh``; "battery"); ``truncated`` only through wrappers: Gymnasium's
    ``TimeLimit`` (150 steps when made with ``gymnasium.make``, whatever the scenario's
    own ``step_budget``: pass ``max_episode_steps`` for the longer families) and
    `cavenav.sim.wrappers.StuckLimit` where you add it.

    Reward: the sum of `Reward`'s terms, each in ``info["reward_terms"]``. By default,
    metres made good toward the exit during the step, measured along the passage's
    centre line where the cave has one (procedural caves) and otherwise as the decrease
    of the distance to the nearest exit plane; minus 10 on a collision. Turning in place
    earns nothing; backing up costs what it loses. `LEARNER_REWARD` (the default of
    ``cavenav/CaveNav-vector-v0``) adds a cost for flying inside the standoff and a bonus
    at the exit.

    Info: ``pose`` (x, y, z, yaw_deg), ``clearance_m`` (exact distance to the nearest
    surface), ``collision``, ``exit``, ``entrance`` (left through the entrance),
    ``action`` (the action executed, canonical), ``invalid_action`` (the reason, or
    None), ``progress_m`` (made good since the start), ``collision_pose``,
    ``scenario``/``cave_seed``, ``termination`` ("exit", "collision",
    "exited_entrance", "battery" or None while the episode goes on), ``energy_used_wh``
    and ``energy_left_wh`` (`cavenav.motion.energy`), ``clock_s`` (the time the moves took
    through the water), ``current_m_s`` (the water's speed at the vehicle; None in still
    water) and, after a step, ``reward_terms`` (`Reward`'s terms, which sum to the
    reward), ``step_energy_wh`` and ``move_s``. For drivers, typed:
    ``observation`` (the `Observation` a pilot receives; its ``previous_action`` is the
    action executed), ``vehicle_pose`` (the `Pose`, unrounded) and ``timings``
    (`Timings`, equal whatever they hold, so that ``info`` stays deterministic). A
    `Motion` that drifts from its commands (a vehicle), or a current, adds
    ``commanded_pose``, ``drift_m`` and ``drift_deg`` (`cavenav.motion.kinematics.Drift`).

    Water and battery: with a ``current`` (`cavenav.world.current.Current`) the water
    flows through the cave and carries the vehicle for each move's duration at its cruise
    speed (``cruise``, `cavenav.core.types.Cruise`); ``info`` then gains the drift. None or a
    discharge of 0 keep SPEC section 5's kinematics; a vehicle (``motion``) meets its own
    water, so the two do not go together. Every move's energy is counted
    (`cavenav.motion.energy`, with the lamps of ``sensors``): against ``battery_wh`` where
    given, and the episode ends as "battery" once that is spent; otherwise against a
    full pack, which never ends an episode.

    Reset options (for that reset only): ``scenario`` (a family name, a scenario file's path,
    or a `Scenario`), ``cave_seed`` (which cave of a procedural family). Seeds are drawn
    from ``self.np_random``: the sensor noise of the episode, and the cave itself when
    the environment was made with ``cave_seed=None`` (seeds below `TRAINING_SEEDS`).
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 4}
    _field: CurrentField | None  # the episode's flowing water; None: still
    _world: _World | None  # the cave flown; None before the first reset
    pose: Pose | None  # where the vehicle is; None before the first reset
    observation: Observation | None

    def __init__(
        self,
        scenario: str | Path | Scenario = "S1",
        *,
        cave_seed: int | None = 0,
        sensors: SensorConfig | None = None,
        resolution: tuple[int, int] | None = None,
        body: VehicleBody | None = None,
        rules: Rules = DEFAULT_RULES,
        space: ActionSpace = DEFAULT_SPACE,
        action_format: Literal["text", "vector"] = "text",
        collision_penalty: float | None = None,
        reward: Reward | None = None,
        render_mode: str | None = None,
        motion: Motion | None = None,
        current: Current | None = None,
        battery_wh: float | None = None,
        caves: MutableMapping[tuple[str, int | None], tuple[Scenario, RayCaster]] | None = None,
        guideline: str | None = None,
    ):
        """
        Args:
            scenario: the cave flown after a reset without a ``scenario`` option.
            cave_seed: which cave of a procedural family; None draws one per reset.
            sensors: camera, sounders and optics (default: SPEC section 2). A scenario
                file's [optics] and [sensors] tables are the drivers' to layer
                (`SensorConfig.for_scenario`): the environment flies the sensors it was
                made with, so its observation space holds for every reset.
            resolution: (width, height) of the forward camera, over ``sensors``; e.g.
                (84, 84) for fast training. The horizontal field of view stays 53.1
                degrees, pixels stay square (`SensorConfig.with_resolution`).
            body: the vehicle's size, for the swept collision check.
            rules: the strategy's distances (for the shield and the metrics of drivers).
            space: admissible magnitudes.
            action_format: "text" (action strings) or "vector" (four numbers).
            collision_penalty: sets ``reward.collision`` (the keyword before `Reward`).
            reward: its terms (default: progress and collisions, the method's reward).
            render_mode: None or "rgb_array" (the forward colour image).
            motion: who carries out the actions: the kinematics of SPEC section 5 (the
                default), or a vehicle (`cavenav.vehicle.mavlink.ArduSubMotion`), whose
                reported pose is then sensed and checked; ``info`` gains the move's
                drift from the pose the kinematics command (`Motion.drift`).
            current: the water's flow; battery_wh: an energy budget (class docstring).
            caves: built caves and ray casters shared by environments (`cavenav.sim.vector_env`).
            guideline: a diver's line of this colour ("white" or "yellow") laid in every
                cave flown, as ``--guideline`` lays it (`Scenario.with_guideline`); None:
                a line only where a scenario file asks for one.
        """
        _check_modes(render_mode, action_format)
        self.render_mode, self.body = render_mode, body or VehicleBody()
        self.sensors = _sized(sensors or SensorConfig(), resolution)
        self.rules, self.space, self.action_format = rules, space, action_format
        self.reward = replace(reward or Reward(), **_penalty(collision_penalty))
        self.motion: Motion = motion or Kinematic()
        self.current, self.battery_wh = _water(motion, current), checked_budget(battery_wh)
        self.cruise, self.power = Cruise(), _power(self.sensors, self.body)
        self._default_scenario, self._default_cave_seed = scenario, cave_seed
        self._guideline = None if guideline is None else check_colour(guideline)
        self._world, self._caves = None, caves
        self.observation_space, self.action_space = _spaces(self.sensors, action_format, space)  # type: ignore[assignment]
        self.pose, self.observation = None, None
        self._timings, self._clearance, self._progress = Timings(0.0), math.inf, 0.0
        self._steps = self._noise_seed = 0
        self._ended = self._left_by_entrance = self._flat = False
        self._field, self._clock_s, self._energy_wh = None, 0.0, 0.0  # water, time, energy

    # ------------------------------------------------------------------ the cave
    @property
    def scenario(self) -> Scenario:
        """The cave of the current episode (loaded by the first reset)."""
        if self._world is None:
            raise gym.error.ResetNeeded("Call reset before using the environment.")
        return self._world.scenario

    @property
    def caster(self) -> RayCaster:
        """Geometry queries on the current cave, for drivers that plot it (never pilots)."""
        if self._world is None:
            raise gym.error.ResetNeeded("Call reset before using the environment.")
        return self._world.caster

    @property
    def timings_ms(self) -> dict[str, float]:
        """How long the last reset or step took, milliseconds: ``{"sense": ...}`` after a
        reset, ``{"physics": ..., "sense": ...}`` after a step, empty before the first
        reset. ``info["timings"]`` carries the same as a `Timings`; this is where drivers
        read them before they travelled in ``info``."""
        if self.pose is None:
            return {}
        sense, physics = self._timings.sense_ms, self._timings.physics_ms
        return {"sense": sense} if physics is None else {"physics": physics, "sense": sense}

    def _load(self, scenario: str | Path | Scenario, cave_seed: int | None) -> _World:
        """The world for ``scenario``, built only when it is not the current one."""
        if isinstance(scenario, Scenario):
            key: tuple[str, int | None] = (f"object:{id(scenario)}", scenario.seed)
        else:
            name = str(scenario)
            procedural = name in SCENARIOS
            if procedural and cave_seed is None:
                cave_seed = int(self.np_random.integers(TRAINING_SEEDS))
            key = (SCENARIOS[name].name if procedural else name, cave_seed if procedural else None)
        if self._world is not None and self._world.key == key:
            return self._world
        if self._caves is not None and key in self._caves:
            cave, caster = self._caves[key]
        else:
            name, seed = key
            cave = scenario if isinstance(scenario, Scenario) else load_scenario(name, seed or 0)
            caster = RayCaster(cave.mesh)
        validate_start(cave, caster, self.body)
        if self._caves is not None:
            self._caves[key] = cave, caster
        if self._guideline is not None:  # on this environment's cave, not the shared one
            cave = cave.with_guideline(self._guideline)
        self._world = None  # free the previous cave's tables before building the next
        sensors = self.sensors
        sonar = None if sensors.sonar is None else Sonar(caster, SONARS[sensors.sonar])
        dvl = DopplerLog(caster) if sensors.dvl else None
        rig = SensorRig(caster, sensors, cave.guideline)
        return _World(key, cave, caster, rig, sonar, dvl)

    # ------------------------------------------------------------------ the API
    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        super().reset(seed=seed)
        options = dict(options or {})
        unknown = set(options) - {"scenario", "cave_seed"}
        if unknown:
            raise ConfigError(
                f"unknown reset option(s) {', '.join(sorted(unknown))}; "
                "the options are 'scenario' and 'cave_seed'"
            )
        self._world = self._load(
            options.get("scenario", self._default_scenario),
            options.get("cave_seed", self._default_cave_seed),
        )
        self._noise_seed = int(self.np_random.integers(2**31))
        self.pose = self.motion.start(self.scenario.start)
        self._clearance = clearance(self.caster, self.pose)
        self._progress = self.scenario.progress(self.pose.position)
        self._steps = 0
        self._ended = self._left_by_entrance = self._flat = False
        self._silt = SiltCloud() if self._silts_out() else None
        self._field = self._current_field()
        self._clock_s = self._energy_wh = 0.0
        started = time.perf_counter()
        world = self._world
        observation = world.rig.observe(self.pose, 0, self._noise_seed)
        if world.sonar is not None:  # a scanning head has swept its sector at the start
            world.sonar.reset()
        if world.dvl is not None:
            world.dvl.reset(self._noise_seed)
        sweep_s = 0.0 if world.sonar is None else world.sonar.sweep_s
        observation = world.acoustic(
            observation, None, self.pose, sweep_s, self._noise_seed, self._silt
        )
        self.observation = replace(observation, energy_left_wh=self._energy_left_wh)
        self._timings = Timings(sense_ms=1e3 * (time.perf_counter() - started))
        info = self._info(Action(), None, None)
        if getattr(self.motion, "start_report", None) is not None:  # a vehicle's dive
            info["vehicle_start"] = self.motion.start_report  # type: ignore[attr-defined]
        return self._observation_dict(), info

    def step(
        self, action: str | np.ndarray | Action
    ) -> tuple[dict[str, np.ndarray], float, bool, bool, dict[str, Any]]:
        return self.end_step(self.begin_step(action))

    def begin_step(self, action: str | np.ndarray | Action) -> Move:
        """The first half of `step`: the move, its collision check and its reward, up to
        what the sensors see after it (`end_step`). A batched environment
        (`cavenav.sim.vector_env`) casts many environments' `sensor_rays` between the two."""
        if self._world is None or self.pose is None:
            raise gym.error.ResetNeeded("Call reset before using step method.")
        if self._ended:
            raise gym.error.ResetNeeded(
                "The episode has ended (exit, entrance, collision or battery): call reset "
                "before step."
            )
        started = time.perf_counter()
        command, invalid = self.command(action)
        start = self._before = self.pose
        # One pose update: the vehicle's move, then what the water carried it off it.
        moved = self.motion.move(start, command)
        asked, command = command, getattr(self.motion, "flown", command)  # cut at a limit
        passage = carry(self._field, start, command, moved, self._clock_s, self.cruise)
        flowing = self._field is not None
        if flowing:
            moved = carried(moved, passage.carried_m)
        self._clock_s += passage.seconds
        step_wh = self.power.energy_wh(passage.dt, passage.through_water)
        self._energy_wh += step_wh
        hit = swept_collision(self.caster, self.body, start, moved, self._clearance)
        if not hit:
            self.pose = moved
            self._clearance = clearance(self.caster, moved)
        exited = not hit and self.scenario.exited(self.pose.position)
        self._left_by_entrance = (
            not hit and not exited and self.scenario.left_through_entrance(self.pose.position)
        )
        progress = self.scenario.progress(self.pose.position)
        terms = self._reward_terms(progress - self._progress, hit, exited)
        self._progress = progress
        self._steps += 1
        self._flat = not (hit or exited or self._left_by_entrance) and self._battery_spent
        self._ended = hit or exited or self._left_by_entrance or self._flat
        if self._silt is not None:
            floor = float(self.caster.first_hit(self.pose.position, np.array([0.0, 0.0, -1.0])))
            field, now = self._field, self._clock_s
            water = None if field is None else (lambda at: field.velocity(at, now))
            self._silt = self._silt.stirred(self.pose, command, floor, water)
        if flowing:
            drift: Drift | None = Drift.of(start, command, moved)
        else:
            drift = _drift(self.motion, start, asked, moved)
        physics_ms = 1e3 * (time.perf_counter() - started)
        return Move(command, invalid, moved if hit else None, terms, step_wh, passage.seconds,
                    drift, physics_ms, _vehicle_move(self.motion))  # fmt: skip

    def sensor_rays(self) -> np.ndarray:
        """The rays the sensors cast where the vehicle is now (`SensorRig.rays`)."""
        assert self._world is not None and self.pose is not None
        return self._world.rig.rays(self.pose)

    def end_step(
        self, move: Move, cast: Mapping[str, np.ndarray] | None = None, cast_ms: float = 0.0
    ) -> tuple[dict[str, np.ndarray], float, bool, bool, dict[str, Any]]:
        """The second half of `step`: what the sensors see after ``move``; ``cast``: what
        casting `sensor_rays` gave, when the caller cast them (None casts here), and
        ``cast_ms`` this environment's share of that cast's time, counted as sensing."""
        assert self._world is not None and self.pose is not None
        sensed = time.perf_counter()
        observation = self._world.rig.observe(
            self.pose, self._steps, self._noise_seed, self._silt, cast
        )
        observation = self._world.acoustic(
            observation, self._before, self.pose, move.seconds, self._noise_seed, self._silt
        )
        self.observation = replace(
            observation, previous_action=move.command, energy_left_wh=self._energy_left_wh
        )
        sense_ms = cast_ms + 1e3 * (time.perf_counter() - sensed)
        self._timings = Timings(physics_ms=move.physics_ms, sense_ms=sense_ms)
        info = self._info(move.command, move.invalid, move.collision_pose)
        info["reward_terms"] = move.terms
        info.update(step_energy_wh=move.energy_wh, move_s=move.seconds)
        if move.drift is not None:
            info.update(move.drift.to_info())
        if move.vehicle is not None:
            info["vehicle_move"] = move.vehicle
        reward = float(sum(move.terms.values()))
        return self._observation_dict(), reward, self._ended, False, info

    def render(self) -> np.ndarray | None:
        """The forward colour image (H, W, 3) uint8 with ``render_mode="rgb_array"``."""
        if self.render_mode != "rgb_array" or self.observation is None:
            return None
        return self.observation.rgb.copy()

    # ------------------------------------------------------------------ helpers
    @property
    def _energy_left_wh(self) -> float:
        """What the battery has left: of the budget, else of a full pack."""
        return (self.battery_wh or BATTERY_WH) - self._energy_wh

    @property
    def _battery_spent(self) -> bool:
        return self.battery_wh is not None and self._energy_wh >= self.battery_wh

    def _current_field(self) -> CurrentField | None:
        """The water of this episode: measured on the cave, gusts drawn from the
        episode's seed; None in still water.

        Raises:
            ConfigError: a flowing current in a cave with no centre line and no path
                from the start to an exit to take for one.
        """
        if self.current.still:
            return None
        line = self.scenario.centreline
        if line is None:
            try:
                line = shortest_path_of(self.scenario).points
            except NoPath as exc:
                raise ConfigError(f"a current needs the passage's course: {exc}") from None
        return CurrentField.measure(self.caster, line, self.current, self._noise_seed)

    def _silts_out(self) -> bool:
        """Whether thrust near the floor raises silt: the optics' setting, else the cave's
        own choice (the crawl's silt floor silts out)."""
        chosen = self.sensors.optics.silt_out
        return bool(self.scenario.optics.get("silt_out", False)) if chosen is None else chosen

    @property
    def collision_penalty(self) -> float:
        """What a collision costs (``reward.collision``)."""
        return self.reward.collision

    def _reward_terms(self, made_good: float, hit: bool, exited: bool) -> dict[str, float]:
        """Each term of this step's reward (`Reward`), in the order they are summed."""
        short = max(self.rules.standoff_m - self._clearance, 0.0)
        return {
            "progress": self.reward.progress * made_good,
            "collision": -self.reward.collision if hit else 0.0,
            "standoff": -self.reward.standoff * short,
            "exit": self.reward.exit if exited else 0.0,
        }

    def command(self, action: object) -> tuple[Action, str | None]:
        """The action ``action`` asks for and, when it is not admissible, why (then hold):
        `read_action` in this environment's action space and format."""
        return read_action(action, self.space, self.action_format)

    def _observation_dict(self) -> dict[str, np.ndarray]:
        obs, cfg = self.observation, self.sensors
        assert obs is not None
        return obs.arrays(cfg.depth_max_m, cfg.sounder_max_range_m)

    def _info(
        self, executed: Action, invalid: str | None, collision_pose: Pose | None
    ) -> dict[str, Any]:
        assert self.pose is not None and self._world is not None
        collided, entrance = collision_pose is not None, self._left_by_entrance
        exited = self._ended and not collided and not entrance and not self._flat
        ending = {
            "collision": collided,
            "exit": exited,
            "exited_entrance": entrance,
            "battery": self._flat,
        }
        return {
            "pose": self.pose.to_dict(),
            "clearance_m": float(self._clearance),
            "collision": collided,
            "exit": exited,
            "entrance": entrance,
            "action": format_action(executed),
            "invalid_action": invalid,
            "progress_m": float(self._progress),
            "collision_pose": collision_pose.to_dict() if collision_pose else None,
            "scenario": self.scenario.name,
            "cave_seed": self._world.key[1],
            "termination": next((name for name, ended in ending.items() if ended), None),
            "observation": self.observation,
            "vehicle_pose": self.pose,
            "timings": self._timings,
            "silt_g": None if self._silt is None else round(self._silt.mass_g, 1),
            "energy_used_wh": self._energy_wh,
            "energy_left_wh": self._energy_left_wh,
            "clock_s": self._clock_s,
            "current_m_s": self._water_speed(),
        }

    def _water_speed(self) -> float | None:
        """The water's speed where the vehicle is now, m/s; None in still water."""
        if self._field is None or self.pose is None:
            return None
        return float(np.linalg.norm(self._field.velocity(self.pose.position, self._clock_s)))


def learner_env(
    scenario: str | Path | Scenario = "S1",
    *,
    resolution: tuple[int, int] | None = (84, 84),
    action_format: Literal["text", "vector"] = "vector",
    reward: Reward | None = LEARNER_REWARD,
    **options: Any,
) -> CaveNavEnv:
    """`CaveNavEnv` as ``cavenav/CaveNav-vector-v0`` makes it: vector actions, 84 x 84
    images and `LEARNER_REWARD`, each overridable as in `CaveNavEnv`."""
    return CaveNavEnv(
        scenario, resolution=resolution, action_format=action_format, reward=reward, **options
    )
