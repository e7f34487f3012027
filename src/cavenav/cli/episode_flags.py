"""The flags of the VLM pilot (`VLM`) and of the episode, its sensors and optics
(`SETTINGS`), each declared once (`cavenav.cli.flags`)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Literal

import typer

from cavenav.cli.flags import Backend, Flag, OptionGroup, Sounder, WaterType, finite, flag
from cavenav.episode.settings import EpisodeConfig, configured
from cavenav.pilots.factory import VLMOptions
from cavenav.world.current import MAX_DISCHARGE_M3S

__all__ = ["SETTINGS", "VLM", "episode_settings"]


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


def _vlm(name: str, kind: Any, text: str, *decls: str, **limits: Any) -> Flag:
    """A VLM option, its default `VLMOptions`'s."""
    return flag(name, kind, getattr(VLMOptions(), name), text, *decls, **limits)


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

_SETTINGS = EpisodeConfig()


def _size(given: str | None, flag: str) -> tuple[int, int] | None:
    """The pixel count a flag gave, parsed (None when not given)."""
    from cavenav.sensors.camera import parse_resolution

    return None if given is None else parse_resolution(given, flag)


def episode_settings(
    *,
    steps: int | None = _SETTINGS.max_steps,
    stuck_after: int | None = _SETTINGS.stuck_after,
    sounder: Literal["camera", "beam"] = _SETTINGS.sensors.sounder,
    depth_max: float = _SETTINGS.sensors.depth_max_m,
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
    noise_seed: int | None = _SETTINGS.seed,
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
        difficulty=parse_difficulty(difficulty or []).to_dict(),
        discharge_m3s=discharge,
        gusts=gusts,
        battery_wh=battery_wh,
        noise_seed=noise_seed,
    )


# The episode's options, its sensors' and their optics (None keeps the scenario's own).
SETTINGS = OptionGroup(
    (
        flag(
            "steps",
            int,
            _SETTINGS.max_steps,
            "step budget (default: the scenario's; 150 for S1-S5)",
            min=1,
        ),
        flag(
            "stuck_after",
            int,
            _SETTINGS.stuck_after,
            "end as 'stuck' after this many steps without headway (new progress toward the "
            "exit or new ground); 0: never",
            min=0,
        ),
        flag("sounder", Sounder, _SETTINGS.sensors.sounder, "echo-sounder model"),
        flag(
            "depth_max",
            float,
            _SETTINGS.sensors.depth_max_m,
            "D_max of the depth PNG, metres (above 0)",
            callback=_positive,
        ),
        flag("water", WaterType, None, "water preset (default: clear)"),
        flag(
            "light_power",
            float,
            None,
            "the lamps' total output as the radiance of a white wall 1 m ahead, overriding "
            "their lumens; 0 turns them off (default: from the lamps, about 32)",
            min=0,
            callback=finite,
        ),
        flag("lamps", int, None, "lamps on the vehicle, 1-4 (default 2)", min=1, max=4),
        flag(
            "lamp_lumens",
            float,
            None,
            "luminous flux of each lamp (default 1500, a Lumen light)",
            min=0,
            max=100_000,
            callback=finite,
        ),
        flag(
            "lamp_beam",
            float,
            None,
            "full beam angle of each lamp in water, degrees at half intensity (default 90)",
            min=10,
            max=170,
            callback=finite,
        ),
        flag(
            "lamp_kelvin",
            float,
            None,
            "colour temperature of the lamps (default 6200)",
            min=1500,
            max=20_000,
            callback=finite,
        ),
        flag(
            "daylight",
            float,
            None,
            "open-water brightness at exits (default 1)",
            min=0,
            callback=finite,
        ),
        flag(
            "particles",
            float,
            None,
            "marine snow, particles per m³ (default 4)",
            min=0,
            callback=finite,
        ),
        flag(
            "silt_out",
            bool,
            None,
            "thrust near the floor raises silt that hangs and clouds the camera "
            "(default: on in the crawl family, off elsewhere)",
            "--silt-out/--no-silt-out",
        ),
        flag("noise", float, None, "sensor noise, 0 = none (default 1)", min=0, callback=finite),
        flag(
            "depth_dropout",
            float,
            None,
            "drop depth where returned lamp light is below this (default 0)",
            min=0,
            callback=finite,
        ),
        flag(
            "depth_noise",
            float,
            None,
            "depth noise std at 10 m, metres (default 0)",
            min=0,
            callback=finite,
        ),
        flag(
            "resolution",
            str,
            None,
            "forward camera pixels, e.g. 160x120 or 84x84 (default: the scenario file's "
            "\\[sensors] table, else 640x480); the horizontal field of view stays 53 degrees",
            metavar="WxH",
        ),
        flag(
            "sounder_resolution",
            str,
            None,
            "pixels of each echo sounder's depth camera (default 32x24)",
            metavar="WxH",
        ),
        flag(
            "difficulty",
            list[str],
            None,
            "a difficulty knob of the cave family, KEY=VALUE (repeat for more), "
            "e.g. constriction_m=2.5; see docs/guides/scenarios.md",
        ),
        flag(
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
        flag(
            "gusts",
            float,
            _SETTINGS.gusts,
            "the current's slow turbulent gusts, as a fraction of its speed (default: the "
            "cave's own, else 0.2)",
            min=0,
            max=1,
            metavar="FRACTION",
        ),
        flag(
            "battery_wh",
            float,
            _SETTINGS.battery_wh,
            "an energy budget in Wh: the episode ends as 'battery' once the moves have "
            "spent it (a BlueROV2's full pack holds 266 Wh); default: no budget",
            min=0.001,
            callback=finite,
        ),
        flag(
            "noise_seed",
            int,
            _SETTINGS.seed,
            "seed of the sensor noise, held apart from the cave's (default: the episode's "
            "own seed, so another --seed draws other noise too)",
            min=0,
        ),
    ),
    episode_settings,
)
