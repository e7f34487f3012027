"""The flags of where an episode is shown (`LIVE_VIEW`), of a vehicle's own sensors
(`OWN_SENSORS`) and of the fake sub's cave (`CAVE_SCENE`), each declared once
(`cavenav.cli.flags`)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from cavenav.cli.flags import Flag, OptionGroup, finite, flag

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
LIVE_VIEW = OptionGroup(
    (
        flag(
            "rerun",
            bool,
            LiveView.rerun,
            "show the episode live in a Rerun viewer: cave, path, camera, depth, sounders, "
            "map and each decision (pip install -e '.[rerun]')",
            "--rerun",
        ),
        flag("rerun_save", Path, None, "write the Rerun recording to this .rrd file"),
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
    """

    camera: str = "udp:5600"
    camera_hfov: float = 53.13
    camera_latency: float = 0.2
    ping_up: str | None = None
    ping_down: str | None = None
    depth_model: str | None = None


_OWN = OwnSensors()
OWN_SENSORS = OptionGroup(
    (
        flag(
            "camera",
            str,
            _OWN.camera,
            "without --sim: the video, udp:PORT (RTP H.264, as BlueOS sends it) or rtsp://...",
        ),
        flag(
            "camera_hfov",
            float,
            _OWN.camera_hfov,
            "without --sim: the camera's horizontal field of view in water, degrees",
            min=10,
            max=170,
            callback=finite,
        ),
        flag(
            "camera_latency",
            float,
            _OWN.camera_latency,
            "without --sim: seconds from the camera's sensor to a decoded frame; each step "
            "waits for a frame decoded this long after the move ended",
            min=0,
            max=5,
            callback=finite,
        ),
        flag(
            "ping_up",
            str,
            None,
            "without --sim: the upward sounder, udp:HOST:PORT or serial:DEVICE[:BAUD]",
        ),
        flag("ping_down", str, None, "without --sim: the downward sounder (udp:HOST:9090)"),
        flag(
            "depth_model",
            Path,
            None,
            "without --sim: a folder holding a metric monocular depth model (none: no depth image)",
        ),
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


def _port(name: str, text: str) -> Flag:
    return flag(name, int, getattr(CaveScene(), name), f"--scene: {text}", min=1, max=65535)


CAVE_SCENE = OptionGroup(
    (
        flag(
            "scene",
            str,
            None,
            "serve the vehicle's camera (RTP H.264) and sounders "
            "(Ping1D) rendered in this cave (a family or a .toml)",
        ),  # fmt: skip
        flag("cave_seed", int, CaveScene.cave_seed, "seed of the --scene cave", min=0),
        _port("camera_port", "the camera's UDP port on 127.0.0.1"),
        _port("ping_up_port", "the upward Ping1D's UDP port"),
        _port("ping_down_port", "the downward Ping1D's UDP port"),
    ),
    CaveScene,
)
