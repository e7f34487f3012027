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
cavenav dataset SWEEP --out DIR        flights as training data for a VLM (Hugging Face)
cavenav finetune DATA --new small      train a VLM pilot on it (or --base MODEL_DIR)

The options several commands share (the VLM pilot's, the episode's, the sensors' and
optics') are declared once in `cavenav.cli_options`; `cavenav.cli_flights` flies with a
progress bar and handles Ctrl-C; `cavenav.cli_output` prints the tables.
"""

from __future__ import annotations

import contextlib
import errno
import math
import os
import sys
import time
import warnings
from collections.abc import Callable
from dataclasses import replace
from enum import StrEnum
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer
from rich.markup import escape
from rich.table import Table

from cavenav.cli_flights import fly_episode, fly_on_own_sensors, fly_sweep, fly_vehicle
from cavenav.cli_options import (
    CAVE_SCENE,
    LIVE_VIEW,
    OWN_SENSORS,
    SETTINGS,
    VLM,
    CaveScene,
    ExrCompression,
    LiveView,
    OwnSensors,
    bounded,
    finite,
    takes,
)
from cavenav.cli_output import (
    console,
    errors,
    print_comparison,
    print_groups,
    print_leaderboard,
)
from cavenav.cli_training import dataset, finetune
from cavenav.episode.settings import FRAME_MODES, VIDEO_MODES, EpisodeSettings
from cavenav.errors import CavenavError
from cavenav.pilots.factory import PilotSpec, VLMOptions
from cavenav.pilots.replay import recorded_noise_seed, recorded_scenario
from cavenav.redaction import redact
from cavenav.types import STEP_BUDGET

if TYPE_CHECKING:  # pymavlink loads with it: only where the fake sub runs
    from cavenav.vehicle.fake_sub import FakeSubState

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    help="cavenav: VLM-steered navigation of an underwater vehicle through unseen caves.",
)
app.command()(dataset)
app.command()(finetune)


ScenarioArg = Annotated[
    str, typer.Argument(help="a family (S1..S5, crawl, maze, long) or a scenario .toml file")
]
PilotOpt = Annotated[str, typer.Option(help="pilot to fly: geometric, vlm, replay, random, policy")]
RunsOut = Annotated[Path, typer.Option(help="folder that receives the run folder")]
FramesOpt = Annotated[bool, typer.Option(help="save RGB, depth PNG and EXR of every step")]
FromOpt = Annotated[Path | None, typer.Option("--from", help="run folder to replay")]
PolicyOpt = Annotated[
    Path | None,
    typer.Option(
        help="model file the policy pilot flies (Stable-Baselines3 .zip; --resolution follows it)"
    ),
]
TeacherOpt = Annotated[
    str | None,
    typer.Option(
        help="a pilot (geometric, random) that decides alongside at every step, recorded "
        "as the step's teacher label for `cavenav dataset --labels teacher` (DAgger)"
    ),
]
# Placeholder defaults: `takes` puts each group's flags in their place and passes the
# value built from them (`cavenav.cli_options`), so a command never sees these.
FILLED_BY_TAKES, VLM_FILLED_BY_TAKES, VIEW_FILLED_BY_TAKES = (
    EpisodeSettings(),
    VLMOptions(),
    LiveView(),
)
OWN_SENSORS_FILLED_BY_TAKES, CAVE_SCENE_FILLED_BY_TAKES = OwnSensors(), CaveScene()


@app.command()
@takes(settings=SETTINGS, vlm=VLM, view=LIVE_VIEW)
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
        bool, typer.Option(help="safety shield between pilot and vehicle (cavenav.shield)")
    ] = False,
    from_: FromOpt = None,
    policy: PolicyOpt = None,
    teacher: TeacherOpt = None,
    settings: EpisodeSettings = FILLED_BY_TAKES,
    vlm: VLMOptions = VLM_FILLED_BY_TAKES,
    view: LiveView = VIEW_FILLED_BY_TAKES,
) -> None:
    """Fly one episode and write its run folder (summary, steps, frames, plots)."""
    from cavenav.episode.run_folder import new_run_dir, prepared_root

    _check_view(view)
    spec = _pilot_spec(pilot, vlm, from_, policy, teacher)
    if pilot == "replay":
        seed = _recorded_seed(scenario, str(from_), seed)
        if settings.noise_seed is None:  # observations as the recording's were
            settings = replace(settings, noise_seed=recorded_noise_seed(str(from_)))
    flyer = spec.build(seed=seed)  # a refused pilot or recording leaves no folder behind
    settings = replace(
        _camera_for(spec, settings),
        save_frames=frames,
        exr_compression=exr_compression.value,
        shield=shield,
    )
    # A folder that cannot be written is refused before the cave is built; one made here
    # for a cave that is refused (unknown, a start in rock) is removed again.
    with prepared_root(out):
        cave = _built(settings, scenario, seed)
        config = settings.episode_config(cave, seed)
        console.print(
            f"[bold]{cave.name}[/]: {cave.description or cave.mesh.name} "
            f"({cave.mesh.triangle_count:,} triangles)"
        )
        run_dir = new_run_dir(out, cave.name, pilot, cave.seed)
        fly_episode(cave, flyer, config, run_dir, view=view)


def _check_view(view: LiveView) -> None:
    """A Rerun recording's file checked first, before a pilot, a cave or a vehicle."""
    if view.rerun_save:
        from cavenav.episode.rerun_log import check_recording_path

        check_recording_path(Path(view.rerun_save))


def _built(settings: EpisodeSettings, scenario: str, seed: int) -> Any:  # noqa: ANN401
    """The cave ``scenario`` of ``seed``, built under a status line (a large mesh takes a
    while)."""
    with console.status(f"building {scenario} (seed {seed})"):
        return settings.load(scenario, seed)


def _pilot_spec(
    pilot: str,
    vlm: VLMOptions,
    from_: Path | None,
    policy: Path | None,
    teacher: str | None = None,
) -> PilotSpec:
    return PilotSpec(
        pilot,
        vlm.for_model(),  # a model folder cavenav finetune wrote: asked as it learned
        recording=str(from_) if from_ else None,
        policy=str(policy.absolute()) if policy else None,  # as workers elsewhere find it
        teacher=teacher,
    )


def _camera_for(spec: PilotSpec, settings: EpisodeSettings) -> EpisodeSettings:
    """``settings`` with the camera size a pilot trained at one size needs (a policy):
    set when --resolution was not given, refused when it names another size."""
    size = spec.image_size()
    if size is None or settings.resolution == size:
        return settings
    if settings.resolution is not None:
        given, wanted = (f"{w}x{h}" for w, h in (settings.resolution, size))
        raise CavenavError(
            f"--resolution {given}: the policy {spec.policy} was trained on {wanted} images; "
            f"leave --resolution out or give {wanted}"
        )
    console.print(f"[yellow]note:[/] the camera is {size[0]}x{size[1]}, as the policy saw it")
    return replace(settings, resolution=size)


def _recorded_seed(scenario: str, recording: str, seed: int) -> int:
    """The seed the replayed ``recording`` flew (``seed`` if it names none), with a note
    when it flew another scenario."""
    recorded, recorded_seed = recorded_scenario(recording)
    if recorded.casefold() != scenario.casefold() and Path(scenario).stem not in recorded:
        console.print(f"[yellow]note:[/] the recording flew {recorded}, replaying in {scenario}")
    return recorded_seed if recorded_seed is not None else seed


@app.command()
@takes(
    settings=SETTINGS.only(
        "depth_max", "water", "light_power", "lamps", "lamp_lumens", "lamp_beam", "lamp_kelvin",
        "daylight", "particles", "noise",
        "resolution", "sounder_resolution", "difficulty",
    )
)  # fmt: skip
def render(
    scenario: ScenarioArg,
    seed: Annotated[int, typer.Option(min=0, help="seed of the procedural cave")] = 0,
    views: Annotated[int, typer.Option(min=1, max=24, help="poses along the passage")] = 6,
    out: Annotated[
        Path | None, typer.Option(help="PNG to write (default: render-SCENARIO-WATER.png)")
    ] = None,
    settings: EpisodeSettings = FILLED_BY_TAKES,
) -> None:
    """Write a contact sheet: colour and depth views from poses along the passage."""
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


@app.command()
@takes(vlm=VLM.without("history", "map_image", "energy_prompt", "price", "cache"))
def ask(
    image: Annotated[Path, typer.Argument(help="a colour photograph (PNG or JPEG)")],
    depth: Annotated[Path | None, typer.Option(help="a depth PNG (dark near, bright far)")] = None,
    top: Annotated[float | None, typer.Option(help="d_top: metres to the ceiling")] = None,
    bottom: Annotated[float | None, typer.Option(help="d_bottom: metres to the floor")] = None,
    vlm: VLMOptions = VLM_FILLED_BY_TAKES,
) -> None:
    """Send one query for a single image (e.g. a photograph from a real cave).

    The photograph is turned upright and shrunk to what the model can use; without
    --depth the request carries no depth image and says so, and a missing --top or
    --bottom is sent as "unknown".
    """
    from cavenav.actions import to_twist
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


@app.command("eval")
@takes(settings=SETTINGS, vlm=VLM)
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
    settings: EpisodeSettings = FILLED_BY_TAKES,
    vlm: VLMOptions = VLM_FILLED_BY_TAKES,
) -> None:
    """Fly a pilot over scenarios x seeds (x trials); results.csv, aggregate.json, a report."""
    from cavenav.episode.run_folder import prepare_root
    from cavenav.evaluation.sweep import SweepConfig, check_grid, parse_seeds

    if pilot == "replay":
        raise CavenavError("a sweep flies geometric, vlm, random or policy pilots, not replay")
    spec = _pilot_spec(pilot, vlm, None, policy, teacher)
    settings = replace(_camera_for(spec, settings), shield=shield).with_frames(frames.value)
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


def _sweep_flown(out: Path, rows: list[dict], report: bool, log: Any) -> None:  # noqa: ANN401
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


@app.command()
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
    from cavenav.episode.run_folder import write_json
    from cavenav.errors import RecordingError
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
    from cavenav.errors import ConfigError
    from cavenav.files import cannot_write

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


@app.command()
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
    settings = EpisodeSettings(difficulty=summary.get("difficulty") or {})
    return settings.load(str(name), int(summary.get("seed") or 0))


@app.command()
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


@app.command()
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


class FlyMode(StrEnum):
    """How the bridge drives an ArduSub vehicle (`cavenav.vehicle.mavlink`)."""

    manual = "manual"
    guided = "guided"


@app.command()
@takes(settings=SETTINGS, vlm=VLM, view=LIVE_VIEW, own=OWN_SENSORS)
def fly(
    connect: Annotated[
        str | None,
        typer.Option(help="MAVLink address of the vehicle (default udpin:0.0.0.0:14550)"),
    ] = None,
    pilot: PilotOpt = "geometric",
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
    out: RunsOut = Path("runs"),
    frames: FramesOpt = True,
    shield: Annotated[
        bool, typer.Option(help="safety shield between pilot and vehicle (on by default here)")
    ] = True,
    from_: FromOpt = None,
    policy: PolicyOpt = None,
    settings: EpisodeSettings = FILLED_BY_TAKES,
    vlm: VLMOptions = VLM_FILLED_BY_TAKES,
    view: LiveView = VIEW_FILLED_BY_TAKES,
    own: OwnSensors = OWN_SENSORS_FILLED_BY_TAKES,
) -> None:
    """Fly a pilot on an ArduSub vehicle over MAVLink (BlueROV2): on its own camera,
    sounders and depth model, or with --sim in a simulated cave."""
    from cavenav.vehicle.mavlink import load_bridge_config

    _check_view(view)
    bridge = load_bridge_config(config, connect=connect, mode=mode.value if mode else None)
    if dry_run:
        _print_dry_run(bridge, action or [])
        return
    spec = _pilot_spec(pilot, vlm, from_, policy)
    settings = replace(settings, save_frames=frames, shield=shield)
    confirm = None if yes else typer.confirm
    if sim is None:
        _fly_own_sensors(bridge, spec, own, settings, view, out, confirm)
    else:
        _fly_in_a_simulated_cave(bridge, spec, (sim, seed), settings, view, out, confirm)


def _fly_in_a_simulated_cave(
    bridge: Any,  # noqa: ANN401
    spec: PilotSpec,
    cave_and_seed: tuple[str, int],
    settings: EpisodeSettings,
    view: LiveView,
    out: Path,
    confirm: Callable[[str], bool] | None,
) -> None:
    """`fly --sim`: each observation rendered where the vehicle reports it is."""
    from cavenav.episode.run_folder import new_run_dir, prepare_root

    scenario, seed = cave_and_seed
    flyer = spec.build(seed=seed)
    settings = _on_a_vehicle(settings, spec)
    prepare_root(out)
    cave = _built(settings, scenario, seed)
    if not settings.current_for(cave).still:  # the scenario file's [water]
        console.print(f"[yellow]note:[/] {cave.name}'s [water] is not simulated: a vehicle "
                      "over MAVLink meets its own water", soft_wrap=True)  # fmt: skip
        settings = replace(settings, discharge_m3s=0.0)
    run_dir = new_run_dir(out, cave.name, spec.name, cave.seed)
    fly_vehicle(bridge, cave, flyer, settings.episode_config(cave, seed), run_dir, confirm, view)


def _fly_own_sensors(
    bridge: Any,  # noqa: ANN401
    spec: PilotSpec,
    own: OwnSensors,
    settings: EpisodeSettings,
    view: LiveView,
    out: Path,
    confirm: Callable[[str], bool] | None,
) -> None:
    """`fly` without --sim: the pilot on the vehicle's own sensors (`fly_on_own_sensors`)."""
    if view.wanted or settings.battery_wh is not None:
        raise CavenavError(
            "--rerun, --rerun-save and --battery-wh need --sim: a vehicle on its own "
            "sensors has no cave model to show, and reports its own battery"
        )
    from cavenav.episode.on_vehicle import Flight
    from cavenav.episode.run_folder import new_run_dir, prepare_root
    from cavenav.vehicle.camera import CameraAddress
    from cavenav.vehicle.ping import PingAddress

    camera = CameraAddress.parse(own.camera)  # refused before any folder or connection
    for sounder in (own.ping_up, own.ping_down):
        if sounder:
            PingAddress.parse(sounder)

    if spec.name in ("geometric", "policy") and own.depth_model is None:
        raise CavenavError(
            f"the {spec.name} pilot steers by the depth image: give --depth-model FOLDER "
            "(a metric monocular depth model), or fly --pilot vlm, which is told it has none"
        )
    if not settings.shield and own.depth_model is None:
        raise CavenavError(
            "--no-shield without --depth-model would fly turns and horizontal moves into "
            "water nothing has seen: keep the shield (it lets vertical moves fly) or give one"
        )
    settings = _on_a_vehicle(settings, spec)
    vehicle = {
        "connect": bridge.connect, "mode": bridge.mode, "camera": str(camera),
        "camera_hfov_deg": own.camera_hfov, "camera_latency_s": own.camera_latency,
        "ping_up": own.ping_up, "ping_down": own.ping_down,
        "depth_model": own.depth_model,
    }  # fmt: skip
    flight = Flight(settings.steps or STEP_BUDGET, settings.shield, settings.save_frames, vehicle)
    flyer = spec.build(seed=0)
    prepare_root(out)
    size = settings.resolution or (640, 480)
    run_dir = partial(new_run_dir, out, "vehicle", spec.name, None)
    fly_on_own_sensors(bridge, flyer, flight, (own, size), run_dir, confirm)


def _on_a_vehicle(settings: EpisodeSettings, spec: PilotSpec) -> EpisodeSettings:
    """``settings`` for ``spec``'s pilot on a vehicle over MAVLink (`_camera_for`); the
    vehicle meets its own water, so a simulated current is refused before connecting."""
    if settings.flowing:
        raise CavenavError(
            "--discharge: a vehicle over MAVLink meets its own water; "
            "simulate one with `cavenav fake-sub --current`"
        )
    return _camera_for(spec, settings)


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
@takes(cave=CAVE_SCENE)
def fake_sub(
    # Flags left out keep FakeSubConfig's defaults, which their help repeats (a test checks).
    connect: Annotated[
        str | None,
        typer.Option(
            help="where to send (the bridge listens there with udpin)",
            show_default="udpout:127.0.0.1:14550",
        ),
    ] = None,
    noise: Annotated[
        float | None,
        typer.Option(
            min=0, callback=finite, help="execution noise (relative gain error)", show_default="0"
        ),
    ] = None,
    current: Annotated[
        str, typer.Option(metavar="N,E,D", help="water current, m/s north, east, down")
    ] = "0,0,0",
    depth: Annotated[
        float | None,
        typer.Option(min=0, callback=finite, help="start depth, m", show_default="5"),
    ] = None,
    position: Annotated[
        bool, typer.Option(help="report LOCAL_POSITION_NED and allow GUIDED (a DVL)")
    ] = True,
    pilot_timeout: Annotated[
        float | None,
        typer.Option(min=0.1, callback=finite, help="FS_PILOT_TIMEOUT, seconds", show_default="3"),
    ] = None,
    seed: Annotated[
        int | None, typer.Option(min=0, help="seed of the execution noise", show_default="0")
    ] = None,
    cave: CaveScene = CAVE_SCENE_FILLED_BY_TAKES,
) -> None:
    """A simulated ArduSub autopilot on MAVLink, for `cavenav fly` with no vehicle; with
    --scene, its camera and sounders too, rendered in a cave."""
    from cavenav.vehicle.fake_sub import FakeSubConfig, serve

    given = {
        "address": connect,
        "noise": noise,
        "start_ned": None if depth is None else (0.0, 0.0, depth),
        "pilot_timeout_s": pilot_timeout,
        "seed": seed,
    }
    settings = FakeSubConfig(
        current_ned_mps=_current_ned(current),
        position_estimate=position,
        **{key: value for key, value in given.items() if value is not None},
    )

    if cave.scene is not None:
        _serve_in_a_cave(settings, EpisodeSettings(), cave, _show_fake_sub)
        return
    console.print(f"fake ArduSub sending to {settings.address}; Ctrl-C stops it")
    with contextlib.suppress(KeyboardInterrupt):
        serve(settings, on_state=_show_fake_sub)


def _show_fake_sub(state: FakeSubState) -> None:
    """One line of the fake autopilot's state, as it changes."""
    console.print(
        f"{'ARMED' if state.armed else 'disarmed':8} {state.mode_name:8} "
        f"N {state.north:7.2f}  E {state.east:7.2f}  depth {state.down:6.2f}  "
        f"yaw {state.yaw_deg:7.1f}  sticks {state.sticks}"
        + ("  [red]pilot-input failsafe[/]" if state.failsafe else ""),
        highlight=False,
        soft_wrap=True,
    )


def _current_ned(current: str) -> tuple[float, ...]:
    """``--current N,E,D``: the water's velocity, m/s north, east and down."""
    try:
        drift = tuple(float(v) for v in current.split(","))
    except ValueError:
        drift = ()
    if len(drift) != 3 or not all(map(math.isfinite, drift)):
        raise typer.BadParameter(
            f"{current!r}: give three numbers N,E,D in m/s", param_hint="--current"
        )
    return drift


def _serve_in_a_cave(
    config: Any,  # noqa: ANN401 - lazy imports
    settings: EpisodeSettings,
    scene: CaveScene,
    show: Callable[[Any], None],
) -> None:
    """`fake-sub --scene`: the fake autopilot with its camera and sounders in a cave
    (`cavenav.cave_sensors`), until Ctrl-C."""
    from cavenav.cave_sensors import CaveSensors
    from cavenav.vehicle.fake_sub import FakeSub

    assert scene.scene is not None
    cave = _built(settings, scene.scene, scene.cave_seed)
    pings = (scene.ping_up_port, scene.ping_down_port)
    with FakeSub(config) as sub, CaveSensors(
        sub, cave, settings.sensors_for(cave), scene.camera_port, pings
    ) as sensors:  # fmt: skip
        console.print(
            f"fake ArduSub in {cave.name} sending to {config.address}; camera "
            f"udp:{scene.camera_port} "
            f"(RTP H.264), sounders {sensors.up.address} (up) and {sensors.down.address} "
            "(down); Ctrl-C stops it",
            soft_wrap=True,
            highlight=False,
        )
        with contextlib.suppress(KeyboardInterrupt):
            while True:
                time.sleep(1.0)
                show(sub.state())
                clearance = sensors.clearance_m()
                where = "[red]inside rock[/]" if clearance < 0 else f"clearance {clearance:.2f} m"
                console.print(f"         {where}", highlight=False)


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
    except OSError as exc:
        if exc.errno != errno.ENAMETOOLONG:
            raise
        # A path given (--out, a scenario file) that no file system takes: bad input,
        # met where the path is first looked at, before anything is written.
        name = str(exc.filename or "")
        shown = name if len(name) <= 80 else f"{name[:40]}...{name[-37:]}"
        errors.print(f"error: a path is too long for the file system: {escape(shown)}")
        sys.exit(2)


def _show_warning(message: Warning | str, category: type[Warning], *_: Any, **__: Any) -> None:
    """Our warnings (a mesh in centimetres, ...) as one line; others as Python prints them."""
    from cavenav.errors import CavenavWarning

    if issubclass(category, CavenavWarning):
        errors.print(f"[yellow]warning:[/] {escape(str(message))}", highlight=False)
    else:
        errors.print(f"{category.__name__}: {escape(str(message))}", highlight=False)


if __name__ == "__main__":
    main()
