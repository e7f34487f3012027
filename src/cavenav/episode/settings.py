"""What a user sets for an episode, as one JSON-able value: `EpisodeSettings`.

`cavenav run`, `eval`, `fly` and `render` turn their flags into one `EpisodeSettings`, a
sweep keeps one in sweep.json, and each worker asks it for the `EpisodeConfig` of the
cave it flies: the layering of a scenario's own [optics] and [sensors] tables under the
flags is written here once, not once per command.

It imports the layers below it only when asked for a cave's configuration, so that the
command line can declare its options from these defaults without loading the kernels.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any, Literal

from cavenav.energy import checked_budget
from cavenav.errors import ConfigError
from cavenav.sensors.depth import DEPTH_RANGE_M, EXR_COMPRESSIONS
from cavenav.world.current import Current

if TYPE_CHECKING:
    from cavenav.episode.loop import EpisodeConfig
    from cavenav.sensors.rig import SensorConfig
    from cavenav.world.scenarios import Scenario

__all__ = ["FRAME_MODES", "SENSOR_FIELDS", "VIDEO_MODES", "EpisodeSettings"]

# What a sweep keeps of each step's images, as sweep.json names it: (frames, EXR).
FRAME_MODES = {"all": (True, True), "png": (True, False), "none": (False, False)}
# Which episodes of a sweep get an episode.mp4 (`cavenav eval --video`).
VIDEO_MODES = ("none", "failures", "all")
# The pixel counts, named as a scenario file's [sensors] table names them: the keys of
# `cavenav.sensors.rig.SENSOR_KEYS`, written again here because importing the rig loads
# its kernels (0.4 s at every command's start); tests/test_settings.py holds them equal.
_SIZES = ("resolution", "sounder_resolution")
# The settings sweep.json keeps under "sensors".
SENSOR_FIELDS = ("sounder", "depth_max_m", "optics", *_SIZES)


@dataclass(frozen=True)
class EpisodeSettings:
    """The settings of an episode that a user chooses, before a cave is known.

    Attributes:
        steps: step budget; None gives each scenario its own (`EpisodeConfig.max_steps`).
        stuck_after: steps without headway that end an episode as stuck; None never does.
        shield: put the safety shield between the pilot and the vehicle.
        save_frames, save_exr, exr_compression: what the run folder keeps of each step
            (`EpisodeConfig`).
        sounder: the echo-sounder model, "camera" or "beam" (`SensorConfig.sounder`).
        depth_max_m: D_max of the depth PNG, metres.
        optics: optics overrides over the scenario's [optics] table (water, light_power,
            ...; see `cavenav.sensors.optics.optics_from_table`); absent keys keep it.
        resolution, sounder_resolution: (width, height) pixels over the scenario's
            [sensors] table; None keeps it.
        difficulty: `Difficulty` knobs of the cave family, by name.
        discharge_m3s, gusts: the water's flow (`cavenav.world.current.Current`); None
            keeps the cave's own (`Scenario.water`: still, but where a scenario file's
            [water] table says otherwise).
        battery_wh: an energy budget that ends an episode as ``battery``; None: none.
        noise_seed: seeds the sensor noise of every episode (a sweep's further trials one
            more each); None draws it from the episode's own seed (`episode_config`), so
            that another seed flies other noise as well as another cave.
    """

    steps: int | None = None
    stuck_after: int | None = 50
    shield: bool = False
    save_frames: bool = True
    save_exr: bool = True
    exr_compression: str = "none"
    sounder: Literal["camera", "beam"] = "camera"
    depth_max_m: float = DEPTH_RANGE_M[1]
    optics: Mapping[str, Any] = field(default_factory=dict)
    resolution: tuple[int, int] | None = None
    sounder_resolution: tuple[int, int] | None = None
    difficulty: Mapping[str, float] = field(default_factory=dict)
    discharge_m3s: float | None = None
    gusts: float | None = None
    battery_wh: float | None = None
    noise_seed: int | None = None

    def __post_init__(self) -> None:
        if self.exr_compression not in EXR_COMPRESSIONS:
            raise ConfigError(
                f"EXR compression {self.exr_compression!r}: choose one of "
                f"{', '.join(EXR_COMPRESSIONS)}"
            )
        for name in _SIZES:  # JSON gives lists
            size = getattr(self, name)
            if size is not None:
                object.__setattr__(self, name, tuple(size))
        if self.difficulty:  # a bad knob fails here, not in a worker
            from cavenav.world.scenarios import Difficulty

            Difficulty.from_dict(self.difficulty)
        self.current_for({})  # a bad value fails here, not in a worker
        checked_budget(self.battery_wh)
        seed = self.noise_seed
        if seed is not None and (not isinstance(seed, int) or isinstance(seed, bool) or seed < 0):
            raise ConfigError(f"noise_seed must be a whole number of 0 or more, not {seed!r}")

    @property
    def flowing(self) -> bool:
        """Whether these settings make the water flow, whatever the cave's own."""
        return bool(self.discharge_m3s)

    def current_for(self, cave: Scenario | Mapping[str, Any]) -> Current:
        """The water's flow in ``cave`` (or a [water] table): these settings over its own."""
        water = cave if isinstance(cave, Mapping) else cave.water
        discharge, gusts = self.discharge_m3s, self.gusts
        return Current(
            water.get("discharge_m3s", Current.discharge_m3s) if discharge is None else discharge,
            water.get("gusts", Current.gusts) if gusts is None else gusts,
        )

    @property
    def frames(self) -> str:
        """The frames as a sweep names them: "all", "png" or "none" (`FRAME_MODES`)."""
        return "none" if not self.save_frames else "all" if self.save_exr else "png"

    def with_frames(self, mode: str) -> EpisodeSettings:
        """These settings keeping ``mode``'s images: "all", "png" or "none".

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
        from cavenav.world.scenarios import Difficulty, load_scenario

        return load_scenario(scenario, seed, difficulty=Difficulty.from_dict(self.difficulty))

    def sensors_for(self, cave: Scenario) -> SensorConfig:
        """The sensors in ``cave``: the defaults, the cave's [optics] and [sensors] tables,
        then these settings over them (`SensorConfig.for_scenario`)."""
        from cavenav.sensors.rig import SensorConfig

        sizes = {key: getattr(self, key) for key in _SIZES if getattr(self, key) is not None}
        base = replace(SensorConfig(), sounder=self.sounder, depth_max_m=self.depth_max_m)
        return base.for_scenario(cave.name, cave.optics, self.optics, cave.sensors, sizes)

    def episode_config(self, cave: Scenario, seed: int = 0) -> EpisodeConfig:
        """The `EpisodeConfig` of an episode in ``cave`` with these settings; ``seed``,
        the episode's own (its cave's, or its trial's in a sweep), seeds the sensor noise
        unless ``noise_seed`` holds it apart."""
        from cavenav.episode.loop import EpisodeConfig

        return EpisodeConfig(
            max_steps=self.steps,
            stuck_after=self.stuck_after,
            save_frames=self.save_frames,
            save_exr=self.save_exr,
            exr_compression=self.exr_compression,  # type: ignore[arg-type]
            shield=self.shield,
            sensors=self.sensors_for(cave),
            current=self.current_for(cave),
            battery_wh=self.battery_wh,
            seed=seed if self.noise_seed is None else self.noise_seed,
        )

    def to_dict(self) -> dict[str, Any]:
        """JSON-able, laid out as sweep.json's "episode", "difficulty" and "sensors"."""
        episode: dict[str, Any] = {
            "steps": self.steps,
            "stuck_after": self.stuck_after,
            "shield": self.shield,
            "frames": self.frames,
        }
        if self.noise_seed != 0:  # absent: seed 0, as every sweep's was before it was set
            episode["noise_seed"] = self.noise_seed
        if self.exr_compression != "none":  # no sweep flag sets it: absent, as before
            episode["exr_compression"] = self.exr_compression
        for key in _WATER:  # absent in still water with no budget, as before they existed
            if getattr(self, key) != getattr(_DEFAULTS, key):
                episode[key] = getattr(self, key)
        sensors: dict[str, Any] = {
            "sounder": self.sounder,
            "depth_max_m": self.depth_max_m,
            "optics": dict(self.optics),
        }
        for key in _SIZES:
            if getattr(self, key) is not None:
                sensors[key] = list(getattr(self, key))
        return {"episode": episode, "difficulty": dict(self.difficulty), "sensors": sensors}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> EpisodeSettings:
        """The settings `to_dict` wrote; absent keys keep their defaults (a sweep.json
        written before they existed).

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
        settings = cls(
            **{k: episode[k] for k in (*_EPISODE_KEYS, *_WATER) if k in episode},
            **sensors,
            difficulty=data.get("difficulty", {}),
        )  # fmt: skip
        return settings.with_frames(frames)


_DEFAULTS = EpisodeSettings()
# The settings sweep.json keeps under "episode" always (the frames apart).
_EPISODE_KEYS = ("steps", "stuck_after", "shield", "exr_compression", "noise_seed")
# The settings of the water and the battery, kept in sweep.json's "episode" when set.
_WATER = ("discharge_m3s", "gusts", "battery_wh")
