"""The options of where an episode is shown (`LiveView`), of a vehicle's own sensors
(`OwnSensors`) and of the fake sub's cave (`CaveScene`), each declared once as a typer
``Annotated`` type that a command names in its signature; `LIVE_VIEW`, `OWN_SENSORS` and
`CAVE_SCENE` build the values from a command's arguments (`cavenav.cli.flags.Group`)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import typer

from cavenav.cli.flags import Group, bounded, finite, ranged

__all__ = ["CAVE_SCENE", "LIVE_VIEW", "OWN_SENSORS", "CaveScene", "LiveView", "OwnSensors"]


@dataclass(frozen=True)
class LiveView:
    """Where an episode is shown as it flies, in Rerun (`cavenav.episode.rerun_log`).

    Attributes:
        rerun: spawn a live Rerun viewer.
        rerun_save: write the recording to this .rrd file.
    """

    rerun: bool = False
    rerun_save: str | None = None

    @property
    def wanted(self) -> bool:
        return self.rerun or self.rerun_save is not None


# `run` and `fly`: a live 3D view of the episode.
RerunOpt = Annotated[
    bool,
    typer.Option(
        "--rerun",
        help="show the episode live in a Rerun viewer: cave, path, camera, depth, sounders, "
        "map and each decision (pip install -e '.[rerun]')",
    ),
]
RerunSaveOpt = Annotated[
    Path | None, typer.Option(help="write the Rerun recording to this .rrd file")
]
LIVE_VIEW = Group(
    (
        "rerun",
        "rerun_save",
    ),
    LiveView,
)


@dataclass(frozen=True)
class OwnSensors:
    """A vehicle's own sensors, for `cavenav fly` without --sim (`cavenav.episode.on_vehicle`).

    Attributes:
        camera: the video stream (`cavenav.vehicle.camera.CameraAddress`).
        camera_hfov: the camera's horizontal field of view in water, degrees.
        camera_latency: seconds from the camera's sensor to a decoded frame.
        ping_up, ping_down: the sounders' addresses (`cavenav.vehicle.ping.PingAddress`);
            None: not fitted.
        depth_model: the folder of a metric monocular depth model; None: no depth image.
        sonar_address: a Ping360's address (`cavenav.vehicle.ping360`), ``--sonar``;
            None: not fitted. (Named apart from the episode's ``sonar``, the kind a
            simulated vehicle carries, which `fly --sim` takes from the scenario.)
        dvl_address: a Water Linked DVL's address (`cavenav.vehicle.waterlinked`),
            ``--dvl``; None: not fitted.
    """

    camera: str = "udp:5600"
    camera_hfov: float = 53.13
    camera_latency: float = 0.2
    ping_up: str | None = None
    ping_down: str | None = None
    depth_model: str | None = None
    sonar_address: str | None = None
    dvl_address: str | None = None


OWN = OwnSensors()
CameraOpt = Annotated[
    str,
    typer.Option(
        help="without --sim: the video, udp:PORT (RTP H.264, as BlueOS sends it) or rtsp://..."
    ),
]
CameraHfovOpt = Annotated[
    float,
    typer.Option(
        help=ranged(
            "without --sim: the camera's horizontal field of view in water, degrees", 10, 170
        ),
        callback=bounded(10, 170, finite),
    ),
]
CameraLatencyOpt = Annotated[
    float,
    typer.Option(
        help=ranged(
            "without --sim: seconds from the camera's sensor to a decoded frame; each step "
            "waits for a frame decoded this long after the move ended",
            0,
            5,
        ),
        callback=bounded(0, 5, finite),
    ),
]
PingUpOpt = Annotated[
    str | None,
    typer.Option(help="without --sim: the upward sounder, udp:HOST:PORT or serial:DEVICE[:BAUD]"),
]
PingDownOpt = Annotated[
    str | None, typer.Option(help="without --sim: the downward sounder (udp:HOST:9090)")
]
DepthModelOpt = Annotated[
    Path | None,
    typer.Option(
        help="without --sim: a folder holding a metric monocular depth model (none: no depth image)"
    ),
]
OwnSonarOpt = Annotated[
    str | None,
    typer.Option(
        "--sonar",
        help="without --sim: a Ping360 scanning sonar, udp:HOST:PORT (BlueOS serves one on "
        "9092) or serial:DEVICE[:BAUD]; its disc goes to the pilot",
    ),
]
OwnDvlOpt = Annotated[
    str | None,
    typer.Option(
        "--dvl",
        help="without --sim: a Water Linked DVL, tcp:HOST[:PORT] (16171); dead reckoning "
        "uses its velocity while it has bottom lock",
    ),
]
OWN_SENSORS = Group(
    (
        "camera",
        "camera_hfov",
        "camera_latency",
        "ping_up",
        "ping_down",
        "depth_model",
        "sonar_address",
        "dvl_address",
    ),
    OwnSensors,
)


@dataclass(frozen=True)
class CaveScene:
    """Where `cavenav fake-sub --scene` puts the fake vehicle, and where its camera and
    sounders answer (`cavenav.sim.cave_sensors`)."""

    scene: str | None = None
    cave_seed: int = 0
    camera_port: int = 5600
    ping_up_port: int = 9091
    ping_down_port: int = 9090
    sonar_port: int | None = None
    dvl_port: int | None = None


SceneOpt = Annotated[
    str | None,
    typer.Option(
        help="serve the vehicle's camera (RTP H.264) and sounders "
        "(Ping1D) rendered in this cave (a family or a .toml)"
    ),
]
CaveSeedOpt = Annotated[int, typer.Option(help="seed of the --scene cave", min=0)]
SCENE = CaveScene()
CameraPortOpt = Annotated[
    int, typer.Option(help="--scene: the camera's UDP port on 127.0.0.1", min=1, max=65535)
]
PingUpPortOpt = Annotated[
    int, typer.Option(help="--scene: the upward Ping1D's UDP port", min=1, max=65535)
]
PingDownPortOpt = Annotated[
    int, typer.Option(help="--scene: the downward Ping1D's UDP port", min=1, max=65535)
]
SonarPortOpt = Annotated[
    int | None,
    typer.Option(
        help="--scene: also answer as a Ping360 on this UDP port (BlueOS's is 9092)",
        min=1,
        max=65535,
    ),
]
DvlPortOpt = Annotated[
    int | None,
    typer.Option(
        help="--scene: also stream a Water Linked DVL's reports on this TCP port (16171)",
        min=1,
        max=65535,
    ),
]
CAVE_SCENE = Group(
    (
        "scene",
        "cave_seed",
        "camera_port",
        "ping_up_port",
        "ping_down_port",
        "sonar_port",
        "dvl_port",
    ),
    CaveScene,
)
