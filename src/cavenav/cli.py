"""The command line: flags -> configuration -> library calls, nothing else.

cavenav run S4                         fly S4 with the geometric pilot
cavenav run examples/osrf_cave_L.toml  fly a user mesh described by a scenario file
cavenav render S4 --water turbid       contact sheet of the views along the passage
cavenav scenarios                      list what can be flown
"""

from __future__ import annotations

import sys
from dataclasses import replace
from enum import StrEnum
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.console import Console
from rich.markup import escape
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from cavenav.errors import CavenavError
from cavenav.sensors.depth import DEPTH_RANGE_M

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    help="cavenav: VLM-steered navigation of an underwater vehicle through unseen caves.",
)
console = Console()
errors = Console(stderr=True, soft_wrap=True)

PILOTS = ("geometric", "vlm", "replay", "random")


class Sounder(StrEnum):
    """Echo-sounder models (see `cavenav.sensors.rig.SensorConfig`)."""

    camera = "camera"
    beam = "beam"


class Backend(StrEnum):
    openai = "openai"
    transformers = "transformers"


class WaterType(StrEnum):
    """Water presets (see `cavenav.sensors.optics.WATER_TYPES`)."""

    clear = "clear"
    ocean = "ocean"
    coastal = "coastal"
    turbid = "turbid"


# Options shared by `run` and `render`: how the cave looks. None keeps the scenario's own.
WaterOpt = Annotated[WaterType | None, typer.Option(help="water preset (default: clear)")]
LightPower = Annotated[
    float | None, typer.Option(min=0, help="lamp power; 0 turns the lamps off (default 20)")
]
Daylight = Annotated[
    float | None, typer.Option(min=0, help="open-water brightness at exits (default 1)")
]
Particles = Annotated[
    float | None, typer.Option(min=0, help="marine snow, particles per m³ (default 2)")
]
Noise = Annotated[float | None, typer.Option(min=0, help="sensor noise, 0 = none (default 1)")]
DepthDropout = Annotated[
    float | None,
    typer.Option(min=0, help="drop depth where returned lamp light is below this (default 0)"),
]
DepthNoise = Annotated[
    float | None, typer.Option(min=0, help="depth noise std at 10 m, metres (default 0)")
]


def _sensors(cave: Any, base: Any, **options: Any) -> Any:  # noqa: ANN401 - lazy imports
    """``base`` SensorConfig with the scenario's [optics] table, then the CLI options."""
    from cavenav.sensors.optics import optics_from_table

    optics = optics_from_table(cave.optics, base.optics, where=f"{cave.name}: [optics]")
    flags = {k: (v.value if isinstance(v, StrEnum) else v) for k, v in options.items()}
    return replace(base, optics=optics_from_table(flags, optics, where="options"))


DepthMax = Annotated[float, typer.Option(help="D_max of the depth PNG, metres")]

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
Timeout = Annotated[float, typer.Option(help="seconds per request")]
Retries = Annotated[int, typer.Option(min=0, help="transport retries per request")]
Temperature = Annotated[float, typer.Option(help="sampling temperature")]
MaxTokens = Annotated[int, typer.Option(min=16, help="maximum output tokens per reply")]
Detail = Annotated[str | None, typer.Option(help="image detail sent with images: low, high, auto")]
Requeries = Annotated[int, typer.Option(min=0, help="re-queries after an unusable reply")]
History = Annotated[int, typer.Option(min=0, help="earlier observations sent (K)")]
PromptFile = Annotated[Path | None, typer.Option(help="your own system-prompt template")]
Structured = Annotated[bool, typer.Option(help="ask for a JSON schema with fixed keys")]
Price = Annotated[str | None, typer.Option(help="USD per million tokens, 'input,output'")]
Cache = Annotated[Path | None, typer.Option(help="reply cache folder (keyed by request hash)")]
Device = Annotated[str, typer.Option(help="transformers device: auto, cpu, cuda")]


def _vlm_pilot(
    *,
    backend: Backend,
    base_url: str | None,
    model: str | None,
    api_key_env: str,
    timeout: float,
    retries: int,
    temperature: float,
    max_tokens: int,
    detail: str | None,
    requeries: int,
    history: int,
    prompt_file: Path | None,
    structured: bool,
    price: str | None,
    cache: Path | None,
    device: str,
):  # noqa: ANN202 - VLMPilot
    from cavenav.pilots.backends import (
        CachedBackend,
        OpenAIBackend,
        OpenAIConfig,
        TransformersBackend,
        TransformersConfig,
    )
    from cavenav.pilots.prompt import PromptConfig
    from cavenav.pilots.vlm import VLMPilot

    if not model:
        raise CavenavError(
            "the VLM pilot needs --model (a model name, or a folder for transformers)"
        )
    engine: Any
    if backend is Backend.openai:
        engine = OpenAIBackend(
            OpenAIConfig(
                model=model,
                base_url=base_url,
                api_key_env=api_key_env,
                timeout_s=timeout,
                max_retries=retries,
                temperature=temperature,
                max_tokens=max_tokens,
                detail=detail or "auto",
            )
        )
    else:
        engine = TransformersBackend(
            TransformersConfig(
                model=model, device=device, max_new_tokens=max_tokens, temperature=temperature
            )
        )
    if cache is not None:
        engine = CachedBackend(engine, cache)
    prices = None
    if price:
        try:
            price_in, price_out = (float(v) for v in price.split(","))
        except ValueError:
            raise CavenavError(
                f"--price must be 'input,output' in USD per million tokens, got '{price}'"
            ) from None
        prices = (price_in, price_out)
    prompt = PromptConfig(history=history, system_file=prompt_file, structured=structured)
    return VLMPilot(engine, prompt, max_requeries=requeries, detail=detail, price_per_mtok=prices)


@app.command()
def run(
    scenario: Annotated[str, typer.Argument(help="S1..S5, or the path of a scenario .toml file")],
    pilot: Annotated[str, typer.Option(help=f"pilot to fly: {', '.join(PILOTS)}")] = "geometric",
    seed: Annotated[
        int, typer.Option(help="seed of the procedural cave (S1..S5) and of the random pilot")
    ] = 0,
    out: Annotated[Path, typer.Option(help="folder that receives the run folder")] = Path("runs"),
    steps: Annotated[int, typer.Option(min=1, help="step budget")] = 150,
    frames: Annotated[bool, typer.Option(help="save RGB, depth PNG and EXR of every step")] = True,
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
    from_: Annotated[Path | None, typer.Option("--from", help="run folder to replay")] = None,
    backend: BackendOpt = Backend.openai,
    base_url: BaseUrl = None,
    model: Model = None,
    api_key_env: ApiKeyEnv = "OPENAI_API_KEY",
    timeout: Timeout = 60.0,
    retries: Retries = 4,
    temperature: Temperature = 0.2,
    max_tokens: MaxTokens = 1024,
    detail: Detail = None,
    requeries: Requeries = 3,
    history: History = 2,
    prompt_file: PromptFile = None,
    structured: Structured = False,
    price: Price = None,
    cache: Cache = None,
    device: Device = "auto",
) -> None:
    """Fly one episode and write its run folder (summary, steps, frames, plots)."""
    from cavenav.episode.loop import EpisodeConfig, run_episode
    from cavenav.episode.run_folder import new_run_dir
    from cavenav.sensors.rig import SensorConfig
    from cavenav.world.scenarios import load_scenario

    if pilot not in PILOTS:
        raise CavenavError(f"unknown pilot '{pilot}'; choose one of {', '.join(PILOTS)}")
    flyer: Any
    if pilot == "replay":
        from cavenav.pilots.replay import ReplayPilot, recorded_scenario

        if from_ is None:
            raise CavenavError("--pilot replay needs --from RUN_DIR")
        flyer = ReplayPilot(from_)
        recorded, recorded_seed = recorded_scenario(from_)
        if recorded != scenario.upper() and Path(scenario).stem not in recorded:
            console.print(
                f"[yellow]note:[/] the recording flew {recorded}, replaying in {scenario}"
            )
        seed = recorded_seed if recorded_seed is not None else seed
    elif pilot == "vlm":
        flyer = _vlm_pilot(
            backend=backend,
            base_url=base_url,
            model=model,
            api_key_env=api_key_env,
            timeout=timeout,
            retries=retries,
            temperature=temperature,
            max_tokens=max_tokens,
            detail=detail,
            requeries=requeries,
            history=history,
            prompt_file=prompt_file,
            structured=structured,
            price=price,
            cache=cache,
            device=device,
        )
    elif pilot == "random":
        from cavenav.pilots.random_pilot import RandomPilot

        flyer = RandomPilot(seed)
    else:
        from cavenav.pilots.geometric import GeometricPilot

        flyer = GeometricPilot()
    with console.status(f"building {scenario} (seed {seed})"):
        cave = load_scenario(scenario, seed)
    sensors = _sensors(
        cave,
        replace(SensorConfig(), sounder=sounder.value, depth_max_m=depth_max),
        water=water,
        light_power=light_power,
        daylight=daylight,
        particles=particles,
        noise=noise,
        depth_dropout=depth_dropout,
        depth_noise_m=depth_noise,
    )
    config = EpisodeConfig(max_steps=steps, save_frames=frames, shield=shield, sensors=sensors)
    run_dir = new_run_dir(out, cave.name, pilot, cave.seed)
    console.print(
        f"[bold]{cave.name}[/]: {cave.description or cave.mesh.name} "
        f"({cave.mesh.triangle_count:,} triangles)"
    )
    with Progress(
        TextColumn("[progress.description]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("{task.fields[status]}"),
        TimeElapsedColumn(),
        console=console,
    ) as progress:
        task = progress.add_task(f"flying {cave.name}", total=steps, status="")

        def on_step(record: dict) -> None:
            status = f"clearance {record['clearance_m']:.2f} m  {record.get('action') or ''}"
            progress.update(task, advance=1, status=status[:60])

        try:
            result = run_episode(cave, flyer, config, run_dir, on_step)
        except KeyboardInterrupt:
            progress.stop()
            errors.print(f"interrupted: the partial record is in {run_dir}")
            raise typer.Exit(130) from None
    _print_summary(result.summary)
    # soft_wrap: paths stay on one line, whatever the terminal width, for copy and paste.
    console.print(f"run folder: [bold]{run_dir}[/]", soft_wrap=True)
    for name in result.summary.get("plots", {}).values():
        console.print(f"plot:       {run_dir / name}", soft_wrap=True)


@app.command()
def render(
    scenario: Annotated[str, typer.Argument(help="S1..S5, or the path of a scenario .toml file")],
    water: WaterOpt = None,
    seed: Annotated[int, typer.Option(help="seed of the procedural cave (S1..S5)")] = 0,
    views: Annotated[int, typer.Option(min=1, max=24, help="poses along the passage")] = 6,
    out: Annotated[
        Path | None, typer.Option(help="PNG to write (default: render-SCENARIO-WATER.png)")
    ] = None,
    light_power: LightPower = None,
    daylight: Daylight = None,
    particles: Particles = None,
    noise: Noise = None,
    depth_max: DepthMax = DEPTH_RANGE_M[1],
) -> None:
    """Write a contact sheet: colour and depth views from poses along the passage."""
    from cavenav.episode.gallery import passage_poses, write_contact_sheet
    from cavenav.sensors.rig import SensorConfig
    from cavenav.world.scenarios import load_scenario

    with console.status(f"building {scenario} (seed {seed})"):
        cave = load_scenario(scenario, seed)
    sensors = _sensors(
        cave,
        replace(SensorConfig(), depth_max_m=depth_max),
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
    retries: Retries = 4,
    temperature: Temperature = 0.2,
    max_tokens: MaxTokens = 1024,
    detail: Detail = None,
    requeries: Requeries = 3,
    prompt_file: PromptFile = None,
    structured: Structured = False,
    device: Device = "auto",
) -> None:
    """Send one query for a single image (e.g. a photograph from a real cave)."""
    import numpy as np
    from PIL import Image, UnidentifiedImageError

    from cavenav.types import Observation

    def read(path: Path, mode: str) -> np.ndarray:
        try:
            return np.asarray(Image.open(path).convert(mode))
        except (OSError, UnidentifiedImageError) as exc:
            raise CavenavError(f"cannot read image {path}: {exc}") from None

    from cavenav.sensors.camera import CameraIntrinsics

    rgb = read(image, "RGB")
    depth_png = read(depth, "L") if depth else np.full(rgb.shape[:2], 255, np.uint8)
    pilot = _vlm_pilot(
        backend=backend,
        base_url=base_url,
        model=model,
        api_key_env=api_key_env,
        timeout=timeout,
        retries=retries,
        temperature=temperature,
        max_tokens=max_tokens,
        detail=detail,
        requeries=requeries,
        history=0,
        prompt_file=prompt_file,
        structured=structured,
        price=None,
        cache=None,
        device=device,
    )
    nan = float("nan")
    observation = Observation(
        rgb=rgb,
        depth_m=depth_png.astype(np.float32),
        depth_png=depth_png,
        d_top=nan if top is None else top,
        d_bottom=nan if bottom is None else bottom,
        depth_range=DEPTH_RANGE_M,
        hfov_deg=CameraIntrinsics().hfov_deg,
    )
    decision = pilot.decide(observation)
    console.rule("reasoning")
    console.print(decision.raw, markup=False, highlight=False)
    console.rule("parsed action")
    console.print(f"action:        {decision.action_text}", markup=False)
    console.print(f"justification: {decision.justification}", markup=False)
    from cavenav.actions import to_twist

    console.print(f"twist:         {to_twist(decision.action)}", markup=False)


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
    if summary.get("failure"):
        rows.append(("failure", summary["failure"]))
    for key, value in rows:
        table.add_row(key, "-" if value is None else str(value))
    console.print(table)


def _metres(value: float | None) -> str:
    return "-" if value is None else f"{value:.2f} m"


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
    """Entry point: typer reports usage errors; our own errors become one line, exit 2."""
    try:
        app()
    except CavenavError as exc:
        errors.print(f"[red]error:[/] {escape(str(exc))}", highlight=False)
        sys.exit(2)
    except KeyboardInterrupt:
        errors.print("interrupted")
        sys.exit(130)


if __name__ == "__main__":
    main()
