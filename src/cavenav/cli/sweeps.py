"""Many episodes: `eval` flies a sweep, `compare` sets sweeps side by side, `report` writes
the HTML report of a sweep or a run folder."""

from __future__ import annotations

import os
from dataclasses import replace
from enum import StrEnum
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer

from cavenav.cli.common import (
    PolicyOpt,
    TeacherOpt,
    camera_for,
    pilot_spec,
)
from cavenav.cli.episode_flags import (
    BACKEND,
    EPISODE,
    MODEL,
    SETTINGS,
    SOUNDER,
    VLM,
    ApiKeyEnvOpt,
    BackendOpt,
    BaseUrlOpt,
    BatteryWhOpt,
    CacheOpt,
    DaylightOpt,
    DeadlineOpt,
    DepthDropoutOpt,
    DepthMaxOpt,
    DepthNoiseOpt,
    DepthSourceOpt,
    DesignOpt,
    DetailOpt,
    DeviceOpt,
    DifficultyOpt,
    DischargeOpt,
    DvlOpt,
    EnergyPromptOpt,
    GuidelineColourOpt,
    GuidelineOpt,
    GustsOpt,
    HistoryOpt,
    ImageFormatOpt,
    ImageSizeOpt,
    JpegQualityOpt,
    LampBeamOpt,
    LampKelvinOpt,
    LampLumensOpt,
    LampsOpt,
    LightPowerOpt,
    MapImageOpt,
    MaxTokensOpt,
    ModelOpt,
    NoiseOpt,
    NoiseSeedOpt,
    ParticlesOpt,
    PriceOpt,
    PromptFileOpt,
    ReplanEveryOpt,
    RequeriesOpt,
    ResolutionOpt,
    RetriesOpt,
    SiltOutOpt,
    SonarOpt,
    SounderOpt,
    SounderResolutionOpt,
    StepsOpt,
    StructuredOpt,
    StuckAfterOpt,
    TemperatureOpt,
    TimeoutOpt,
    WaterOpt,
)
from cavenav.cli.flights import fly_sweep
from cavenav.cli.output import console, print_comparison, print_groups, print_leaderboard
from cavenav.core.errors import CavenavError
from cavenav.episode.settings import FRAME_MODES, VIDEO_MODES
from cavenav.pilots.factory import VLMOptions

if TYPE_CHECKING:
    from cavenav.evaluation.results import ResultRow

# What a sweep keeps of each step's images (`cavenav.episode.settings.FRAME_MODES`).
FramesMode = StrEnum("FramesMode", {name: name for name in FRAME_MODES})  # type: ignore[misc]
# Which episodes of a sweep get a video (`cavenav.episode.settings.VIDEO_MODES`).
VideoMode = StrEnum("VideoMode", {name: name for name in VIDEO_MODES})  # type: ignore[misc]
VideoOpt = Annotated[
    VideoMode, typer.Option(help="episode.mp4 for none, failures or all episodes, as each ends")
]


TrialsOpt = Annotated[
    int, typer.Option(min=1, help="flights of each cave, for pilots that sample (temperature > 0)")
]
WandbOpt = Annotated[
    bool, typer.Option(help="log episodes, results and videos to Weights & Biases (offline)")
]


def eval_(
    scenarios: Annotated[
        str,
        typer.Option(help="comma-separated families (S1..S5, crawl, maze, long) or scenario files"),
    ] = "S1,S2,S3,S4,S5",
    seeds: Annotated[
        str, typer.Option(help="caves of each family: 0-19, or 0,3,1000-1019 (test split 1000+)")
    ] = "0-19",
    pilot: Annotated[
        str, typer.Option(help="pilot to fly: geometric, vlm, random, policy")
    ] = "geometric",
    policy: PolicyOpt = None,
    teacher: TeacherOpt = None,
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
    ] = FramesMode["all"],
    shield: Annotated[bool, typer.Option(help="safety shield between pilot and vehicle")] = False,
    report: Annotated[bool, typer.Option(help="write the HTML report at the end")] = True,
    video: VideoOpt = VideoMode["none"],
    trials: TrialsOpt = 1,
    wandb: WandbOpt = False,
    steps: StepsOpt = EPISODE.max_steps,
    stuck_after: StuckAfterOpt = EPISODE.stuck_after,
    sounder: SounderOpt = SOUNDER,
    depth_max: DepthMaxOpt = EPISODE.sensors.depth_max_m,
    water: WaterOpt = None,
    light_power: LightPowerOpt = None,
    lamps: LampsOpt = None,
    lamp_lumens: LampLumensOpt = None,
    lamp_beam: LampBeamOpt = None,
    lamp_kelvin: LampKelvinOpt = None,
    daylight: DaylightOpt = None,
    particles: ParticlesOpt = None,
    silt_out: SiltOutOpt = None,
    noise: NoiseOpt = None,
    depth_dropout: DepthDropoutOpt = None,
    depth_noise: DepthNoiseOpt = None,
    resolution: ResolutionOpt = None,
    sounder_resolution: SounderResolutionOpt = None,
    depth_source: DepthSourceOpt = None,
    sonar: SonarOpt = None,
    dvl: DvlOpt = None,
    difficulty: DifficultyOpt = None,
    discharge: DischargeOpt = EPISODE.discharge_m3s,
    gusts: GustsOpt = EPISODE.gusts,
    battery_wh: BatteryWhOpt = EPISODE.battery_wh,
    noise_seed: NoiseSeedOpt = EPISODE.seed,
    guideline: GuidelineOpt = EPISODE.guideline,
    guideline_colour: GuidelineColourOpt = None,
    backend: BackendOpt = BACKEND,
    base_url: BaseUrlOpt = None,
    model: ModelOpt = None,
    api_key_env: ApiKeyEnvOpt = MODEL.api_key_env,
    timeout: TimeoutOpt = MODEL.timeout,
    deadline: DeadlineOpt = None,
    retries: RetriesOpt = MODEL.retries,
    temperature: TemperatureOpt = MODEL.temperature,
    max_tokens: MaxTokensOpt = MODEL.max_tokens,
    detail: DetailOpt = None,
    requeries: RequeriesOpt = MODEL.requeries,
    history: HistoryOpt = MODEL.history,
    prompt_file: PromptFileOpt = None,
    structured: StructuredOpt = MODEL.structured,
    map_image: MapImageOpt = MODEL.map_image,
    energy_prompt: EnergyPromptOpt = MODEL.energy_prompt,
    design: DesignOpt = MODEL.design,
    replan_every: ReplanEveryOpt = MODEL.replan_every,
    image_format: ImageFormatOpt = MODEL.image_format,
    jpeg_quality: JpegQualityOpt = MODEL.jpeg_quality,
    image_size: ImageSizeOpt = None,
    price: PriceOpt = None,
    cache: CacheOpt = None,
    device: DeviceOpt = MODEL.device,
) -> None:
    """Fly a pilot over scenarios x seeds (x trials); results.csv, aggregate.json, a report."""
    settings = SETTINGS.value(locals())
    vlm = VLM.value(locals())
    from cavenav.episode.run_folder import prepare_root
    from cavenav.evaluation.sweep import SweepConfig, check_grid, parse_seeds

    if pilot == "replay":
        raise CavenavError("a sweep flies geometric, vlm, random or policy pilots, not replay")
    spec = pilot_spec(pilot, vlm, None, policy, teacher)
    settings = replace(camera_for(spec, settings), shield=shield).with_frames(frames.value)
    grid = (_scenario_list(scenarios), parse_seeds(seeds))
    config = SweepConfig(*grid, spec, settings, video=video.value, trials=trials)
    check_grid(config)  # every scenario and knob, in milliseconds, before anything is written
    if pilot == "vlm":
        spec.build()  # a missing key or an unreachable server fails now, not in a worker
    log = _wandb_log(out, config) if wandb else None  # wandb missing: refused here
    prepare_root(out)  # only now: a refused grid or pilot leaves no folder behind
    executor = _executor(workers, concurrency, ray_address)
    rows = fly_sweep(config, out, executor, log.episode if log else None)
    _sweep_flown(out, rows, report, log)


def _sweep_flown(out: Path, rows: list[ResultRow], report: bool, log: Any) -> None:  # noqa: ANN401
    """The tables, the paths, the report and the W&B run's last entries of a sweep."""
    if log:
        log.finish(rows)
    print_groups(rows)
    console.print(f"sweep folder: [bold]{out}[/]", soft_wrap=True)
    console.print(f"results:      {out / 'results.csv'}", soft_wrap=True)
    if report:
        from cavenav.evaluation.report import write_report

        console.print(f"report:       {write_report(out, rows)}", soft_wrap=True)


def _wandb_log(out: Path, config: Any) -> Any:  # noqa: ANN401
    from cavenav.evaluation.export import WandbLog

    return WandbLog(out, config.to_dict())


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


def compare(
    sweeps: Annotated[
        list[Path], typer.Argument(help="two sweep folders or more, over the same caves")
    ],
    out: Annotated[
        Path | None,
        typer.Option(help="write the comparison page here: index.html, compare.json, tables"),
    ] = None,
    json_out: Annotated[
        Path | None, typer.Option("--json", help="also write the comparison to this file")
    ] = None,
    price: Annotated[
        list[str] | None,
        typer.Option(
            metavar="MODEL=IN,OUT",
            help="price MODEL's recorded tokens: USD per million in, out (repeatable)",
        ),
    ] = None,
    allow_unpaired: Annotated[
        bool,
        typer.Option(help="show sweeps over different caves side by side, without tests"),
    ] = False,
) -> None:
    """Pilots side by side, paired by cave: success with its interval, McNemar, Wilcoxon.

    With two sweeps it prints the paired table and the caves only one got through; with
    more, a leaderboard and every pair. --out DIR writes the page (DIR/index.html), the
    JSON behind it (DIR/compare.json) and the leaderboard as Markdown and LaTeX.
    """
    from cavenav.core.errors import RecordingError
    from cavenav.episode.run_folder import write_json
    from cavenav.evaluation import comparison

    _check_compare_outputs(json_out, out)
    read = comparison.load_sweeps(sweeps, _model_prices(price or []), allow_unpaired)
    result = comparison.comparison(read)
    if result["unpaired"]:
        console.print(f"unpaired, no tests: {result['unpaired']}", soft_wrap=True)
    if len(read) == 2 and not result["unpaired"]:
        a, b = read
        title = f"A = {a.label} ({a.path})   B = {b.label} ({b.path})"
        print_comparison(result["pairs"][0], title, (a.path, b.path))
    else:
        print_leaderboard(result)
    if json_out:
        try:  # two sweeps: the pair's tests, as before; more: the whole comparison
            write_json(json_out, result["pairs"][0] if len(result["pairs"]) == 1 else result)
        except OSError as exc:
            raise RecordingError.cannot_write(
                f"the comparison to {json_out}", exc, " (the table above is complete)"
            ) from None
        console.print(f"comparison: {json_out}", soft_wrap=True)
    if out:
        comparison.write(read, result, out)
        for table in (comparison.markdown_table(result), comparison.latex_table(result)):
            console.print(table, markup=False, highlight=False, soft_wrap=True)
        console.print(f"comparison page: [bold]{out / 'index.html'}[/]", soft_wrap=True)


def _check_compare_outputs(json_out: Path | None, out: Path | None) -> None:
    """--json and --out checked before any sweep is read: a file and a folder."""
    from cavenav.core.errors import ConfigError
    from cavenav.core.files import cannot_write

    if json_out is not None and json_out.is_dir():
        raise ConfigError(f"--json {json_out} is a folder: name the file to write")
    why = json_out and cannot_write(json_out)
    if why:
        raise ConfigError(f"cannot write {json_out}: {why}")
    if out is not None and out.exists() and not out.is_dir():
        raise ConfigError(f"cannot write {out}: it is no folder")


def _model_prices(given: list[str]) -> dict[str, tuple[float, float]]:
    """``--price MODEL=IN,OUT`` options as {model: (in, out)}."""
    prices = {}
    for text in given:
        model, _, pair = text.rpartition("=")
        price = VLMOptions(price=pair).prices() if model else None
        if price is None:
            raise CavenavError(f"--price takes MODEL=IN,OUT (USD per million tokens), got '{text}'")
        prices[model] = price
    return prices


def report(
    folder: Annotated[Path, typer.Argument(help="a sweep folder or a run folder")],
    price: Annotated[
        str | None,
        typer.Option(help="IN,OUT: USD per million tokens, to price the recorded tokens"),
    ] = None,
) -> None:
    """Write the static HTML report of a sweep (or of one run folder)."""
    from cavenav.evaluation.report import write_report

    prices = VLMOptions(price=price).prices()
    console.print(f"report: [bold]{write_report(folder, prices=prices)}[/]", soft_wrap=True)
