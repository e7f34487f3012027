"""One episode at a time: `run`, `render`, `ask`, `view`, `video`, `scenarios` and `warmup`."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.markup import escape
from rich.table import Table

from cavenav.cli.common import (
    FramesOpt,
    FromOpt,
    PilotOpt,
    PolicyOpt,
    RunsOut,
    ScenarioArg,
    TeacherOpt,
    built,
    camera_for,
    check_view,
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
from cavenav.cli.flags import ExrCompression, bounded
from cavenav.cli.flights import fly_episode
from cavenav.cli.output import console, errors
from cavenav.cli.vehicle_flags import LIVE_VIEW, LiveView, RerunOpt, RerunSaveOpt
from cavenav.episode.settings import EpisodeConfig
from cavenav.pilots.factory import PilotSpec
from cavenav.pilots.replay import recorded_noise_seed, recorded_scenario


def run(
    scenario: ScenarioArg,
    pilot: PilotOpt = "geometric",
    seed: Annotated[
        int,
        typer.Option(
            min=0, help="seed of the procedural cave, the sensor noise and the random pilot"
        ),
    ] = 0,
    out: RunsOut = Path("runs"),
    frames: FramesOpt = True,
    exr_compression: Annotated[
        ExrCompression,
        typer.Option(
            help="depth EXR compression, all lossless: none (fastest; any reader), zip (a "
            "fifth smaller), or htj2k (two thirds smaller; readers need OpenEXR 3.4 or later)"
        ),
    ] = ExrCompression["none"],
    shield: Annotated[
        bool, typer.Option(help="safety shield between pilot and vehicle (cavenav.safety.shield)")
    ] = False,
    from_: FromOpt = None,
    policy: PolicyOpt = None,
    teacher: TeacherOpt = None,
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
    rerun: RerunOpt = LiveView.rerun,
    rerun_save: RerunSaveOpt = None,
) -> None:
    """Fly one episode and write its run folder (summary, steps, frames, plots)."""
    settings = SETTINGS.value(locals())
    vlm = VLM.value(locals())
    view = LIVE_VIEW.value(locals())
    from cavenav.episode.run_folder import new_run_dir, prepared_root

    check_view(view)
    spec = pilot_spec(pilot, vlm, from_, policy, teacher)
    if pilot == "replay":
        seed = _recorded_seed(scenario, str(from_), seed)
        if settings.seed is None:  # observations as the recording's were
            settings = replace(settings, seed=recorded_noise_seed(str(from_)))
    flyer = spec.build(seed=seed)  # a refused pilot or recording leaves no folder behind
    settings = replace(
        camera_for(spec, settings),
        save_frames=frames,
        exr_compression=exr_compression.value,  # type: ignore[arg-type]
        shield=shield,
    )
    # A folder that cannot be written is refused before the cave is built; one made here
    # for a cave that is refused (unknown, a start in rock) is removed again.
    with prepared_root(out):
        cave = built(settings, scenario, seed)
        config = settings.for_episode(cave, seed)
        console.print(
            f"[bold]{cave.name}[/]: {cave.description or cave.mesh.name} "
            f"({cave.mesh.triangle_count:,} triangles)"
        )
        run_dir = new_run_dir(out, cave.name, pilot, cave.seed)
        fly_episode(cave, flyer, config, run_dir, view=view)


def _recorded_seed(scenario: str, recording: str, seed: int) -> int:
    """The seed the replayed ``recording`` flew (``seed`` if it names none), with a note
    when it flew another scenario."""
    recorded, recorded_seed = recorded_scenario(recording)
    if recorded.casefold() != scenario.casefold() and Path(scenario).stem not in recorded:
        console.print(f"[yellow]note:[/] the recording flew {recorded}, replaying in {scenario}")
    return recorded_seed if recorded_seed is not None else seed


def render(
    scenario: ScenarioArg,
    seed: Annotated[int, typer.Option(min=0, help="seed of the procedural cave")] = 0,
    views: Annotated[int, typer.Option(min=1, max=24, help="poses along the passage")] = 6,
    out: Annotated[
        Path | None, typer.Option(help="PNG to write (default: render-SCENARIO-WATER.png)")
    ] = None,
    depth_max: DepthMaxOpt = EPISODE.sensors.depth_max_m,
    water: WaterOpt = None,
    light_power: LightPowerOpt = None,
    lamps: LampsOpt = None,
    lamp_lumens: LampLumensOpt = None,
    lamp_beam: LampBeamOpt = None,
    lamp_kelvin: LampKelvinOpt = None,
    daylight: DaylightOpt = None,
    particles: ParticlesOpt = None,
    noise: NoiseOpt = None,
    resolution: ResolutionOpt = None,
    sounder_resolution: SounderResolutionOpt = None,
    difficulty: DifficultyOpt = None,
    guideline: GuidelineOpt = EPISODE.guideline,
    guideline_colour: GuidelineColourOpt = None,
) -> None:
    """Write a contact sheet: colour and depth views from poses along the passage."""
    settings = SETTINGS.value(locals())
    from cavenav.episode.gallery import passage_poses, sheet_path, write_contact_sheet

    if out is not None:
        sheet_path(out)  # before the cave is built and rendered
    with console.status(f"building {scenario} (seed {seed})"):
        cave = settings.load(scenario, seed)
    sensors = settings.sensors_for(cave)
    path = out or sheet_path(f"render-{cave.name}-{sensors.optics.water_name}.png")
    with console.status(f"finding {views} poses along {cave.name}"):
        poses = passage_poses(cave, views)
    with console.status("rendering"):
        write_contact_sheet(cave, path, sensors, poses=poses)
    console.print(f"contact sheet: [bold]{path}[/]", soft_wrap=True)


def ask(
    image: Annotated[Path, typer.Argument(help="a colour photograph (PNG or JPEG)")],
    depth: Annotated[Path | None, typer.Option(help="a depth PNG (dark near, bright far)")] = None,
    top: Annotated[float | None, typer.Option(help="d_top: metres to the ceiling")] = None,
    bottom: Annotated[float | None, typer.Option(help="d_bottom: metres to the floor")] = None,
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
    prompt_file: PromptFileOpt = None,
    structured: StructuredOpt = MODEL.structured,
    image_format: ImageFormatOpt = MODEL.image_format,
    jpeg_quality: JpegQualityOpt = MODEL.jpeg_quality,
    image_size: ImageSizeOpt = None,
    device: DeviceOpt = MODEL.device,
) -> None:
    """Send one query for a single image (e.g. a photograph from a real cave).

    The photograph is turned upright and shrunk to what the model can use; without
    --depth the request carries no depth image and says so, and a missing --top or
    --bottom is sent as "unknown".
    """
    vlm = VLM.value(locals())
    from cavenav.motion.actions import to_twist
    from cavenav.pilots.photo import load_photo

    # The images first: a bad one is refused before the endpoint is contacted.
    observation, notes = load_photo(image, depth, d_top=top, d_bottom=bottom, detail=vlm.detail)
    for note in notes:
        console.print(f"[yellow]note:[/] {escape(note)}", soft_wrap=True)
    pilot = PilotSpec("vlm", replace(vlm, history=0)).build()  # one image, no history
    decision = pilot.decide(observation)
    console.rule("reasoning")
    console.print(decision.raw, markup=False, highlight=False)
    console.rule("parsed action")
    console.print(f"action:        {decision.action_text}", markup=False)
    console.print(f"justification: {decision.justification}", markup=False)
    console.print(f"twist:         {to_twist(decision.action)}", markup=False)


def view(
    run_folder: Annotated[Path, typer.Argument(help="a run folder (cavenav run, eval or fly)")],
    save: Annotated[
        Path | None, typer.Option(help="write the recording to this .rrd file, open no viewer")
    ] = None,
    scenario: Annotated[
        str | None,
        typer.Option(help="the cave flown, for a scenario file (a family's is rebuilt)"),
    ] = None,
) -> None:
    """Show a recorded episode in Rerun: the cave, the path, the frames kept, the sounders
    and every decision, on a step timeline (pip install -e '.[rerun]')."""
    from cavenav.episode.records import read_steps, read_summary
    from cavenav.episode.rerun_log import log_run_folder, open_recording

    summary = read_summary(run_folder / "summary.json")
    steps = read_steps(run_folder / "steps.jsonl")
    cave = _recorded_cave(summary, scenario)
    recording = open_recording(run_folder.name, live=save is None, save=save)
    log_run_folder(recording, run_folder, summary, steps, cave)
    if save is not None:
        console.print(f"rerun: [bold]{save}[/]", soft_wrap=True)


def _recorded_cave(summary: dict[str, Any], scenario: str | None) -> Any:  # noqa: ANN401
    """The cave a run folder's episode flew: ``scenario`` where given, else the family's
    cave of its seed and difficulty; None for a scenario file not given (said so)."""
    from cavenav.world.scenarios import SCENARIOS

    name = scenario or summary.get("scenario")
    if scenario is None and name not in SCENARIOS:
        errors.print(f"no cave shown: give the scenario file it flew with --scenario ({name})")
        return None
    settings = EpisodeConfig(difficulty=summary.get("difficulty") or {})
    return settings.load(str(name), int(summary.get("seed") or 0))


def video(
    run_dir: Annotated[Path, typer.Argument(help="a run folder flown with frames")],
    out: Annotated[
        Path | None, typer.Option(help="MP4 to write (default: RUN/episode.mp4)")
    ] = None,
    fps: Annotated[
        float, typer.Option(callback=bounded(0.5, 60), help="steps per second, 0.5 to 60")
    ] = 4.0,
) -> None:
    """Write an MP4 of an episode: RGB, depth and the top-down map, side by side."""
    from cavenav.episode.video import write_video

    with console.status("encoding"):
        path = write_video(run_dir, out, fps)
    console.print(f"video: [bold]{path}[/]", soft_wrap=True)


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


def warmup() -> None:
    """Compile the sensor and pilot kernels into numba's cache (once per machine; make setup
    runs it)."""
    from cavenav.episode.warmup import warm_up

    with console.status("loading the kernels (the first time on a machine: compiling)"):
        seconds = warm_up()
    console.print(f"sensor and pilot kernels ready ({seconds:.1f} s)")
