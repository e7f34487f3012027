"""`fake-sub`: a simulated ArduSub autopilot on MAVLink to fly `cavenav fly` against, with
no vehicle; with --scene, its camera and sounders too, rendered in a cave."""

from __future__ import annotations

import contextlib
import math
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Annotated, Any

import typer

from cavenav.cli.common import built
from cavenav.cli.episode_flags import GuidelineColourOpt, GuidelineOpt
from cavenav.cli.flags import finite
from cavenav.cli.output import console
from cavenav.cli.vehicle_flags import (
    CAVE_SCENE,
    SCENE,
    CameraPortOpt,
    CaveScene,
    CaveSeedOpt,
    DvlPortOpt,
    PingDownPortOpt,
    PingUpPortOpt,
    SceneOpt,
    SonarPortOpt,
)
from cavenav.episode.settings import EpisodeConfig

if TYPE_CHECKING:  # pymavlink loads with it: only where the fake sub runs
    from cavenav.vehicle.fake_sub import FakeSubState

__all__ = ["fake_sub"]


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
    scene: SceneOpt = None,
    cave_seed: CaveSeedOpt = SCENE.cave_seed,
    camera_port: CameraPortOpt = SCENE.camera_port,
    ping_up_port: PingUpPortOpt = SCENE.ping_up_port,
    ping_down_port: PingDownPortOpt = SCENE.ping_down_port,
    sonar_port: SonarPortOpt = SCENE.sonar_port,
    dvl_port: DvlPortOpt = SCENE.dvl_port,
    guideline: GuidelineOpt = None,
    guideline_colour: GuidelineColourOpt = None,
) -> None:
    """A simulated ArduSub autopilot on MAVLink, for `cavenav fly` with no vehicle; with
    --scene, its camera and sounders too, rendered in a cave."""
    cave = CAVE_SCENE.value(locals())
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
        lined = EpisodeConfig(guideline=guideline, guideline_colour=guideline_colour)
        _serve_in_a_cave(settings, lined, cave, _show_fake_sub)
        return
    if guideline or guideline_colour:
        raise typer.BadParameter("the guideline is drawn by the camera of a cave: give --scene")
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
        sub, cave, settings.sensors_for(cave), scene.camera_port, pings,
        sonar_port=scene.sonar_port, dvl_port=scene.dvl_port,
    ) as sensors:  # fmt: skip
        acoustic = "".join(
            f", {what} {device.address}"
            for what, device in (("Ping360", sensors.sonar), ("DVL", sensors.dvl))
            if device is not None
        )
        console.print(
            f"fake ArduSub in {cave.name} sending to {config.address}; camera "
            f"udp:{scene.camera_port} "
            f"(RTP H.264), sounders {sensors.up.address} (up) and {sensors.down.address} "
            f"(down){acoustic}; Ctrl-C stops it",
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
