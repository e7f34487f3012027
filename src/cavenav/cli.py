"""The command line: flags -> configuration -> library calls, nothing else.

cavenav run S4                         fly S4 with the geometric pilot
cavenav run examples/osrf_cave_L.toml  fly a user mesh described by a scenario file
cavenav render S4 --water turbid       contact sheet of the views along the passage
cavenav scenarios                      list what can be flown
cavenav eval --seeds 0-19 --out DIR    families x 20 caves each, resumable, with a report
cavenav compare DIR_A DIR_B            two sweeps paired by cave (McNemar)
cavenav report DIR                     the HTML report of a sweep or a run folder
cavenav video RUN                      an MP4 of one episode
cavenav fly --sim S4 --yes             the same pilots on an ArduSub vehicle over MAVLink
cavenav fake-sub                       a simulated ArduSub autopilot to fly against
"""

from __future__ import annotations

import contextlib
import math
import os
import signal
import sys
import warnings
from collections.abc import Iterator
from dataclasses import replace
from enum import StrEnum
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.console import Console
from rich.markup import escape
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)
from rich.table import Table

from cavenav.errors import CavenavError
from cavenav.redaction import redact
from cavenav.sensors.depth import DEPTH_RANGE_M, EXR_COMPRESSIONS

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    help="cavenav: VLM-steered navigation of an underwater vehicle through unseen caves.",
)
console = Console()
errors = Console(stderr=True, soft_wrap=True)


class Sounder(StrEnum):
    """Echo-sounder models (see `cavenav.sensors.rig.SensorConfig`)."""

    camera = "camera"
    beam = "beam"


# Depth EXR compressions, all lossless (measured in `cavenav.sensors.depth`).
ExrCompression = StrEnum("ExrCompression", {name: name for name in EXR_COMPRESSIONS})


class Backend(StrEnum):
    openai = "openai"
    transformers = "transformers"


class WaterType(StrEnum):
    """Water presets (see `cavenav.sensors.optics.WATER_TYPES`)."""

    clear = "clear"
    ocean = "ocean"
    coastal = "coastal"
    turbid = "turbid"


def _finite(value: float | None) -> float | None:
    """A range's bounds let infinity through: refuse it (and NaN) by name."""
    if value is not None and not math.isfinite(value):
        raise typer.BadParameter(f"{value} is not finite; give a number")
    return value


def _positive(value: float) -> float:
    if not (math.isfinite(value) and value > 0):
        raise typer.BadParameter(f"{value} m: give a finite distance above 0")
    return value


# Options shared by `run` and `render`: how the cave looks. None keeps the scenario's own.
WaterOpt = Annotated[WaterType | None, typer.Option(help="water preset (default: clear)")]
LightPower = Annotated[
    float | None,
    typer.Option(min=0, callback=_finite, help="lamp power; 0 turns the lamps off (default 20)"),
]
Daylight = Annotated[
    float | None,
    typer.Option(min=0, callback=_finite, help="open-water brightness at exits (default 1)"),
]
Particles = Annotated[
    float | None,
    typer.Option(min=0, callback=_finite, help="marine snow, particles per m³ (default 2)"),
]
Noise = Annotated[
    float | None, typer.Option(min=0, callback=_finite, help="sensor noise, 0 = none (default 1)")
]
DepthDropout = Annotated[
    float | None,
    typer.Option(
        min=0,
        callback=_finite,
        help="drop depth where returned lamp light is below this (default 0)",
    ),
]
DepthNoise = Annotated[
    float | None,
    typer.Option(min=0, callback=_finite, help="depth noise std at 10 m, metres (default 0)"),
]


def _optics_flags(**options: Any) -> dict[str, Any]:
    """The optics flags that were given (None keeps the scenario's or the default)."""
    return {
        k: (v.value if isinstance(v, StrEnum) else v) for k, v in options.items() if v is not None
    }


# Options shared by `run`, `render` and `eval`: pixel counts. None keeps the scenario's.
Resolution = Annotated[
    str | None,
    typer.Option(
        metavar="WxH",
        help="forward camera pixels, e.g. 160x120 or 84x84 (default: the scenario file's "
        "\\[sensors] table, else 640x480); the horizontal field of view stays 53 degrees",
    ),
]
SounderResolution = Annotated[
    str | None,
    typer.Option(metavar="WxH", help="pixels of each echo sounder's depth camera (default 32x24)"),
]


def _sizes(resolution: str | None, sounder_resolution: str | None) -> dict[str, Any]:
    """The pixel counts that were given, parsed (a bad one is refused before any work)."""
    from cavenav.sensors.camera import parse_resolution

    given = {"resolution": resolution, "sounder_resolution": sounder_resolution}
    return {
        key: parse_resolution(text, f"--{key.replace('_', '-')}")
        for key, text in given.items()
        if text is not None
    }


def _sensors(  # noqa: ANN401 - lazy imports
    cave: Any, base: Any, sizes: dict[str, Any] | None = None, **options: Any
) -> Any:
    """``base`` SensorConfig with the scenario's [optics] and [sensors] tables, then the
    CLI options (optics flags, then the pixel counts ``sizes``)."""
    return base.for_scenario(
        cave.name, cave.optics, _optics_flags(**options), cave.sensors, sizes or {}
    )


DepthMax = Annotated[
    float, typer.Option(callback=_positive, help="D_max of the depth PNG, metres (above 0)")
]
DifficultyOpt = Annotated[
    list[str] | None,
    typer.Option(
        help="a difficulty knob of the cave family, KEY=VALUE (repeat for more), "
        "e.g. constriction_m=2.5; see the README's cave families"
    ),
]

# Options shared by `run --pilot vlm` and `ask`.
BaseUrl = Annotated[
    str | None,
    typer.Option(
        help="OpenAI-compatible endpoint, e.g. http://localhost:8000/v1 (vLLM, "
        "SGLang, Ollama, llama.cpp); default: api.openai.com"
    ),
]
Model = Annotated[str | None, typer.Option(help="model name, or a local folder for transformers")]
BackendOpt = Annotated[Backend, typer.Option(help="where the model runs")]
ApiKeyEnv = Annotated[str, typer.Option(help="environment variable that holds the API key")]
Timeout = Annotated[
    float, typer.Option(min=0.1, callback=_finite, help="seconds one attempt may take, whole")
]
Deadline = Annotated[
    float | None,
    typer.Option(
        min=0.1,
        callback=_finite,
        help="seconds a request may take, retries and waits included "
        "(default: timeout x (retries + 1))",
    ),
]
Retries = Annotated[int, typer.Option(min=0, help="transport retries per request")]
Temperature = Annotated[float, typer.Option(min=0, callback=_finite, help="sampling temperature")]
MaxTokens = Annotated[int, typer.Option(min=16, help="maximum output tokens per reply")]
Detail = Annotated[str | None, typer.Option(help="image detail sent with images: low, high, auto")]
Requeries = Annotated[int, typer.Option(min=0, help="re-queries after an unusable reply")]
History = Annotated[int, typer.Option(min=0, help="earlier observations sent (K)")]
PromptFile = Annotated[Path | None, typer.Option(help="your own system-prompt template")]
Structured = Annotated[bool, typer.Option(help="ask for a JSON schema with fixed keys")]
MapImage = Annotated[
    bool,
    typer.Option(
        "--map-image",
        help="send a top-down picture of the pilot's own map (what it saw, where it flew) "
        "with every step: the memory ablation",
    ),
]
Price = Annotated[str | None, typer.Option(help="USD per million tokens, 'input,output'")]
Cache = Annotated[Path | None, typer.Option(help="reply cache folder (keyed by request hash)")]
Device = Annotated[str, typer.Option(help="transformers device: auto, cpu, cuda")]
Steps = Annotated[
    int | None,
    typer.Option(min=1, help="step budget (default: the scenario's; 150 for S1-S5)"),
]
StuckAfter = Annotated[
    int,
    typer.Option(
        min=0,
        help="end as 'stuck' after this many steps without headway (new progress toward "
        "the exit or new ground); 0: never",
    ),
]


def _vlm_options(flags: dict[str, Any], **overrides: Any) -> Any:  # noqa: ANN401
    """`VLMOptions` from a command's flags (its ``locals()``): the flags share its names."""
    from dataclasses import fields

    from cavenav.pilots.factory import VLMOptions

    values = {f.name: flags[f.name] for f in fields(VLMOptions) if f.name in flags}
    values.update(overrides)
    plain = {
        k: v.value if isinstance(v, StrEnum) else str(v) if isinstance(v, Path) else v
        for k, v in values.items()
    }
    return VLMOptions(**plain)


@app.command()
def run(
    scenario: Annotated[
        str, typer.Argument(help="a family (S1..S5, crawl, maze, long) or a scenario .toml file")
    ],
    pilot: Annotated[
        str, typer.Option(help="pilot to fly: geometric, vlm, replay, random")
    ] = "geometric",
    seed: Annotated[
        int,
        typer.Option(min=0, help="seed of the procedural cave and of the random pilot"),
    ] = 0,
    out: Annotated[Path, typer.Option(help="folder that receives the run folder")] = Path("runs"),
    steps: Steps = None,
    stuck_after: StuckAfter = 50,
    frames: Annotated[bool, typer.Option(help="save RGB, depth PNG and EXR of every step")] = True,
    exr_compression: Annotated[
        ExrCompression,
        typer.Option(
            help="depth EXR compression, all lossless: none (fastest; any reader), zip (a "
            "fifth smaller), or htj2k (two thirds smaller; readers need OpenEXR 3.4 or later)"
        ),
    ] = ExrCompression["none"],
    shield: Annotated[
        bool, typer.Option(help="safety shield between pilot and vehicle (cavenav.shield)")
    ] = False,
    sounder: Annotated[Sounder, typer.Option(help="echo-sounder model")] = Sounder.camera,
    depth_max: DepthMax = DEPTH_RANGE_M[1],
    water: WaterOpt = None,
    light_power: LightPower = None,
    daylight: Daylight = None,
    particles: Particles = None,
    noise: Noise = None,
    depth_dropout: DepthDropout = None,
    depth_noise: DepthNoise = None,
    resolution: Resolution = None,
    sounder_resolution: SounderResolution = None,
    from_: Annotated[Path | None, typer.Option("--from", help="run folder to replay")] = None,
    difficulty: DifficultyOpt = None,
    backend: BackendOpt = Backend.openai,
    base_url: BaseUrl = None,
    model: Model = None,
    api_key_env: ApiKeyEnv = "OPENAI_API_KEY",
    timeout: Timeout = 60.0,
    deadline: Deadline = None,
    retries: Retries = 4,
    temperature: Temperature = 0.2,
    max_tokens: MaxTokens = 1024,
    detail: Detail = None,
    requeries: Requeries = 3,
    history: History = 2,
    prompt_file: PromptFile = None,
    structured: Structured = False,
    map_image: MapImage = False,
    price: Price = None,
    cache: Cache = None,
    device: Device = "auto",
) -> None:
    """Fly one episode and write its run folder (summary, steps, frames, plots)."""
    sizes = _sizes(resolution, sounder_resolution)
    from cavenav.episode.loop import EpisodeConfig
    from cavenav.episode.run_folder import new_run_dir, prepare_root
    from cavenav.pilots.factory import PilotSpec
    from cavenav.sensors.rig import SensorConfig
    from cavenav.world.scenarios import load_scenario, parse_difficulty

    spec = PilotSpec(
        pilot,
        _vlm_options(locals()),
        recording=str(from_) if from_ else None,
    )
    if pilot == "replay":
        from cavenav.pilots.replay import recorded_scenario

        recorded, recorded_seed = recorded_scenario(str(from_))
        if recorded.casefold() != scenario.casefold() and Path(scenario).stem not in recorded:
            console.print(
                f"[yellow]note:[/] the recording flew {recorded}, replaying in {scenario}"
            )
        seed = recorded_seed if recorded_seed is not None else seed
    flyer = spec.build(seed=seed)  # a refused pilot or recording leaves no folder behind
    prepare_root(out)  # a folder that cannot be written is refused before the cave is built
    with console.status(f"building {scenario} (seed {seed})"):
        cave = load_scenario(scenario, seed, difficulty=parse_difficulty(difficulty or []))
    sensors = _sensors(
        cave,
        replace(SensorConfig(), sounder=sounder.value, depth_max_m=depth_max),
        sizes,
        water=water,
        light_power=light_power,
        daylight=daylight,
        particles=particles,
        noise=noise,
        depth_dropout=depth_dropout,
        depth_noise_m=depth_noise,
    )
    config = EpisodeConfig(
        max_steps=steps,
        stuck_after=stuck_after or None,
        save_frames=frames,
        exr_compression=exr_compression.value,
        shield=shield,
        sensors=sensors,
    )
    console.print(
        f"[bold]{cave.name}[/]: {cave.description or cave.mesh.name} "
        f"({cave.mesh.triangle_count:,} triangles)"
    )
    run_dir = new_run_dir(out, cave.name, pilot, cave.seed)
    _fly_episode(cave, flyer, config, run_dir)


def _fly_episode(
    cave: Any,  # noqa: ANN401 - lazy imports
    flyer: Any,  # noqa: ANN401
    config: Any,  # noqa: ANN401
    run_dir: Path,
    motion: Any = None,  # noqa: ANN401
) -> None:
    """Fly the episode with a progress bar, print its summary, and exit as the README says."""
    from cavenav.episode.loop import run_episode, step_budget

    with Progress(
        TextColumn("[progress.description]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("{task.fields[status]}"),
        TimeElapsedColumn(),
        console=console,
    ) as progress:
        # Before the first step: the kernels load (the first run on a machine compiles
        # them, about a minute), the lighting tables are built and the start is checked.
        task = progress.add_task(
            f"preparing {cave.name}",
            total=step_budget(cave, config),
            status="sensors, lighting, start check",
        )

        def on_step(record: dict) -> None:
            status = f"clearance {record['clearance_m']:.2f} m  {record.get('action') or ''}"
            progress.update(task, advance=1, description=f"flying {cave.name}", status=status[:60])

        try:
            result = run_episode(cave, flyer, config, run_dir, on_step, motion)
        except KeyboardInterrupt:
            progress.stop()
            errors.print(_interrupted(run_dir), soft_wrap=True)
            raise typer.Exit(130) from None
        except CavenavError as exc:
            progress.stop()
            _remove_if_empty(run_dir)  # refused before anything was written (the start)
            if (run_dir / "summary.json").is_file():
                exc.args = (f"{exc} (the record so far is in {run_dir})",)
            raise
    _print_summary(result.summary)
    # soft_wrap: paths stay on one line, whatever the terminal width, for copy and paste.
    console.print(f"run folder: [bold]{run_dir}[/]", soft_wrap=True)
    for name in result.summary.get("plots", {}).values():
        console.print(f"plot:       {run_dir / name}", soft_wrap=True)
    if result.termination == "pilot_failure":
        raise typer.Exit(1)


def _interrupted(run_dir: Path) -> str:
    """What Ctrl-C left: a partial record, or a whole episode without its plots."""
    import json

    try:
        status = json.loads((run_dir / "summary.json").read_text())["status"]
    except (OSError, ValueError, KeyError):
        status = None
    if status == "finished":
        return f"interrupted while drawing the plots: the episode's record is whole in {run_dir}"
    return f"interrupted: the partial record is in {run_dir}"


def _remove_if_empty(folder: Path) -> None:
    with contextlib.suppress(OSError):  # not empty: it holds the record
        folder.rmdir()


@app.command()
def render(
    scenario: Annotated[
        str, typer.Argument(help="a family (S1..S5, crawl, maze, long) or a scenario .toml file")
    ],
    water: WaterOpt = None,
    seed: Annotated[int, typer.Option(min=0, help="seed of the procedural cave")] = 0,
    views: Annotated[int, typer.Option(min=1, max=24, help="poses along the passage")] = 6,
    out: Annotated[
        Path | None, typer.Option(help="PNG to write (default: render-SCENARIO-WATER.png)")
    ] = None,
    light_power: LightPower = None,
    daylight: Daylight = None,
    particles: Particles = None,
    noise: Noise = None,
    depth_max: DepthMax = DEPTH_RANGE_M[1],
    difficulty: DifficultyOpt = None,
    resolution: Resolution = None,
    sounder_resolution: SounderResolution = None,
) -> None:
    """Write a contact sheet: colour and depth views from poses along the passage."""
    sizes = _sizes(resolution, sounder_resolution)
    from cavenav.episode.gallery import passage_poses, write_contact_sheet
    from cavenav.sensors.rig import SensorConfig
    from cavenav.world.scenarios import load_scenario, parse_difficulty

    with console.status(f"building {scenario} (seed {seed})"):
        cave = load_scenario(scenario, seed, difficulty=parse_difficulty(difficulty or []))
    sensors = _sensors(
        cave,
        replace(SensorConfig(), depth_max_m=depth_max),
        sizes,
        water=water,
        light_power=light_power,
        daylight=daylight,
        particles=particles,
        noise=noise,
    )
    path = out or Path(f"render-{cave.name}-{sensors.optics.water_name}.png")
    with console.status(f"finding {views} poses along {cave.name}"):
        poses = passage_poses(cave, views)
    with console.status("rendering"):
        write_contact_sheet(cave, path, sensors, poses=poses)
    console.print(f"contact sheet: [bold]{path}[/]", soft_wrap=True)


@app.command()
def ask(
    image: Annotated[Path, typer.Argument(help="a colour photograph (PNG or JPEG)")],
    depth: Annotated[Path | None, typer.Option(help="a depth PNG (dark near, bright far)")] = None,
    top: Annotated[float | None, typer.Option(help="d_top: metres to the ceiling")] = None,
    bottom: Annotated[float | None, typer.Option(help="d_bottom: metres to the floor")] = None,
    backend: BackendOpt = Backend.openai,
    base_url: BaseUrl = None,
    model: Model = None,
    api_key_env: ApiKeyEnv = "OPENAI_API_KEY",
    timeout: Timeout = 60.0,
    deadline: Deadline = None,
    retries: Retries = 4,
    temperature: Temperature = 0.2,
    max_tokens: MaxTokens = 1024,
    detail: Detail = None,
    requeries: Requeries = 3,
    prompt_file: PromptFile = None,
    structured: Structured = False,
    device: Device = "auto",
) -> None:
    """Send one query for a single image (e.g. a photograph from a real cave).

    The photograph is turned upright and shrunk to what the model can use; without
    --depth the request carries no depth image and says so, and a missing --top or
    --bottom is sent as "unknown".
    """
    from cavenav.pilots.factory import PilotSpec
    from cavenav.pilots.photo import load_photo

    # The images first: a bad one is refused before the endpoint is contacted.
    observation, notes = load_photo(image, depth, d_top=top, d_bottom=bottom, detail=detail)
    for note in notes:
        console.print(f"[yellow]note:[/] {escape(note)}", soft_wrap=True)
    options = _vlm_options(locals(), history=0, price=None, cache=None)
    pilot = PilotSpec("vlm", options).build()
    decision = pilot.decide(observation)
    console.rule("reasoning")
    console.print(decision.raw, markup=False, highlight=False)
    console.rule("parsed action")
    console.print(f"action:        {decision.action_text}", markup=False)
    console.print(f"justification: {decision.justification}", markup=False)
    from cavenav.actions import to_twist

    console.print(f"twist:         {to_twist(decision.action)}", markup=False)


class FramesMode(StrEnum):
    """What a sweep keeps of each step's images."""

    all = "all"
    png = "png"
    none = "none"


@app.command("eval")
def eval_(
    scenarios: Annotated[
        str,
        typer.Option(help="comma-separated families (S1..S5, crawl, maze, long) or scenario files"),
    ] = "S1,S2,S3,S4,S5",
    seeds: Annotated[
        str, typer.Option(help="caves of each family: 0-19, or 0,3,1000-1019 (test split 1000+)")
    ] = "0-19",
    pilot: Annotated[str, typer.Option(help="pilot to fly: geometric, vlm, random")] = "geometric",
    out: Annotated[
        Path, typer.Option(help="sweep folder; re-run the same command to resume it")
    ] = Path("runs/sweep"),
    workers: Annotated[
        int | None, typer.Option(min=1, help="worker processes (default: the core count)")
    ] = None,
    concurrency: Annotated[
        int, typer.Option(min=1, help="episodes in flight per worker (for model pilots)")
    ] = 1,
    ray_address: Annotated[
        str | None,
        typer.Option(help="run on Ray: 'auto' (this cluster), 'local', or ray://HOST:PORT"),
    ] = None,
    frames: Annotated[
        FramesMode, typer.Option(help="all: PNG + EXR; png: no EXR; none: no images")
    ] = FramesMode.all,
    steps: Steps = None,
    stuck_after: StuckAfter = 50,
    shield: Annotated[bool, typer.Option(help="safety shield between pilot and vehicle")] = False,
    report: Annotated[bool, typer.Option(help="write the HTML report at the end")] = True,
    difficulty: DifficultyOpt = None,
    sounder: Annotated[Sounder, typer.Option(help="echo-sounder model")] = Sounder.camera,
    depth_max: DepthMax = DEPTH_RANGE_M[1],
    water: WaterOpt = None,
    light_power: LightPower = None,
    daylight: Daylight = None,
    particles: Particles = None,
    noise: Noise = None,
    depth_dropout: DepthDropout = None,
    depth_noise: DepthNoise = None,
    resolution: Resolution = None,
    sounder_resolution: SounderResolution = None,
    backend: BackendOpt = Backend.openai,
    base_url: BaseUrl = None,
    model: Model = None,
    api_key_env: ApiKeyEnv = "OPENAI_API_KEY",
    timeout: Timeout = 60.0,
    deadline: Deadline = None,
    retries: Retries = 4,
    temperature: Temperature = 0.2,
    max_tokens: MaxTokens = 1024,
    detail: Detail = None,
    requeries: Requeries = 3,
    history: History = 2,
    prompt_file: PromptFile = None,
    structured: Structured = False,
    map_image: MapImage = False,
    price: Price = None,
    cache: Cache = None,
    device: Device = "auto",
) -> None:
    """Fly a pilot over scenarios x seeds; results.csv, aggregate.json and an HTML report."""
    sizes = _sizes(resolution, sounder_resolution)
    from cavenav.episode.run_folder import prepare_root
    from cavenav.errors import RecordingError
    from cavenav.evaluation.sweep import SweepConfig, check_grid, parse_seeds, run_sweep
    from cavenav.pilots.factory import PilotSpec
    from cavenav.world.scenarios import parse_difficulty

    if pilot == "replay":
        raise CavenavError("a sweep flies geometric, vlm or random pilots, not replay")
    spec = PilotSpec(
        pilot,
        _vlm_options(locals()),
    )
    optics = _optics_flags(
        water=water,
        light_power=light_power,
        daylight=daylight,
        particles=particles,
        noise=noise,
        depth_dropout=depth_dropout,
        depth_noise_m=depth_noise,
    )
    config = SweepConfig(
        scenarios=_scenario_list(scenarios),
        seeds=parse_seeds(seeds),
        pilot=spec,
        steps=steps,
        stuck_after=stuck_after or None,
        shield=shield,
        frames=frames.value,
        difficulty=parse_difficulty(difficulty or []).to_dict(),
        sensors={"sounder": sounder.value, "depth_max_m": depth_max, "optics": optics, **sizes},
    )
    check_grid(config)  # every scenario and knob, in milliseconds, before anything is written
    if pilot == "vlm":
        spec.build()  # a missing key or an unreachable server fails now, not in a worker
    prepare_root(out)  # only now: a refused grid or pilot leaves no folder behind
    executor = _executor(workers, concurrency, ray_address)
    counts = {"done": 0, "success": 0}
    with Progress(
        TextColumn("[progress.description]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("{task.fields[status]}"),
        TimeElapsedColumn(),
        TextColumn("ETA"),
        TimeRemainingColumn(),
        console=console,
    ) as progress:
        task = progress.add_task("episodes", total=None, status="")

        def started(left: int, grid: int) -> None:
            if left < grid:
                progress.console.print(f"resuming {out}: {grid - left} of {grid} episodes done")
            progress.update(task, total=left)

        def done(row: dict) -> None:
            counts["done"] += 1
            counts["success"] += row.get("outcome") == "success"
            status = f"{counts['success']}/{counts['done']} succeeded  last: {row['episode']} "
            progress.update(task, advance=1, status=status + str(row.get("outcome")))

        terminated: list[int] = []
        try:
            with _sigterm_as_ctrl_c(terminated):
                rows = run_sweep(config, out, executor, done, started)
        except KeyboardInterrupt:
            progress.stop()
            errors.print(
                f"interrupted after {counts['done']} episodes: results so far are in {out}; "
                "run the same command again to resume"
            )
            raise typer.Exit(143 if terminated else 130) from None
        except RecordingError as exc:
            progress.stop()
            raise RecordingError(
                f"{exc}; the sweep stopped after {counts['done']} episodes, each record whole: "
                "make room, then run the same command again to resume"
            ) from None
    _print_groups(rows)
    console.print(f"sweep folder: [bold]{out}[/]", soft_wrap=True)
    console.print(f"results:      {out / 'results.csv'}", soft_wrap=True)
    if report:
        from cavenav.evaluation.report import write_report

        console.print(f"report:       {write_report(out, rows)}", soft_wrap=True)


@contextlib.contextmanager
def _sigterm_as_ctrl_c(caught: list[int]) -> Iterator[None]:
    """SIGTERM (kill, a batch scheduler's stop) ends the block as Ctrl-C does: the workers
    are stopped and the tables written; ``caught`` gets the signal, for the exit status
    (143 = 128 + SIGTERM). A second SIGTERM while stopping is ignored."""

    def stop(signum: int, frame: object) -> None:
        caught.append(signum)
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, stop)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def _scenario_list(text: str) -> tuple[str, ...]:
    from cavenav.world.scenarios import SCENARIOS

    names = [part.strip() for part in text.split(",") if part.strip()]
    return tuple(SCENARIOS[name].name if name in SCENARIOS else name for name in names)


def _executor(workers: int | None, concurrency: int, ray_address: str | None) -> Any:
    from cavenav.evaluation.executors import InProcess, LocalPool, RayCluster

    if ray_address:
        return RayCluster(ray_address, workers, concurrency)
    workers = workers or len(os.sched_getaffinity(0))
    return InProcess(concurrency) if workers == 1 else LocalPool(workers, concurrency)


def _print_groups(rows: list[dict]) -> None:
    from cavenav.evaluation.results import aggregate

    groups = aggregate(rows)
    pilots = sorted({g["pilot"] for g in groups})
    table = Table(title=f"{', '.join(pilots)}: success with its 95% Wilson interval")
    for column in ("scenario", "done", "success", "95% CI", "collided", "other outcomes",
                   "min clear.", "path eff.", "steps"):  # fmt: skip
        table.add_column(column)
    for g in groups:
        ci = g["success_ci95"]
        others = ", ".join(
            f"{k} {v}" for k, v in g["outcomes"].items() if k not in ("success", "collision")
        )
        table.add_row(
            g["scenario"],
            f"{g['completed']}/{g['episodes']}",
            "-" if g["success_rate"] is None else f"{g['success_rate']:.0%}",
            "-" if ci is None else f"{ci[0]:.0%}-{ci[1]:.0%}",
            str(g["collisions"]),
            others or "-",
            _metres(g["min_clearance_m"]["min"]),
            "-" if g["path_efficiency"] is None else f"{g['path_efficiency']:.2f}",
            "-" if g["steps"] is None else f"{g['steps']:.0f}",
        )
    console.print(table)


@app.command()
def compare(
    sweep_a: Annotated[Path, typer.Argument(help="sweep folder A")],
    sweep_b: Annotated[Path, typer.Argument(help="sweep folder B, over the same caves")],
    json_out: Annotated[
        Path | None, typer.Option("--json", help="also write the comparison to this file")
    ] = None,
) -> None:
    """Pair two sweeps by cave: success rates, exact McNemar test, caves only one got through."""
    from cavenav.episode.run_folder import write_json
    from cavenav.errors import ConfigError, RecordingError
    from cavenav.evaluation.results import compare as compare_rows
    from cavenav.evaluation.sweep import read_rows, read_sweep

    if json_out is not None and json_out.is_dir():
        raise ConfigError(f"--json {json_out} is a folder: name the file to write")
    (config_a, _), (config_b, _) = read_sweep(sweep_a), read_sweep(sweep_b)
    if dict(config_a.difficulty) != dict(config_b.difficulty):
        raise CavenavError(
            f"the sweeps flew different caves: difficulty {dict(config_a.difficulty)} in "
            f"{sweep_a}, {dict(config_b.difficulty)} in {sweep_b}"
        )
    result = compare_rows(read_rows(sweep_a, write=False), read_rows(sweep_b, write=False))
    label_a, label_b = config_a.pilot.label, config_b.pilot.label
    table = Table(title=f"A = {label_a} ({sweep_a})   B = {label_b} ({sweep_b})")
    for column in ("scenario", "pairs", "A success", "B success", "A - B", "only A", "only B",
                   "McNemar exact p"):  # fmt: skip
        table.add_column(column)
    entries = [*result["per_scenario"].items(), ("all", result["overall"])]
    for name, r in entries:
        if not r["pairs"]:
            continue
        table.add_row(
            name,
            str(r["pairs"]),
            f"{r['success_rate_a']:.0%}",
            f"{r['success_rate_b']:.0%}",
            f"{r['difference']:+.0%}",
            str(len(r["only_a"])),
            str(len(r["only_b"])),
            f"{r['mcnemar_p']:.4g}",
        )
    console.print(table)
    if result["unpaired"]:
        console.print(f"{result['unpaired']} caves were completed in one sweep only (left out)")
    shown = 12
    for side, folder in (("a", sweep_a), ("b", sweep_b)):
        caves = result["overall"][f"only_{side}"]
        if caves:
            console.print(f"[bold]only {side.upper()} got through ({len(caves)}):[/]")
            for cave in caves[:shown]:
                console.print(f"  {cave['cave']}: {folder / cave[side]}", soft_wrap=True)
            if len(caves) > shown:
                console.print(f"  ... {len(caves) - shown} more (all of them with --json FILE)")
    if json_out:
        try:
            write_json(json_out, result)
        except OSError as exc:
            raise RecordingError.cannot_write(
                f"the comparison to {json_out}", exc, " (the table above is complete)"
            ) from None
        console.print(f"comparison: {json_out}", soft_wrap=True)


@app.command()
def report(
    folder: Annotated[Path, typer.Argument(help="a sweep folder or a run folder")],
) -> None:
    """Write the static HTML report of a sweep (or of one run folder)."""
    from cavenav.evaluation.report import write_report

    console.print(f"report: [bold]{write_report(folder)}[/]", soft_wrap=True)


@app.command()
def video(
    run_dir: Annotated[Path, typer.Argument(help="a run folder flown with frames")],
    out: Annotated[
        Path | None, typer.Option(help="MP4 to write (default: RUN/episode.mp4)")
    ] = None,
    fps: Annotated[float, typer.Option(min=0.5, max=60, help="steps per second")] = 4.0,
) -> None:
    """Write an MP4 of an episode: RGB, depth and the top-down map, side by side."""
    from cavenav.episode.video import write_video

    with console.status("encoding"):
        path = write_video(run_dir, out, fps)
    console.print(f"video: [bold]{path}[/]", soft_wrap=True)


class FlyMode(StrEnum):
    """How the bridge drives an ArduSub vehicle (`cavenav.vehicle.mavlink`)."""

    manual = "manual"
    guided = "guided"


# What `cavenav fly` without --sim needs from a real vehicle, and does not have yet.
REAL_VEHICLE_INPUTS = """\
cavenav fly without --sim would fly a real vehicle on its own sensors. A pilot needs, each
step, what the simulator gives it:
  - a forward colour image (640x480 by default, 53 degrees across),
  - a forward depth image in metres, registered to it (a stereo pair or a depth camera),
  - two echo-sounder ranges, up and down (e.g. Blue Robotics Ping2 sonars),
and the bridge needs the vehicle's pose, LOCAL_POSITION_NED and ATTITUDE, in both modes
(a DVL or another position estimate).
cavenav has no driver for these sensors yet. Fly the loop in simulation with
--sim SCENARIO against `cavenav fake-sub` or ArduSub's SITL, or print the MAVLink
commands of an action with --dry-run --action TEXT."""


@app.command()
def fly(
    connect: Annotated[
        str | None,
        typer.Option(help="MAVLink address of the vehicle (default udpin:0.0.0.0:14550)"),
    ] = None,
    pilot: Annotated[
        str, typer.Option(help="pilot to fly: geometric, vlm, replay, random")
    ] = "geometric",
    sim: Annotated[
        str | None,
        typer.Option(
            help="render this scenario (a family or a .toml) at the pose the vehicle reports"
        ),
    ] = None,
    mode: Annotated[
        FlyMode | None,
        typer.Option(help="manual: ALT_HOLD and sticks; guided: GUIDED and position targets"),
    ] = None,
    config: Annotated[
        Path | None, typer.Option(help="bridge settings (TOML): rates, tolerances, limits")
    ] = None,
    yes: Annotated[
        bool, typer.Option("--yes", help="arm without asking (simulation only)")
    ] = False,
    dry_run: Annotated[
        bool, typer.Option("--dry-run", help="print the MAVLink commands of --action, send none")
    ] = False,
    action: Annotated[
        list[str] | None, typer.Option(help="an action string for --dry-run (repeat for more)")
    ] = None,
    seed: Annotated[int, typer.Option(min=0, help="seed of the procedural cave")] = 0,
    out: Annotated[Path, typer.Option(help="folder that receives the run folder")] = Path("runs"),
    steps: Steps = None,
    stuck_after: StuckAfter = 50,
    frames: Annotated[bool, typer.Option(help="save RGB, depth PNG and EXR of every step")] = True,
    shield: Annotated[
        bool, typer.Option(help="safety shield between pilot and vehicle (on by default here)")
    ] = True,
    from_: Annotated[Path | None, typer.Option("--from", help="run folder to replay")] = None,
    backend: BackendOpt = Backend.openai,
    base_url: BaseUrl = None,
    model: Model = None,
    api_key_env: ApiKeyEnv = "OPENAI_API_KEY",
    timeout: Timeout = 60.0,
    deadline: Deadline = None,
    retries: Retries = 4,
    temperature: Temperature = 0.2,
    max_tokens: MaxTokens = 1024,
    detail: Detail = None,
    requeries: Requeries = 3,
    history: History = 2,
    prompt_file: PromptFile = None,
    structured: Structured = False,
    map_image: MapImage = False,
    price: Price = None,
    cache: Cache = None,
    device: Device = "auto",
) -> None:
    """Fly a pilot on an ArduSub vehicle over MAVLink (BlueROV2); with --sim, in a cave."""
    from cavenav.vehicle.mavlink import load_bridge_config

    bridge = load_bridge_config(config, connect=connect, mode=mode.value if mode else None)
    if dry_run:
        _print_dry_run(bridge, action or [])
        return
    if sim is None:
        errors.print(REAL_VEHICLE_INPUTS, highlight=False)
        raise typer.Exit(2)
    from cavenav.episode.loop import EpisodeConfig
    from cavenav.episode.run_folder import new_run_dir, prepare_root
    from cavenav.pilots.factory import PilotSpec
    from cavenav.sensors.rig import SensorConfig
    from cavenav.vehicle.mavlink import ArduSubMotion
    from cavenav.world.scenarios import load_scenario

    spec = PilotSpec(pilot, _vlm_options(locals()), recording=str(from_) if from_ else None)
    prepare_root(out)
    flyer = spec.build(seed=seed)
    with console.status(f"building {sim} (seed {seed})"):
        cave = load_scenario(sim, seed)
    sensors = _sensors(cave, SensorConfig())
    episode = EpisodeConfig(
        max_steps=steps,
        stuck_after=stuck_after or None,
        save_frames=frames,
        shield=shield,
        sensors=sensors,
    )
    run_dir = new_run_dir(out, cave.name, pilot, cave.seed)
    motion = ArduSubMotion(
        bridge, run_dir / "mavlink.jsonl", confirm=None if yes else typer.confirm
    )
    try:
        listening = motion.listen()  # with udpin:HOST:0, the port the system chose
        where = f", listening on {listening[0]}:{listening[1]}" if listening else ""
        console.print(
            f"[bold]{cave.name}[/] through MAVLink ({bridge.mode} mode, {bridge.connect}{where}): "
            "waiting for the vehicle's heartbeat",
            soft_wrap=True,
            highlight=False,
        )
        _fly_episode(cave, flyer, episode, run_dir, motion)
    except CavenavError:
        motion.close()  # closes the command log
        if not (run_dir / "summary.json").exists():  # failed to connect: nothing was flown,
            (run_dir / "mavlink.jsonl").unlink(missing_ok=True)  # so no folder looks like a run
            _remove_if_empty(run_dir)
        raise
    finally:
        motion.close()
    console.print(f"commands:   {run_dir / 'mavlink.jsonl'}", soft_wrap=True)


def _print_dry_run(bridge: Any, actions: list[str]) -> None:  # noqa: ANN401
    from cavenav.actions import format_action, parse_action
    from cavenav.vehicle.mavlink import describe, plan

    if not actions:
        raise typer.BadParameter("give the action to describe, e.g. --action 'forward 0.5 m'")
    for text in actions:
        command = parse_action(text)
        console.print(f"[bold]{format_action(command)}[/] ({bridge.mode} mode):")
        for line in describe(plan(command, bridge), bridge):
            console.print(f"  {line}", soft_wrap=True, highlight=False)


@app.command("fake-sub")
def fake_sub(
    connect: Annotated[
        str, typer.Option(help="where to send (the bridge listens there with udpin)")
    ] = "udpout:127.0.0.1:14550",
    noise: Annotated[
        float, typer.Option(min=0, callback=_finite, help="execution noise (relative gain error)")
    ] = 0.0,
    current: Annotated[
        str, typer.Option(metavar="N,E,D", help="water current, m/s north, east, down")
    ] = "0,0,0",
    depth: Annotated[float, typer.Option(min=0, callback=_finite, help="start depth, m")] = 30.0,
    position: Annotated[
        bool, typer.Option(help="report LOCAL_POSITION_NED and allow GUIDED (a DVL)")
    ] = True,
    pilot_timeout: Annotated[
        float, typer.Option(min=0.1, callback=_finite, help="FS_PILOT_TIMEOUT, seconds")
    ] = 3.0,
    seed: Annotated[int, typer.Option(min=0, help="seed of the execution noise")] = 0,
) -> None:
    """A simulated ArduSub autopilot on MAVLink, for `cavenav fly --sim` with no vehicle."""
    from cavenav.vehicle.fake_sub import FakeSubConfig, FakeSubState, serve

    try:
        drift = tuple(float(v) for v in current.split(","))
    except ValueError:
        drift = ()
    if len(drift) != 3 or not all(map(math.isfinite, drift)):
        raise typer.BadParameter(
            f"{current!r}: give three numbers N,E,D in m/s", param_hint="--current"
        )
    settings = FakeSubConfig(
        address=connect,
        noise=noise,
        current_ned_mps=drift,  # type: ignore[arg-type]
        start_ned=(0.0, 0.0, depth),
        position_estimate=position,
        pilot_timeout_s=pilot_timeout,
        seed=seed,
    )

    def show(state: FakeSubState) -> None:
        console.print(
            f"{'ARMED' if state.armed else 'disarmed':8} {state.mode_name:8} "
            f"N {state.north:7.2f}  E {state.east:7.2f}  depth {state.down:6.2f}  "
            f"yaw {state.yaw_deg:7.1f}  sticks {state.sticks}"
            + ("  [red]pilot-input failsafe[/]" if state.failsafe else ""),
            highlight=False,
            soft_wrap=True,
        )

    console.print(f"fake ArduSub sending to {connect}; Ctrl-C stops it")
    with contextlib.suppress(KeyboardInterrupt):
        serve(settings, on_state=show)


def _print_summary(summary: dict) -> None:
    table = Table(title="episode summary", show_header=False)
    table.add_column(style="bold")
    table.add_column()
    rows = [
        ("scenario", summary["scenario"]),
        ("pilot", summary["pilot"]),
        ("seed", summary["seed"]),
        ("termination", summary["termination"]),
        ("success", "yes" if summary["success"] else "no"),
        ("steps", summary["steps"]),
        ("collisions", summary["collisions"]),
        ("path length", f"{summary['path_length_m']:.1f} m"),
        ("min clearance", _metres(summary["min_clearance_m"])),
        ("mean clearance", _metres(summary["mean_clearance_m"])),
        ("steps below standoff", summary["steps_below_standoff"]),
        ("sensing per step", f"{summary['mean_sense_ms']} ms"),
        ("first sensing", f"{summary.get('first_sense_ms')} ms (with loading the kernels)"),
        ("pilot per step", f"{summary['mean_pilot_ms']} ms"),
    ]
    if summary.get("shield"):
        rows.append(("shield interventions", summary["shield_interventions"]))
    if summary.get("invalid_actions"):
        rows.append(("invalid actions (held)", summary["invalid_actions"]))
    usage = summary.get("usage")
    if usage:
        rows += [
            ("prompt tokens", usage["prompt_tokens"]),
            ("completion tokens", usage["completion_tokens"]),
            ("mean model latency", f"{usage['mean_latency_s']:.2f} s"),
            ("re-queries", usage["requeries"]),
            ("transport retries", usage["transport_retries"]),
            ("cost", "-" if usage["cost_usd"] is None else f"${usage['cost_usd']:.4f}"),
        ]
    if "mean_drift_m" in summary:  # flown on a vehicle (cavenav fly)
        rows += [
            ("drift from command", f"{summary['mean_drift_m']:.3f} m mean, "
             f"{summary['max_drift_m']:.3f} m max, {summary['max_drift_deg']:.1f} deg max"),
            ("action on the vehicle", f"{summary['mean_physics_ms'] / 1e3:.2f} s mean"),
        ]  # fmt: skip
    if summary.get("failure"):
        rows.append(("failure", summary["failure"]))
    for key, value in rows:
        # Escaped: a failure quoting a server or a reply ("[redacted]", "[/]") is text,
        # not rich markup, which would swallow it or fail on it.
        table.add_row(key, "-" if value is None else escape(str(value)))
    console.print(table)


def _metres(value: float | None) -> str:
    return "-" if value is None else f"{value:.2f} m"


@app.command()
def warmup() -> None:
    """Compile the sensor and pilot kernels into numba's cache (once per machine; make setup
    runs it)."""
    from cavenav.episode.warmup import warm_up

    with console.status("loading the kernels (the first time on a machine: compiling)"):
        seconds = warm_up()
    console.print(f"sensor and pilot kernels ready ({seconds:.1f} s)")


@app.command()
def scenarios(
    examples: Annotated[Path, typer.Option(help="folder searched for scenario files")] = Path(
        "examples"
    ),
) -> None:
    """List the built-in scenarios and the scenario files found in EXAMPLES."""
    from cavenav.world.scenarios import SCENARIOS

    table = Table(title="scenarios")
    table.add_column("name", style="bold", no_wrap=True)
    table.add_column("kind")
    table.add_column("description")
    for name, factory in SCENARIOS.items():
        table.add_row(name, "procedural (--seed)", factory.summary)
    for path in sorted(examples.glob("*.toml")) if examples.is_dir() else []:
        table.add_row(str(path), "scenario file", _first_comment(path))
    console.print(table)


def _first_comment(path: Path) -> str:
    for line in path.read_text(errors="replace").splitlines():
        if line.startswith("#"):
            return line.lstrip("# ").strip()
    return ""


def main() -> None:
    """Entry point; the exit status is part of the interface (README, "Bad input and faults").

    0: the command did its work (an episode ended at the exit, a wall or the budget).
    1: an episode ended as a pilot failure, or the run folder could not be written.
    2: bad input (a typer usage error, or a `CavenavError`), refused before anything
       was written.
    3: `fly`: the vehicle failed the bridge (no heartbeat, refused, a stale link).
    130: interrupted (Ctrl-C); what was recorded so far stays valid.
    143: `eval` stopped by SIGTERM, as by Ctrl-C.
    """
    warnings.showwarning = _show_warning
    try:
        app()
    except CavenavError as exc:
        # One line, even when the message quotes a model's multi-line reply; no key in it,
        # whatever a server echoed (backends redact already: this is the last guard).
        message = redact(" ".join(str(exc).split()))
        errors.print(f"[red]error:[/] {escape(message)}", highlight=False)
        sys.exit(exc.exit_status)
    except KeyboardInterrupt:
        errors.print("interrupted")
        sys.exit(130)


def _show_warning(message: Warning | str, category: type[Warning], *_: Any, **__: Any) -> None:
    """Our warnings (a mesh in centimetres, ...) as one line; others as Python prints them."""
    from cavenav.errors import CavenavWarning

    if issubclass(category, CavenavWarning):
        errors.print(f"[yellow]warning:[/] {escape(str(message))}", highlight=False)
    else:
        errors.print(f"{category.__name__}: {escape(str(message))}", highlight=False)


if __name__ == "__main__":
    main()
