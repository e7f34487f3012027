"""The command line's shared options, each declared once: its flag, type, help and default.

A command names the value it wants (``vlm: VLMOptions``, ``settings: EpisodeSettings``)
and `takes` puts the options of that group into its signature in that value's place, so
typer shows them, then builds the value from what was given. A group's defaults are its
value's defaults (`VLMOptions`, `EpisodeSettings`); a flag the value does not take is an
error when the command is declared, not an option silently dropped.
"""

from __future__ import annotations

import functools
import inspect
import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from enum import StrEnum
from pathlib import Path
from typing import Annotated, Any, Literal, TypeVar

import typer

from cavenav.episode.settings import EpisodeSettings
from cavenav.pilots.factory import VLMOptions
from cavenav.sensors.depth import EXR_COMPRESSIONS
from cavenav.sensors.optics import WATER_TYPES
from cavenav.world.current import MAX_DISCHARGE_M3S

__all__ = [
    "CAVE_SCENE",
    "LIVE_VIEW",
    "OWN_SENSORS",
    "SETTINGS",
    "VLM",
    "Backend",
    "ExrCompression",
    "Flag",
    "LiveView",
    "OptionGroup",
    "Sounder",
    "WaterType",
    "episode_settings",
    "finite",
    "takes",
]

Command = TypeVar("Command", bound=Callable[..., Any])


class Sounder(StrEnum):
    """Echo-sounder models (see `cavenav.sensors.rig.SensorConfig`)."""

    camera = "camera"
    beam = "beam"


# Depth EXR compressions, all lossless (measured in `cavenav.sensors.depth`).
ExrCompression = StrEnum("ExrCompression", {name: name for name in EXR_COMPRESSIONS})  # type: ignore[misc]


class Backend(StrEnum):
    """Where the VLM pilot's model runs (`cavenav.pilots.backends`)."""

    openai = "openai"
    transformers = "transformers"


# Water presets, named as `cavenav.sensors.optics.WATER_TYPES` names them.
WaterType = StrEnum("WaterType", {name: name for name in WATER_TYPES})  # type: ignore[misc]


def finite(value: float | None) -> float | None:
    """A range's bounds let infinity through: refuse it (and NaN) by name."""
    if value is not None and not math.isfinite(value):
        raise typer.BadParameter(f"{value} is not finite; give a number")
    return value


def _discharge(value: float | None) -> float | None:
    """A discharge within a scenario file's [water] bound (`MAX_DISCHARGE_M3S`): 1e300
    m³/s would carry the vehicle through rock without a collision."""
    if (value := finite(value)) is not None and abs(value) > MAX_DISCHARGE_M3S:
        raise typer.BadParameter(
            f"{value} m³/s: give a discharge within ±{MAX_DISCHARGE_M3S:g} m³/s"
        )
    return value


def _positive(value: float) -> float:
    if not (math.isfinite(value) and value > 0):
        raise typer.BadParameter(f"{value} m: give a finite distance above 0")
    return value


@dataclass(frozen=True)
class Flag:
    """One option: its parameter name (the flag, with dashes), type with help, default."""

    name: str
    kind: Any  # Annotated[type, typer.Option(...)]
    default: Any = None


@dataclass(frozen=True)
class OptionGroup:
    """Options that make one value: ``build`` is called with each flag by name, enums
    and paths given as plain strings (JSON-able for sweep.json and run folders).

    Raises:
        TypeError: a flag that ``build`` does not take (a renamed field, a typo).
    """

    flags: tuple[Flag, ...]
    build: Callable[..., Any]

    def __post_init__(self) -> None:
        takes_names = inspect.signature(self.build).parameters
        unknown = [flag.name for flag in self.flags if flag.name not in takes_names]
        if unknown:
            raise TypeError(f"{self.build.__name__} takes no option {', '.join(unknown)}")

    def only(self, *names: str) -> OptionGroup:
        """The group with just ``names``, in the group's order; the others keep the
        value's defaults (a command that shows fewer options)."""
        kept = self._known(names)
        return replace(self, flags=tuple(f for f in self.flags if f.name in kept))

    def without(self, *names: str) -> OptionGroup:
        """The group less ``names``: those keep the value's defaults."""
        gone = self._known(names)
        return replace(self, flags=tuple(f for f in self.flags if f.name not in gone))

    def _known(self, names: tuple[str, ...]) -> set[str]:
        unknown = set(names) - {flag.name for flag in self.flags}
        if unknown:
            raise TypeError(f"no option {', '.join(sorted(unknown))} for {self.build.__name__}")
        return set(names)

    def value(self, given: dict[str, Any]) -> Any:
        """Build the value from the command's arguments, taking this group's out of it."""
        return self.build(**{flag.name: _plain(given.pop(flag.name)) for flag in self.flags})


def _plain(value: Any) -> Any:
    """A flag's value as JSON keeps it: an enum by its value, a path as text."""
    if isinstance(value, StrEnum):
        return value.value
    return str(value) if isinstance(value, Path) else value


def takes(**groups: OptionGroup) -> Callable[[Command], Command]:
    """Put each group's options into the command's signature in place of the parameter
    of that name, and call the command with the group's value there.

    Example::

        @app.command()
        @takes(vlm=VLM)
        def ask(image: ..., vlm: VLMOptions = VLMOptions()) -> None: ...
    """

    def decorate(command: Command) -> Command:
        signature = inspect.signature(command, eval_str=True)
        missing = set(groups) - set(signature.parameters)
        if missing:
            raise TypeError(f"{command.__name__} has no parameter {', '.join(sorted(missing))}")
        names = [f.name for group in groups.values() for f in group.flags]
        twice = set(signature.parameters) & set(names) | {n for n in names if names.count(n) > 1}
        if twice:
            raise TypeError(f"{command.__name__} declares {', '.join(sorted(twice))} twice")
        parameters = []
        for parameter in signature.parameters.values():
            group = groups.get(parameter.name)
            if group is None:
                parameters.append(parameter)
                continue
            kind = inspect.Parameter.POSITIONAL_OR_KEYWORD
            parameters += [
                inspect.Parameter(f.name, kind, default=f.default, annotation=f.kind)
                for f in group.flags
            ]

        @functools.wraps(command)
        def run(**given: Any) -> Any:
            for name, group in groups.items():
                given[name] = group.value(given)
            return command(**given)

        run.__signature__ = signature.replace(parameters=parameters)  # type: ignore[attr-defined]
        run.__annotations__ = {p.name: p.annotation for p in parameters}
        return run  # type: ignore[return-value]

    return decorate


def _span(low: float | None, high: float | None) -> str:
    if low is not None and high is not None:
        return f"from {low:g} to {high:g}"
    return f"of {low:g} or more" if low is not None else f"of {high:g} or less"


def bounded(
    low: float | None, high: float | None, then: Callable[[Any], Any] | None = None
) -> Callable[[float | None], float | None]:
    """A callback that holds a float option within [low, high], naming NaN and infinity
    as what they are (typer's own range check calls NaN "not <= 1"); ``then`` runs after."""
    span = _span(low, high)

    def check(value: float | None) -> float | None:
        if value is not None:
            if not math.isfinite(value):
                raise typer.BadParameter(f"{value} is not a finite number; give one {span}")
            if (low is not None and value < low) or (high is not None and value > high):
                raise typer.BadParameter(f"{value}: give a number {span}")
        return then(value) if then else value

    return check


def _flag(name: str, kind: Any, default: Any, text: str, *decls: str, **limits: Any) -> Flag:
    """An option of type ``kind`` (None allowed when that is its default), helped by
    ``text``; ``decls`` and ``limits`` go to `typer.Option` (a float's min and max to
    `bounded`)."""
    if kind is float and ("min" in limits or "max" in limits):
        low, high = limits.pop("min", None), limits.pop("max", None)
        limits["callback"] = bounded(low, high, limits.get("callback"))
        text = f"{text}; a number {_span(low, high)}"
    if isinstance(kind, type) and issubclass(kind, StrEnum) and default is not None:
        default = kind(default)
    allowed = kind if default is not None else kind | None
    return Flag(name, Annotated[allowed, typer.Option(*decls, help=text, **limits)], default)


def _vlm(name: str, kind: Any, text: str, *decls: str, **limits: Any) -> Flag:
    """A VLM option, its default `VLMOptions`'s."""
    return _flag(name, kind, getattr(VLMOptions(), name), text, *decls, **limits)


# The VLM pilot's options: `run`, `eval`, `fly`, and `ask` less history, map, price, cache.
VLM = OptionGroup(
    (
        _vlm("backend", Backend, "where the model runs"),
        _vlm(
            "base_url",
            str,
            "OpenAI-compatible endpoint, e.g. http://localhost:8000/v1 (vLLM, SGLang, Ollama, "
            "llama.cpp); default: api.openai.com",
        ),
        _vlm("model", str, "model name, or a local folder for transformers"),
        _vlm("api_key_env", str, "environment variable that holds the API key"),
        _vlm("timeout", float, "seconds one attempt may take, whole", min=0.1, callback=finite),
        _vlm(
            "deadline",
            float,
            "seconds a request may take, retries and waits included "
            "(default: timeout x (retries + 1))",
            min=0.1,
            callback=finite,
        ),
        _vlm("retries", int, "transport retries per request", min=0),
        _vlm("temperature", float, "sampling temperature", min=0, callback=finite),
        _vlm("max_tokens", int, "maximum output tokens per reply", min=16),
        _vlm("detail", str, "image detail sent with images: low, high, auto"),
        _vlm("requeries", int, "re-queries after an unusable reply", min=0),
        _vlm("history", int, "earlier observations sent (K)", min=0),
        _vlm("prompt_file", Path, "your own system-prompt template"),
        _vlm("structured", bool, "ask for a JSON schema with fixed keys"),
        _vlm(
            "map_image",
            bool,
            "send a top-down picture of the pilot's own map (what it saw, where it flew) with "
            "every step: the memory ablation",
            "--map-image",
        ),
        _vlm(
            "energy_prompt",
            bool,
            "tell the model what its battery has left with every step, and what moves cost: "
            "energy-aware prompting (pair with --battery-wh)",
            "--energy-prompt",
        ),
        _vlm("image_format", str, "how the colour image is sent: png or jpeg (depth: png)"),
        _vlm("jpeg_quality", int, "quality of a jpeg colour image", min=1, max=100),
        _vlm("image_size", str, "WIDTHxHEIGHT the images are resized to before sending"),
        _vlm("price", str, "USD per million tokens, 'input,output'"),
        _vlm("cache", Path, "reply cache folder (keyed by request hash)"),
        _vlm("device", str, "transformers device: auto, cpu, cuda"),
    ),
    VLMOptions,
)

_SETTINGS = EpisodeSettings()


def _size(given: str | None, flag: str) -> tuple[int, int] | None:
    """The pixel count a flag gave, parsed (None when not given)."""
    from cavenav.sensors.camera import parse_resolution

    return None if given is None else parse_resolution(given, flag)


def episode_settings(
    *,
    steps: int | None = _SETTINGS.steps,
    stuck_after: int | None = _SETTINGS.stuck_after,
    sounder: Literal["camera", "beam"] = _SETTINGS.sounder,
    depth_max: float = _SETTINGS.depth_max_m,
    water: str | None = None,
    light_power: float | None = None,
    lamps: int | None = None,
    lamp_lumens: float | None = None,
    lamp_beam: float | None = None,
    lamp_kelvin: float | None = None,
    daylight: float | None = None,
    particles: float | None = None,
    silt_out: bool | None = None,
    noise: float | None = None,
    depth_dropout: float | None = None,
    depth_noise: float | None = None,
    resolution: str | None = None,
    sounder_resolution: str | None = None,
    difficulty: list[str] | None = None,
    discharge: float | None = _SETTINGS.discharge_m3s,
    gusts: float | None = _SETTINGS.gusts,
    battery_wh: float | None = _SETTINGS.battery_wh,
    noise_seed: int | None = _SETTINGS.noise_seed,
) -> EpisodeSettings:
    """`EpisodeSettings` from the episode, sensor and optics flags, one keyword each (so a flag
    renamed in `SETTINGS` alone fails when a command is declared); frames and shield stay.
    A bad pixel count or difficulty knob is a `ConfigError`, refused before any work."""
    from cavenav.world.scenarios import parse_difficulty

    optics = {  # the keys of `cavenav.sensors.optics.optics_from_table`
        "water": water,
        "light_power": light_power,
        "lamp_count": lamps,
        "lamp_lumens": lamp_lumens,
        "lamp_beam_deg": lamp_beam,
        "lamp_kelvin": lamp_kelvin,
        "daylight": daylight,
        "particles": particles,
        "silt_out": silt_out,
        "noise": noise,
        "depth_dropout": depth_dropout,
        "depth_noise_m": depth_noise,
    }
    return EpisodeSettings(
        steps=steps,
        stuck_after=stuck_after or None,  # the flag's 0 is "never"
        sounder=sounder,
        depth_max_m=depth_max,
        optics={key: value for key, value in optics.items() if value is not None},
        resolution=_size(resolution, "--resolution"),
        sounder_resolution=_size(sounder_resolution, "--sounder-resolution"),
        difficulty=parse_difficulty(difficulty or []).to_dict(),
        discharge_m3s=discharge,
        gusts=gusts,
        battery_wh=battery_wh,
        noise_seed=noise_seed,
    )


# The episode's options, its sensors' and their optics (None keeps the scenario's own).
SETTINGS = OptionGroup(
    (
        _flag(
            "steps",
            int,
            _SETTINGS.steps,
            "step budget (default: the scenario's; 150 for S1-S5)",
            min=1,
        ),
        _flag(
            "stuck_after",
            int,
            _SETTINGS.stuck_after,
            "end as 'stuck' after this many steps without headway (new progress toward the "
            "exit or new ground); 0: never",
            min=0,
        ),
        _flag("sounder", Sounder, _SETTINGS.sounder, "echo-sounder model"),
        _flag(
            "depth_max",
            float,
            _SETTINGS.depth_max_m,
            "D_max of the depth PNG, metres (above 0)",
            callback=_positive,
        ),
        _flag("water", WaterType, None, "water preset (default: clear)"),
        _flag(
            "light_power",
            float,
            None,
            "the lamps' total output as the radiance of a white wall 1 m ahead, overriding "
            "their lumens; 0 turns them off (default: from the lamps, about 32)",
            min=0,
            callback=finite,
        ),
        _flag("lamps", int, None, "lamps on the vehicle, 1-4 (default 2)", min=1, max=4),
        _flag(
            "lamp_lumens",
            float,
            None,
            "luminous flux of each lamp (default 1500, a Lumen light)",
            min=0,
            max=100_000,
            callback=finite,
        ),
        _flag(
            "lamp_beam",
            float,
            None,
            "full beam angle of each lamp in water, degrees at half intensity (default 90)",
            min=10,
            max=170,
            callback=finite,
        ),
        _flag(
            "lamp_kelvin",
            float,
            None,
            "colour temperature of the lamps (default 6200)",
            min=1500,
            max=20_000,
            callback=finite,
        ),
        _flag(
            "daylight",
            float,
            None,
            "open-water brightness at exits (default 1)",
            min=0,
            callback=finite,
        ),
        _flag(
            "particles",
            float,
            None,
            "marine snow, particles per m³ (default 4)",
            min=0,
            callback=finite,
        ),
        _flag(
            "silt_out",
            bool,
            None,
            "thrust near the floor raises silt that hangs and clouds the camera "
            "(default: on in the crawl family, off elsewhere)",
            "--silt-out/--no-silt-out",
        ),
        _flag("noise", float, None, "sensor noise, 0 = none (default 1)", min=0, callback=finite),
        _flag(
            "depth_dropout",
            float,
            None,
            "drop depth where returned lamp light is below this (default 0)",
            min=0,
            callback=finite,
        ),
        _flag(
            "depth_noise",
            float,
            None,
            "depth noise std at 10 m, metres (default 0)",
            min=0,
            callback=finite,
        ),
        _flag(
            "resolution",
            str,
            None,
            "forward camera pixels, e.g. 160x120 or 84x84 (default: the scenario file's "
            "\\[sensors] table, else 640x480); the horizontal field of view stays 53 degrees",
            metavar="WxH",
        ),
        _flag(
            "sounder_resolution",
            str,
            None,
            "pixels of each echo sounder's depth camera (default 32x24)",
            metavar="WxH",
        ),
        _flag(
            "difficulty",
            list[str],
            None,
            "a difficulty knob of the cave family, KEY=VALUE (repeat for more), "
            "e.g. constriction_m=2.5; see the README's cave families",
        ),
        _flag(
            "discharge",
            float,
            _SETTINGS.discharge_m3s,
            "water flowing through the cave, m³/s: positive from the exit toward the start "
            "(a spring's outflow, against the vehicle), negative toward the exit; it runs "
            "faster where the passage narrows and carries the vehicle; 0: still water; "
            "default: the cave's own (a scenario file's [water]; the families are still)",
            metavar="M3S",
            callback=_discharge,
        ),
        _flag(
            "gusts",
            float,
            _SETTINGS.gusts,
            "the current's slow turbulent gusts, as a fraction of its speed (default: the "
            "cave's own, else 0.2)",
            min=0,
            max=1,
            metavar="FRACTION",
        ),
        _flag(
            "battery_wh",
            float,
            _SETTINGS.battery_wh,
            "an energy budget in Wh: the episode ends as 'battery' once the moves have "
            "spent it (a BlueROV2's full pack holds 266 Wh); default: no budget",
            min=0.001,
            callback=finite,
        ),
        _flag(
            "noise_seed",
            int,
            _SETTINGS.noise_seed,
            "seed of the sensor noise, held apart from the cave's (default: the episode's "
            "own seed, so another --seed draws other noise too)",
            min=0,
        ),
    ),
    episode_settings,
)


@dataclass(frozen=True)
class LiveView:
    """Where an episode is shown as it flies, in Rerun (`cavenav.episode.rerun_log`).

    Attributes:
        rerun: spawn a live Rerun viewer.
        rerun_save: write the recording to this .rrd file.
    """

    rerun: bool = False
    rerun_save: str | None = None

    @property
    def wanted(self) -> bool:
        return self.rerun or self.rerun_save is not None


# `run` and `fly`: a live 3D view of the episode.
LIVE_VIEW = OptionGroup(
    (
        _flag(
            "rerun",
            bool,
            False,
            "show the episode live in a Rerun viewer: cave, path, camera, depth, sounders, "
            "map and each decision (pip install -e '.[rerun]')",
            "--rerun",
        ),
        _flag("rerun_save", Path, None, "write the Rerun recording to this .rrd file"),
    ),
    LiveView,
)


@dataclass(frozen=True)
class OwnSensors:
    """A vehicle's own sensors, for `cavenav fly` without --sim (`cavenav.episode.on_vehicle`).

    Attributes:
        camera: the video stream (`cavenav.vehicle.camera.CameraAddress`).
        camera_hfov: the camera's horizontal field of view in water, degrees.
        camera_latency: seconds from the camera's sensor to a decoded frame.
        ping_up, ping_down: the sounders' addresses (`cavenav.vehicle.ping.PingAddress`);
            None: not fitted.
        depth_model: the folder of a metric monocular depth model; None: no depth image.
    """

    camera: str = "udp:5600"
    camera_hfov: float = 53.13
    camera_latency: float = 0.2
    ping_up: str | None = None
    ping_down: str | None = None
    depth_model: str | None = None


OWN_SENSORS = OptionGroup(
    (
        _flag(
            "camera",
            str,
            "udp:5600",
            "without --sim: the video, udp:PORT (RTP H.264, as BlueOS sends it) or rtsp://...",
        ),
        _flag(
            "camera_hfov",
            float,
            53.13,
            "without --sim: the camera's horizontal field of view in water, degrees",
            min=10,
            max=170,
            callback=finite,
        ),
        _flag(
            "camera_latency",
            float,
            0.2,
            "without --sim: seconds from the camera's sensor to a decoded frame; each step "
            "waits for a frame decoded this long after the move ended",
            min=0,
            max=5,
            callback=finite,
        ),
        _flag(
            "ping_up",
            str,
            None,
            "without --sim: the upward sounder, udp:HOST:PORT or serial:DEVICE[:BAUD]",
        ),
        _flag("ping_down", str, None, "without --sim: the downward sounder (udp:HOST:9090)"),
        _flag(
            "depth_model",
            Path,
            None,
            "without --sim: a folder holding a metric monocular depth model (none: no depth image)",
        ),
    ),
    OwnSensors,
)


@dataclass(frozen=True)
class CaveScene:
    """Where `cavenav fake-sub --scene` puts the fake vehicle, and where its camera and
    sounders answer (`cavenav.cave_sensors`)."""

    scene: str | None = None
    cave_seed: int = 0
    camera_port: int = 5600
    ping_up_port: int = 9091
    ping_down_port: int = 9090


def _port(name: str, default: int, text: str) -> Flag:
    return _flag(name, int, default, f"--scene: {text}", min=1, max=65535)


CAVE_SCENE = OptionGroup(
    (
        _flag(
            "scene",
            str,
            None,
            "serve the vehicle's camera (RTP H.264) and sounders "
            "(Ping1D) rendered in this cave (a family or a .toml)",
        ),  # fmt: skip
        _flag("cave_seed", int, 0, "seed of the --scene cave", min=0),
        _port("camera_port", 5600, "the camera's UDP port on 127.0.0.1"),
        _port("ping_up_port", 9091, "the upward Ping1D's UDP port"),
        _port("ping_down_port", 9090, "the downward Ping1D's UDP port"),
    ),
    CaveScene,
)
