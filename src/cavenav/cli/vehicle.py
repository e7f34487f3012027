"""A vehicle over MAVLink: `fly` flies a pilot on an ArduSub vehicle (its own sensors, or a
simulated cave with --sim); `cavenav.cli.fake_sub` simulates one to fly against."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from enum import StrEnum
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer

from cavenav.cli.common import (
    FramesOpt,
    FromOpt,
    PilotOpt,
    PolicyOpt,
    RunsOut,
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
    DesignOpt,
    DetailOpt,
    DeviceOpt,
    DifficultyOpt,
    DischargeOpt,
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
    SounderOpt,
    SounderResolutionOpt,
    StepsOpt,
    StructuredOpt,
    StuckAfterOpt,
    TemperatureOpt,
    TimeoutOpt,
    WaterOpt,
)
from cavenav.cli.flags import finite
from cavenav.cli.flights import fly_on_own_sensors, fly_vehicle
from cavenav.cli.output import console
from cavenav.cli.vehicle_flags import (
    LIVE_VIEW,
    OWN,
    OWN_SENSORS,
    CameraHfovOpt,
    CameraLatencyOpt,
    CameraOpt,
    DepthModelOpt,
    LiveView,
    OwnDvlOpt,
    OwnSensors,
    OwnSonarOpt,
    PingDownOpt,
    PingUpOpt,
    RerunOpt,
    RerunSaveOpt,
)
from cavenav.core.errors import CavenavError
from cavenav.episode.settings import EpisodeConfig
from cavenav.pilots.factory import PilotSpec

if TYPE_CHECKING:  # pymavlink loads with it: only where the fake sub runs
    pass


class FlyMode(StrEnum):
    """How the bridge drives an ArduSub vehicle (`cavenav.vehicle.mavlink`)."""

    manual = "manual"
    guided = "guided"


StartDepthOpt = Annotated[
    float | None,
    typer.Option(
        min=0,
        callback=finite,
        help="dive (or rise) to this depth, m, before the first step; with --sim the "
        "default leaves room above for the cave's highest point",
    ),
]


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
    start_depth: StartDepthOpt = None,
    out: RunsOut = Path("runs"),
    frames: FramesOpt = True,
    shield: Annotated[
        bool, typer.Option(help="safety shield between pilot and vehicle (on by default here)")
    ] = True,
    from_: FromOpt = None,
    policy: PolicyOpt = None,
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
    camera: CameraOpt = OWN.camera,
    camera_hfov: CameraHfovOpt = OWN.camera_hfov,
    camera_latency: CameraLatencyOpt = OWN.camera_latency,
    ping_up: PingUpOpt = None,
    ping_down: PingDownOpt = None,
    depth_model: DepthModelOpt = None,
    sonar_address: OwnSonarOpt = None,
    dvl_address: OwnDvlOpt = None,
) -> None:
    """Fly a pilot on an ArduSub vehicle over MAVLink (BlueROV2): on its own camera,
    sounders and depth model, or with --sim in a simulated cave."""
    settings = SETTINGS.value(locals())
    vlm = VLM.value(locals())
    view = LIVE_VIEW.value(locals())
    own = OWN_SENSORS.value(locals())
    from cavenav.vehicle.mavlink import load_bridge_config

    check_view(view)
    bridge = load_bridge_config(
        config, connect=connect, mode=mode.value if mode else None, start_depth_m=start_depth
    )
    if dry_run:
        _print_dry_run(bridge, action or [])
        return
    spec = pilot_spec(pilot, vlm, from_, policy)
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
    settings: EpisodeConfig,
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
    cave = built(settings, scenario, seed)
    if not settings.current_for(cave).still:  # the scenario file's [water]
        console.print(f"[yellow]note:[/] {cave.name}'s [water] is not simulated: a vehicle "
                      "over MAVLink meets its own water", soft_wrap=True)  # fmt: skip
        settings = replace(settings, discharge_m3s=0.0)
    bridge = _room_above(bridge, cave)
    run_dir = new_run_dir(out, cave.name, spec.name, cave.seed)
    fly_vehicle(bridge, cave, flyer, settings.for_episode(cave, seed), run_dir, confirm, view)


def _room_above(bridge: Any, cave: Any) -> Any:  # noqa: ANN401 - lazy imports
    """``bridge`` with a start depth that leaves room above for the cave's highest point
    (as deep below the shallowest allowed depth as the cave rises above its start), where
    none was given: from a shallower start the depth limit would cut every ascent."""
    from cavenav.vehicle.mavlink import START_MARGIN_M

    if bridge.start_depth_m is not None:
        return bridge
    rise = max(float(cave.mesh.bounds[1][2] - cave.start.z), 0.0)
    depth = round(bridge.min_depth_m + rise + START_MARGIN_M, 2)
    if depth > bridge.max_depth_m:
        raise CavenavError(
            f"{cave.name} rises {rise:.1f} m above its start: starting {depth:.1f} m deep is "
            f"beyond max_depth_m ({bridge.max_depth_m:g} m); give --start-depth or a deeper limit"
        )
    return bridge.model_copy(update={"start_depth_m": depth})


def _fly_own_sensors(
    bridge: Any,  # noqa: ANN401
    spec: PilotSpec,
    own: OwnSensors,
    settings: EpisodeConfig,
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
    for sounder in (own.ping_up, own.ping_down, own.sonar_address):
        if sounder:
            PingAddress.parse(sounder)
    if own.dvl_address:
        from cavenav.vehicle.waterlinked import DvlAddress

        DvlAddress.parse(own.dvl_address)

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
        "depth_model": own.depth_model, "sonar": own.sonar_address, "dvl": own.dvl_address,
    }  # fmt: skip
    flight = Flight(settings, vehicle)
    flyer = spec.build(seed=0)
    prepare_root(out)
    size = settings.resolution or settings.sensors.resolution
    run_dir = partial(new_run_dir, out, "vehicle", spec.name, None)
    fly_on_own_sensors(bridge, flyer, flight, (own, size), run_dir, confirm)


def _on_a_vehicle(settings: EpisodeConfig, spec: PilotSpec) -> EpisodeConfig:
    """``settings`` for ``spec``'s pilot on a vehicle over MAVLink (`camera_for`); the
    vehicle meets its own water, so a simulated current is refused before connecting."""
    if settings.flowing:
        raise CavenavError(
            "--discharge: a vehicle over MAVLink meets its own water; "
            "simulate one with `cavenav fake-sub --current`"
        )
    return camera_for(spec, settings)


def _print_dry_run(bridge: Any, actions: list[str]) -> None:  # noqa: ANN401
    from cavenav.motion.actions import format_action, parse_action
    from cavenav.vehicle.mavlink import describe, plan

    if not actions:
        raise typer.BadParameter("give the action to describe, e.g. --action 'forward 0.5 m'")
    for text in actions:
        command = parse_action(text)
        console.print(f"[bold]{format_action(command)}[/] ({bridge.mode} mode):")
        for line in describe(plan(command, bridge), bridge):
            console.print(f"  {line}", soft_wrap=True, highlight=False)
