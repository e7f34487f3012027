"""How an episode is flown, as one frozen value: `EpisodeConfig`.

Every way of flying builds one: `cavenav run`, `eval` (a sweep keeps it in sweep.json),
`fly` and `render` from their flags, the environment (`cavenav.episode.loop.make_env`),
the vehicle flights (`cavenav.episode.on_vehicle`) and a script from its keywords. Each
default is written here once.

Most fields are what a user chooses before a cave is known: overrides over what the cave
itself brings (a scenario file's [optics], [sensors] and [water] tables, a family's step
budget). `for_episode` lays them over one cave and settles the noise seed; the episode
driver flies, and summary.json records, that settled value.
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any

from cavenav.core.errors import ConfigError
from cavenav.core.types import DEFAULT_RULES, STEP_BUDGET, Rules, VehicleBody
from cavenav.motion.energy import checked_budget
from cavenav.sensors.config import SENSOR_KEYS, SIZE_KEYS, SensorConfig
from cavenav.sensors.depth import EXR_COMPRESSIONS, ExrCompression
from cavenav.world.current import Current
from cavenav.world.guideline import check_colour
from cavenav.world.scenario import Difficulty
from cavenav.world.scenarios import Scenario, load_scenario

__all__ = [
    "FRAME_MODES",
    "SENSOR_FIELDS",
    "SETTLED",
    "VIDEO_MODES",
    "EpisodeConfig",
    "EpisodeSettings",
    "configured",
]

# What a sweep keeps of each step's images, as sweep.json names it: (frames, EXR).
FRAME_MODES = {"all": (True, True), "png": (True, False), "none": (False, False)}
# Which episodes of a sweep get an episode.mp4 (`cavenav eval --video`).
VIDEO_MODES = ("none", "failures", "all")
# The settings sweep.json keeps under "sensors".
SENSOR_FIELDS = ("sounder", "depth_max_m", "optics", *SENSOR_KEYS)


@dataclass(frozen=True)
class EpisodeConfig:
    """How an episode is flown.

    Attributes:
        max_steps: step budget; None gives the scenario's own (`Scenario.step_budget`:
            SPEC's 150 for S1-S5, more for the long families).
        stuck_after: end the episode as ``stuck`` after this many steps in a row without
            headway (`cavenav.sim.wrappers.StuckLimit`): neither 0.5 m more progress toward
            the exit than ever before nor a 2 m cube of the cave entered for the first
            time. 50 leaves room to explore a side passage and come back out of it; None
            never ends an episode so.
        shield: put the safety shield between the pilot and the vehicle.
        save_frames: write the RGB and depth PNG of every step; sweeps can turn this off.
        save_exr: with the frames, the depth in metres as OpenEXR (1.24 MB of the 2.05 MB
            a step takes, uncompressed).
        exr_compression: "none" (the fastest), "zip" (a fifth smaller) or "htj2k" (two
            thirds smaller; OpenEXR 3.4 reads it), all lossless: `cavenav.sensors.depth`.
        plots: draw topdown.png and side.png at the end.
        seed: seeds the sensor noise (the environment's reset seed); None draws it from
            the episode's own seed (`for_episode`), so that another cave flies other noise
            too. `cavenav run --noise-seed` sets it.
        sensors: the rig before the cave's tables and the overrides below: its sounder
            model and D_max are the ``--sounder`` and ``--depth-max`` flags.
        optics: optics overrides over the scenario's [optics] table (water, light_power,
            ...; see `cavenav.sensors.optics.optics_from_table`); absent keys keep it.
        resolution, sounder_resolution: (width, height) pixels over the scenario's
            [sensors] table; None keeps it.
        depth_source: "exact", "stereo" or "none" over the scenario's [sensors] table;
            None keeps it.
        sonar, dvl: the imaging sonar ("ping360", "multibeam" or "none") and whether a
            DVL rides along, over the scenario's [sensors] table; None keeps it.
        difficulty: `Difficulty` knobs of the cave family, by name (`load`).
        current: the water's flow (`cavenav.world.current.Current`); None takes the
            cave's own (`Scenario.water`: still, but where a scenario file's [water] table
            says otherwise).
        discharge_m3s, gusts: the flow's discharge and gusts over that; None keeps them.
        battery_wh: an energy budget that ends the episode as ``battery`` once spent;
            None never does (the energy is recorded either way).
        rules: the strategy's distances; the standoff counts "steps below standoff".
        body: the vehicle's size, mass and thrust (`cavenav.core.types.VehicleBody`).
        guideline: lay a diver's guideline along the cave (`cavenav.world.guideline`;
            ``--guideline``); False takes away one a scenario file lays; None keeps the
            cave's own (the families have none, as in the paper). The cave is the same
            rock for rock either way (`cave`).
        guideline_colour: "white" or "yellow", the colour of the line flown; None keeps
            the cave's own, else white.
    """

    max_steps: int | None = None
    stuck_after: int | None = 50
    shield: bool = False
    save_frames: bool = True
    save_exr: bool = True
    exr_compression: ExrCompression = "none"
    plots: bool = True
    seed: int | None = None
    sensors: SensorConfig = field(default_factory=SensorConfig)
    optics: Mapping[str, Any] = field(default_factory=dict)
    resolution: tuple[int, int] | None = None
    sounder_resolution: tuple[int, int] | None = None
    depth_source: str | None = None
    sonar: str | None = None
    dvl: bool | None = None
    difficulty: Mapping[str, float] = field(default_factory=dict)
    current: Current | None = None
    discharge_m3s: float | None = None
    gusts: float | None = None
    battery_wh: float | None = None
    rules: Rules = DEFAULT_RULES
    body: VehicleBody = field(default_factory=VehicleBody)
    guideline: bool | None = None
    guideline_colour: str | None = None

    def __post_init__(self) -> None:
        if self.exr_compression not in EXR_COMPRESSIONS:
            raise ConfigError(
                f"EXR compression {self.exr_compression!r}: choose one of "
                f"{', '.join(EXR_COMPRESSIONS)}"
            )
        for name in SIZE_KEYS:  # JSON gives lists
            size = getattr(self, name)
            if size is not None:
                object.__setattr__(self, name, tuple(size))
        Difficulty.from_dict(self.difficulty)  # a bad knob fails here, not in a worker
        SensorConfig().with_sensors(  # so does a bad sonar, DVL or depth source
            {key: getattr(self, key) for key in SENSOR_KEYS if key not in SIZE_KEYS}, "sensors"
        )
        self.current_for({})  # a bad value fails here, not in a worker
        checked_budget(self.battery_wh)
        if self.guideline is not None and not isinstance(self.guideline, bool):
            raise ConfigError(f"guideline must be true, false or unset, not {self.guideline!r}")
        if self.guideline_colour is not None:
            check_colour(self.guideline_colour)
        seed = self.seed
        if seed is not None and (not isinstance(seed, int) or isinstance(seed, bool) or seed < 0):
            raise ConfigError(f"the noise seed must be a whole number of 0 or more, not {seed!r}")

    @property
    def flowing(self) -> bool:
        """Whether this configuration makes the water flow, whatever the cave's own."""
        return bool(self.discharge_m3s) or (self.current is not None and not self.current.still)

    def current_for(self, cave: Scenario | Mapping[str, Any]) -> Current:
        """The water's flow in ``cave`` (or a [water] table): this configuration's over its
        own."""
        water: Mapping[str, Any] = cave if isinstance(cave, Mapping) else cave.water
        base = self.current or Current(
            water.get("discharge_m3s", Current.discharge_m3s),
            water.get("gusts", Current.gusts),
        )
        discharge, gusts = self.discharge_m3s, self.gusts
        return Current(
            base.discharge_m3s if discharge is None else discharge,
            base.gusts if gusts is None else gusts,
        )

    @property
    def frames(self) -> str:
        """The frames as a sweep names them: "all", "png" or "none" (`FRAME_MODES`)."""
        return "none" if not self.save_frames else "all" if self.save_exr else "png"

    def with_frames(self, mode: str) -> EpisodeConfig:
        """This configuration keeping ``mode``'s images: "all", "png" or "none".

        Raises:
            ConfigError: another mode.
        """
        if mode not in FRAME_MODES:
            raise ConfigError(f"--frames must be one of {', '.join(FRAME_MODES)}, got '{mode}'")
        save_frames, save_exr = FRAME_MODES[mode]
        return replace(self, save_frames=save_frames, save_exr=save_exr)

    def load(self, scenario: str, seed: int) -> Scenario:
        """The cave ``scenario`` (a family or a scenario file) with ``seed`` and these
        difficulty knobs; a sweep sets each knob on the families that have it instead
        (`cavenav.evaluation.sweep.SweepConfig.difficulty_for`)."""
        cave = load_scenario(scenario, seed, difficulty=Difficulty.from_dict(self.difficulty))
        return self.cave(cave)

    def cave(self, scenario: Scenario) -> Scenario:
        """``scenario`` as this configuration flies it: with a guideline laid along it
        (`Scenario.with_guideline`) where `guideline` is True or the cave has one, in
        `guideline_colour` where set, or with none where `guideline` is False. The rock,
        start and exits are the cave's own whichever it is.

        Raises:
            ScenarioError: a guideline asked of a cave with no centre line.
        """
        if self.guideline is False:
            return scenario.without_guideline()
        own = scenario.guideline
        if not (self.guideline or own):
            return scenario
        return scenario.with_guideline(self.guideline_colour or (own.colour if own else "white"))

    def sensors_for(self, cave: Scenario) -> SensorConfig:
        """The sensors in ``cave``: `sensors`, the cave's [optics] and [sensors] tables,
        then these overrides over them (`SensorConfig.for_scenario`)."""
        sizes = {key: getattr(self, key) for key in SENSOR_KEYS if getattr(self, key) is not None}
        return self.sensors.for_scenario(cave.name, cave.optics, self.optics, cave.sensors, sizes)

    def steps_in(self, cave: Scenario) -> int:
        """The steps an episode gets in ``cave``: `max_steps` when set, else the cave's own
        budget, else `cavenav.core.types.STEP_BUDGET`."""
        return self.max_steps or cave.step_budget or STEP_BUDGET

    def for_episode(self, cave: Scenario, seed: int | None = None) -> EpisodeConfig:
        """This configuration as an episode in ``cave`` flies it, every value settled: the
        step budget, the sensors (`sensors_for`), the flow (`current_for`) and the noise
        seed, which ``seed`` (the episode's own: its cave's, or its trial's in a sweep;
        None: the cave's) gives unless `seed` holds it apart. The overrides stay, as
        asked, and are in `sensors` and `current` too (`SETTLED`): settling twice changes
        nothing."""
        own_seed = (cave.seed or 0) if seed is None else seed
        return replace(
            self,
            max_steps=self.steps_in(cave),
            seed=own_seed if self.seed is None else self.seed,
            sensors=self.sensors_for(cave),
            current=self.current_for(cave),
        )

    def to_dict(self) -> dict[str, Any]:
        """JSON-able, laid out as sweep.json's "episode", "difficulty" and "sensors".

        It keeps what a sweep sets: a configuration with another rule set, body, flow or
        rig than the flags give is refused, rather than resumed as another.

        Raises:
            ConfigError: a field sweep.json cannot keep, set.
        """
        unkept = [name for name in _UNKEPT if getattr(self, name) != getattr(_DEFAULTS, name)]
        if self.sensors != _rig(self.sensors.sounder, self.sensors.depth_max_m):
            unkept.append("sensors")
        if unkept:
            raise ConfigError(f"a sweep cannot keep {', '.join(unkept)}; leave them unset")
        episode: dict[str, Any] = {
            "steps": self.max_steps,
            "stuck_after": self.stuck_after,
            "shield": self.shield,
            "frames": self.frames,
        }
        if self.seed != 0:  # absent: seed 0, as every sweep's was before it was set
            episode["noise_seed"] = self.seed
        if self.exr_compression != "none":  # no sweep flag sets it: absent, as before
            episode["exr_compression"] = self.exr_compression
        for key in (*_WATER, *_LINE):  # absent when unset, as before they existed
            if getattr(self, key) != getattr(_DEFAULTS, key):
                episode[key] = getattr(self, key)
        sensors: dict[str, Any] = {
            "sounder": self.sensors.sounder,
            "depth_max_m": self.sensors.depth_max_m,
            "optics": dict(self.optics),
        }
        for key in SENSOR_KEYS:
            value = getattr(self, key)
            if value is not None:
                sensors[key] = list(value) if key in SIZE_KEYS else value
        return {"episode": episode, "difficulty": dict(self.difficulty), "sensors": sensors}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> EpisodeConfig:
        """The configuration `to_dict` wrote; absent keys keep their defaults (a
        sweep.json written before they existed).

        Raises:
            ConfigError: an unknown key or a bad value.
            KeyError: "episode" is missing.
        """
        episode, sensors = dict(data["episode"]), dict(data.get("sensors", {}))
        unknown = set(sensors) - set(SENSOR_FIELDS)
        if unknown:
            raise ConfigError(f"sensors: unknown key(s) {', '.join(sorted(unknown))}")
        frames = episode.pop("frames", "all")
        episode.setdefault("noise_seed", 0)  # see `to_dict`
        return configured(
            **{k: episode[k] for k in (*_EPISODE_KEYS, *_WATER, *_LINE) if k in episode},
            **sensors,
            difficulty=data.get("difficulty", {}),
        ).with_frames(frames)


def _rig(sounder: str, depth_max_m: float) -> SensorConfig:
    """The rig the ``--sounder`` and ``--depth-max`` flags set."""
    return replace(_DEFAULT_RIG, sounder=sounder, depth_max_m=depth_max_m)  # type: ignore[arg-type]


# The overrides `EpisodeConfig.for_episode` lays into the sensors and the flow.
SETTLED = ("optics", *SENSOR_KEYS, "discharge_m3s", "gusts")
# The names the settings had before there was one configuration, and their names now;
# "sounder" and "depth_max_m" are fields of `EpisodeConfig.sensors`.
RENAMED = {"steps": "max_steps", "noise_seed": "seed"}
_RIG_FIELDS = ("sounder", "depth_max_m")


def configured(base: EpisodeConfig | None = None, **settings: Any) -> EpisodeConfig:
    """``base`` (the defaults when None) with ``settings`` set, by their names here or by
    the names sweep.json, the flags and `EpisodeSettings` give them: ``steps``,
    ``noise_seed``, ``sounder`` and ``depth_max_m``.

    Raises:
        TypeError: a name that is none of these.
    """
    base = base or EpisodeConfig()
    rig = {name: settings.pop(name) for name in _RIG_FIELDS if name in settings}
    known = {RENAMED.get(name, name): value for name, value in settings.items()}
    if rig:
        known["sensors"] = replace(known.get("sensors", base.sensors), **rig)
    return replace(base, **known)


def EpisodeSettings(**settings: Any) -> EpisodeConfig:  # noqa: N802 - the old class's name
    """Deprecated: `EpisodeConfig` is the one episode configuration now; this builds one
    from the old keywords (`configured`)."""
    warnings.warn(
        "EpisodeSettings is now EpisodeConfig (steps -> max_steps, noise_seed -> seed, "
        "sounder and depth_max_m -> sensors); EpisodeSettings goes in a later release",
        DeprecationWarning,
        stacklevel=2,
    )
    return configured(**settings)


_DEFAULTS = EpisodeConfig()
_DEFAULT_RIG = SensorConfig()
# The settings sweep.json keeps under "episode" always (the frames apart), by its names.
_EPISODE_KEYS = ("steps", "stuck_after", "shield", "exr_compression", "noise_seed")
# The settings of the water and the battery, kept in sweep.json's "episode" when set.
_WATER = ("discharge_m3s", "gusts", "battery_wh")
# The guideline's settings, kept in sweep.json's "episode" when set.
_LINE = ("guideline", "guideline_colour")
# What sweep.json has no place for.
_UNKEPT = ("plots", "current", "rules", "body")
