"""A vehicle over MAVLink: `fly` flies a pilot on an ArduSub vehicle (its own sensors, or a
simulated cave with --sim), and `fake-sub` simulates one to fly against."""

from __future__ import annotations

import contextlib
import math
import time
from collections.abc import Callable
from dataclasses import replace
from enum import StrEnum
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer

from cavenav.cli.common import (
    CAVE_SCENE_FILLED_BY_TAKES,
    FILLED_BY_TAKES,
    OWN_SENSORS_FILLED_BY_TAKES,
    VIEW_FILLED_BY_TAKES,
    VLM_FILLED_BY_TAKES,
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
from cavenav.cli.episode_flags import SETTINGS, VLM
from cavenav.cli.flags import finite, takes
from cavenav.cli.flights import fly_on_own_sensors, fly_vehicle
from cavenav.cli.output import console
from cavenav.cli.vehicle_flags import (
    CAVE_SCENE,
    LIVE_VIEW,
    OWN_SENSORS,
    CaveScene,
    LiveView,
    OwnSensors,
)
from cavenav.core.errors import CavenavError
from cavenav.episode.settings import EpisodeConfig
from cavenav.pilots.factory import PilotSpec, VLMOptions

if TYPE_CHECKING:  # pymavlink loads with it: only where the fake sub runs
    from cavenav.vehicle.fake_sub import FakeSubState


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
    start_depth: StartDepthOpt = None,
    out: RunsOut = Path("runs"),
    frames: FramesOpt = True,
    shield: Annotated[
        bool, typer.Option(help="safety shield between pilot and vehicle (on by default here)")
    ] = True,
    from_: FromOpt = None,
    policy: PolicyOpt = None,
    settings: EpisodeConfig = FILLED_BY_TAKES,
    vlm: VLMOptions = VLM_FILLED_BY_TAKES,
    view: LiveView = VIEW_FILLED_BY_TAKES,
    own: OwnSensors = OWN_SENSORS_FILLED_BY_TAKES,
) -> None:
    """Fly a pilot on an ArduSub vehicle over MAVLink (BlueROV2): on its own camera,
    sounders and depth model, or with --sim in a simulated cave."""
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
        typer.Option(min=0, callback=finite, help="start depth, m", show_default="30"),
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
        _serve_in_a_cave(settings, EpisodeConfig(), cave, _show_fake_sub)
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
    settings: EpisodeConfig,
    scene: CaveScene,
    show: Callable[[Any], None],
) -> None:
    """`fake-sub --scene`: the fake autopilot with its camera and sounders in a cave
    (`cavenav.sim.cave_sensors`), until Ctrl-C."""
    from cavenav.sim.cave_sensors import CaveSensors
    from cavenav.vehicle.fake_sub import FakeSub

    assert scene.scene is not None
    cave = built(settings, scene.scene, scene.cave_seed)
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
