"""The options of the VLM pilot and of the episode, its sensors and optics, each declared
once as a typer ``Annotated`` type (``StepsOpt``, ``WaterOpt``, ``ModelOpt``, ...) that a
command names in its signature, with the default the value it builds holds (`EPISODE`,
`MODEL`); `SETTINGS` and `VLM` build the `EpisodeConfig` and the `VLMOptions` from a
command's arguments (`cavenav.cli.flags.Group`)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated, Literal

import typer

from cavenav.cli.flags import (
    Backend,
    DepthSource,
    Group,
    LineColour,
    SonarKind,
    Sounder,
    WaterType,
    bounded,
    finite,
    ranged,
)
from cavenav.episode.settings import EpisodeConfig, configured
from cavenav.pilots.factory import VLMOptions
from cavenav.world.current import MAX_DISCHARGE_M3S

__all__ = ["BACKEND", "EPISODE", "MODEL", "SETTINGS", "SOUNDER", "VLM", "episode_settings"]


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


# The defaults of the options, as the values they build hold them (and the enums' as enums).
MODEL = VLMOptions()
BACKEND = Backend(MODEL.backend)
# The VLM pilot's options: `run`, `eval`, `fly`, and `ask` less history, map, price, cache.
BackendOpt = Annotated[Backend, typer.Option(help="where the model runs")]
BaseUrlOpt = Annotated[
    str | None,
    typer.Option(
        help="OpenAI-compatible endpoint, e.g. http://localhost:8000/v1 (vLLM, SGLang, Ollama, "
        "llama.cpp); default: api.openai.com"
    ),
]
ModelOpt = Annotated[
    str | None, typer.Option(help="model name, or a local folder for transformers")
]
ApiKeyEnvOpt = Annotated[str, typer.Option(help="environment variable that holds the API key")]
TimeoutOpt = Annotated[
    float,
    typer.Option(
        help=ranged("seconds one attempt may take, whole", 0.1, None),
        callback=bounded(0.1, None, finite),
    ),
]
DeadlineOpt = Annotated[
    float | None,
    typer.Option(
        help=ranged(
            "seconds a request may take, retries and waits included "
            "(default: timeout x (retries + 1))",
            0.1,
            None,
        ),
        callback=bounded(0.1, None, finite),
    ),
]
RetriesOpt = Annotated[int, typer.Option(help="transport retries per request", min=0)]
TemperatureOpt = Annotated[
    float,
    typer.Option(help=ranged("sampling temperature", 0, None), callback=bounded(0, None, finite)),
]
MaxTokensOpt = Annotated[int, typer.Option(help="maximum output tokens per reply", min=16)]
DetailOpt = Annotated[
    str | None, typer.Option(help="image detail sent with images: low, high, auto")
]
RequeriesOpt = Annotated[int, typer.Option(help="re-queries after an unusable reply", min=0)]
HistoryOpt = Annotated[int, typer.Option(help="earlier observations sent (K)", min=0)]
PromptFileOpt = Annotated[Path | None, typer.Option(help="your own system-prompt template")]
StructuredOpt = Annotated[bool, typer.Option(help="ask for a JSON schema with fixed keys")]
MapImageOpt = Annotated[
    bool,
    typer.Option(
        "--map-image",
        help="send a top-down picture of the pilot's own map (what it saw, where it flew) with "
        "every step: the memory ablation",
    ),
]
EnergyPromptOpt = Annotated[
    bool,
    typer.Option(
        "--energy-prompt",
        help="tell the model what its battery has left with every step, and what moves cost: "
        "energy-aware prompting (pair with --battery-wh)",
    ),
]
DesignOpt = Annotated[
    str,
    typer.Option(
        help="how the model answers: direct (the action string, the paper's), arrows (the "
        "number of a direction drawn on the image) or waypoint (a point on the image a "
        "local planner flies to)"
    ),
]
ReplanEveryOpt = Annotated[
    int,
    typer.Option(help="--design waypoint: the most steps the planner flies before asking again"),
]
ImageFormatOpt = Annotated[
    str, typer.Option(help="how the colour image is sent: png or jpeg (depth: png)")
]
JpegQualityOpt = Annotated[int, typer.Option(help="quality of a jpeg colour image", min=1, max=100)]
ImageSizeOpt = Annotated[
    str | None, typer.Option(help="WIDTHxHEIGHT the images are resized to before sending")
]
PriceOpt = Annotated[str | None, typer.Option(help="USD per million tokens, 'input,output'")]
CacheOpt = Annotated[Path | None, typer.Option(help="reply cache folder (keyed by request hash)")]
DeviceOpt = Annotated[str, typer.Option(help="transformers device: auto, cpu, cuda")]
VLM = Group(
    (
        "backend",
        "base_url",
        "model",
        "api_key_env",
        "timeout",
        "deadline",
        "retries",
        "temperature",
        "max_tokens",
        "detail",
        "requeries",
        "history",
        "prompt_file",
        "structured",
        "map_image",
        "energy_prompt",
        "design",
        "replan_every",
        "image_format",
        "jpeg_quality",
        "image_size",
        "price",
        "cache",
        "device",
    ),
    VLMOptions,
)

EPISODE = EpisodeConfig()
SOUNDER = Sounder(EPISODE.sensors.sounder)


def _size(given: str | None, flag: str) -> tuple[int, int] | None:
    """The pixel count a flag gave, parsed (None when not given)."""
    from cavenav.sensors.camera import parse_resolution

    return None if given is None else parse_resolution(given, flag)


def episode_settings(
    *,
    steps: int | None = EPISODE.max_steps,
    stuck_after: int | None = EPISODE.stuck_after,
    sounder: Literal["camera", "beam"] = EPISODE.sensors.sounder,
    depth_max: float = EPISODE.sensors.depth_max_m,
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
    depth_source: str | None = None,
    sonar: str | None = None,
    dvl: bool | None = None,
    difficulty: list[str] | None = None,
    discharge: float | None = EPISODE.discharge_m3s,
    gusts: float | None = EPISODE.gusts,
    battery_wh: float | None = EPISODE.battery_wh,
    noise_seed: int | None = EPISODE.seed,
    guideline: bool | None = EPISODE.guideline,
    guideline_colour: str | None = EPISODE.guideline_colour,
) -> EpisodeConfig:
    """`EpisodeConfig` from the episode, sensor and optics flags, one keyword each (so a flag
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
    return configured(
        steps=steps,
        stuck_after=stuck_after or None,  # the flag's 0 is "never"
        sounder=sounder,
        depth_max_m=depth_max,
        optics={key: value for key, value in optics.items() if value is not None},
        resolution=_size(resolution, "--resolution"),
        sounder_resolution=_size(sounder_resolution, "--sounder-resolution"),
        depth_source=depth_source,
        sonar=sonar,
        dvl=dvl,
        difficulty=parse_difficulty(difficulty or []).to_dict(),
        discharge_m3s=discharge,
        gusts=gusts,
        battery_wh=battery_wh,
        noise_seed=noise_seed,
        guideline=guideline,
        guideline_colour=guideline_colour,
    )


# The episode's options, its sensors' and their optics (None keeps the scenario's own).
StepsOpt = Annotated[
    int | None, typer.Option(help="step budget (default: the scenario's; 150 for S1-S5)", min=1)
]
StuckAfterOpt = Annotated[
    int | None,
    typer.Option(
        help="end as 'stuck' after this many steps without headway (new progress toward the "
        "exit or new ground); 0: never",
        min=0,
    ),
]
SounderOpt = Annotated[Sounder, typer.Option(help="echo-sounder model")]
DepthMaxOpt = Annotated[
    float, typer.Option(help="D_max of the depth PNG, metres (above 0)", callback=_positive)
]
WaterOpt = Annotated[WaterType | None, typer.Option(help="water preset (default: clear)")]
LightPowerOpt = Annotated[
    float | None,
    typer.Option(
        help=ranged(
            "the lamps' total output as the radiance of a white wall 1 m ahead, overriding "
            "their lumens; 0 turns them off (default: from the lamps, about 32)",
            0,
            None,
        ),
        callback=bounded(0, None, finite),
    ),
]
LampsOpt = Annotated[
    int | None, typer.Option(help="lamps on the vehicle, 1-4 (default 2)", min=1, max=4)
]
LampLumensOpt = Annotated[
    float | None,
    typer.Option(
        help=ranged("luminous flux of each lamp (default 1500, a Lumen light)", 0, 100_000),
        callback=bounded(0, 100_000, finite),
    ),
]
LampBeamOpt = Annotated[
    float | None,
    typer.Option(
        help=ranged(
            "full beam angle of each lamp in water, degrees at half intensity (default 90)", 10, 170
        ),
        callback=bounded(10, 170, finite),
    ),
]
LampKelvinOpt = Annotated[
    float | None,
    typer.Option(
        help=ranged("colour temperature of the lamps (default 6200)", 1500, 20_000),
        callback=bounded(1500, 20_000, finite),
    ),
]
DaylightOpt = Annotated[
    float | None,
    typer.Option(
        help=ranged("open-water brightness at exits (default 1)", 0, None),
        callback=bounded(0, None, finite),
    ),
]
ParticlesOpt = Annotated[
    float | None,
    typer.Option(
        help=ranged("marine snow, particles per m³ (default 4)", 0, None),
        callback=bounded(0, None, finite),
    ),
]
SiltOutOpt = Annotated[
    bool | None,
    typer.Option(
        "--silt-out/--no-silt-out",
        help="thrust near the floor raises silt that hangs and clouds the camera "
        "(default: on in the crawl family, off elsewhere)",
    ),
]
NoiseOpt = Annotated[
    float | None,
    typer.Option(
        help=ranged("sensor noise, 0 = none (default 1)", 0, None),
        callback=bounded(0, None, finite),
    ),
]
DepthDropoutOpt = Annotated[
    float | None,
    typer.Option(
        help=ranged("drop depth where returned lamp light is below this (default 0)", 0, None),
        callback=bounded(0, None, finite),
    ),
]
DepthNoiseOpt = Annotated[
    float | None,
    typer.Option(
        help=ranged("depth noise std at 10 m, metres (default 0)", 0, None),
        callback=bounded(0, None, finite),
    ),
]
ResolutionOpt = Annotated[
    str | None,
    typer.Option(
        help="forward camera pixels, e.g. 160x120 or 84x84 (default: the scenario file's "
        "\\[sensors] table, else 640x480); the horizontal field of view stays 53 degrees",
        metavar="WxH",
    ),
]
SounderResolutionOpt = Annotated[
    str | None,
    typer.Option(help="pixels of each echo sounder's depth camera (default 32x24)", metavar="WxH"),
]
DepthSourceOpt = Annotated[
    DepthSource | None,
    typer.Option(
        help="what makes the depth image: exact (the simulator's, as the paper's), stereo (a "
        "stereo camera's: none where the water, silt or bare rock leave no texture) or none; "
        "default: the scenario's, else exact"
    ),
]
SonarOpt = Annotated[
    SonarKind | None,
    typer.Option(
        help="an imaging sonar on the vehicle: ping360 (a scanning sonar's disc) or "
        "multibeam (a 130-degree forward fan); default: the scenario's, else none"
    ),
]
DvlOpt = Annotated[
    bool | None,
    typer.Option(
        "--dvl/--no-dvl",
        help="a Doppler velocity log (DVL A50-like): dead reckoning uses its velocity while "
        "it has bottom lock; default: the scenario's, else none",
    ),
]
DifficultyOpt = Annotated[
    list[str] | None,
    typer.Option(
        help="a difficulty knob of the cave family, KEY=VALUE (repeat for more), "
        "e.g. constriction_m=2.5; see docs/guides/scenarios.md"
    ),
]
DischargeOpt = Annotated[
    float | None,
    typer.Option(
        help="water flowing through the cave, m³/s: positive from the exit toward the start "
        "(a spring's outflow, against the vehicle), negative toward the exit; it runs "
        "faster where the passage narrows and carries the vehicle; 0: still water; "
        "default: the cave's own (a scenario file's [water]; the families are still)",
        metavar="M3S",
        callback=_discharge,
    ),
]
GustsOpt = Annotated[
    float | None,
    typer.Option(
        help=ranged(
            "the current's slow turbulent gusts, as a fraction of its speed (default: the "
            "cave's own, else 0.2)",
            0,
            1,
        ),
        metavar="FRACTION",
        callback=bounded(0, 1),
    ),
]
BatteryWhOpt = Annotated[
    float | None,
    typer.Option(
        help=ranged(
            "an energy budget in Wh: the episode ends as 'battery' once the moves have "
            "spent it (a BlueROV2's full pack holds 266 Wh); default: no budget",
            0.001,
            None,
        ),
        callback=bounded(0.001, None, finite),
    ),
]
NoiseSeedOpt = Annotated[
    int | None,
    typer.Option(
        help="seed of the sensor noise, held apart from the cave's (default: the episode's "
        "own seed, so another --seed draws other noise too)",
        min=0,
    ),
]
GuidelineOpt = Annotated[
    bool | None,
    typer.Option(
        "--guideline/--no-guideline",
        help="a diver's guideline tied along the passage to the exit, 3 mm thick, with line "
        "arrows pointing out; the camera sees it and the VLM's prompt says so (default: "
        "the scenario file's 'guideline', else none, as in the paper)",
    ),
]
GuidelineColourOpt = Annotated[
    LineColour | None,
    typer.Option(help="the guideline's colour (default: the scenario file's, else white)"),
]
SETTINGS = Group(
    (
        "steps",
        "stuck_after",
        "sounder",
        "depth_max",
        "water",
        "light_power",
        "lamps",
        "lamp_lumens",
        "lamp_beam",
        "lamp_kelvin",
        "daylight",
        "particles",
        "silt_out",
        "noise",
        "depth_dropout",
        "depth_noise",
        "resolution",
        "sounder_resolution",
        "depth_source",
        "sonar",
        "dvl",
        "difficulty",
        "discharge",
        "gusts",
        "battery_wh",
        "noise_seed",
        "guideline",
        "guideline_colour",
    ),
    episode_settings,
)
