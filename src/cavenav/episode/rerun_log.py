"""Episodes in Rerun (https://rerun.io), the viewer the robot-learning field already uses.

One recording holds the cave mesh and, on a ``step`` timeline, the vehicle's pose, the
camera with its frustum and images, the depth image, the two sounder rays, the path flown
so far, the pilot's map where it keeps one, and each step's action and justification.
`RerunWatcher` logs an episode as it flies (``cavenav run --rerun`` or ``--rerun-save``);
`log_run_folder` logs a recorded one (``cavenav view``). Both go through the same
functions below, so a live view and a replay show the same entities:

    cave                 Mesh3D, static: the floor and walls, cut away above (a diver's
                         map view: the path inside stays in sight from above)
    cave/ceiling         Mesh3D, static: the rest, hidden at first (tick it in the viewer)
    cave/exits           Points3D: the exit portals' centres
    path                 LineStrips3D: the positions flown, up to this step
    vehicle              Transform3D: the pose (x forward, y left, z up)
    vehicle/body         Boxes3D: the BlueROV2-sized box
    vehicle/sounders     Arrows3D: d_top up and d_bottom down
    vehicle/camera       Transform3D and Pinhole (the frustum), looking along +x
    vehicle/camera/rgb   Image (JPEG, quality 85, to keep a recording small)
    vehicle/camera/depth DepthImage, millimetres (uint16)
    pilot/action         TextLog: the action string and its justification
    pilot/map            Image: the pilot's own map, top-down, heading up

and, for a vehicle that carries acoustic instruments (`ACOUSTIC_ENTITIES`):

    vehicle/sonar        Image: the imaging sonar's fan or disc as its software draws it,
                         heading up (JPEG, as the colour image)
    dvl/velocity/forward, dvl/velocity/left, dvl/velocity/up
                         Scalars: the DVL's velocity over the ground, body frame, m/s;
                         none at a step without bottom lock
    dvl/altitude         Scalars: the DVL's altitude, m; none where it found no bottom
    reckoned             LineStrips3D: where dead reckoning put the vehicle, up to this
                         step, beside the true path
    reckoned/sigma       Scalars: the reckoned position's standard error, m

Rerun is an optional dependency (``pip install -e '.[rerun]'``).
"""

from __future__ import annotations

import math
import os
import sys
import warnings
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from cavenav.core.errors import CavenavWarning, ConfigError, DependencyError
from cavenav.core.files import cannot_write
from cavenav.core.types import Observation, Pose, VehicleBody
from cavenav.sensors.camera import CameraIntrinsics
from cavenav.sensors.depth import read_exr
from cavenav.world.scenarios import Scenario

__all__ = ["ACOUSTIC_ENTITIES", "ENTITIES", "RerunWatcher", "log_run_folder", "open_recording"]

ENTITIES = (
    "cave",
    "cave/ceiling",
    "cave/exits",
    "path",
    "vehicle",
    "vehicle/body",
    "vehicle/sounders",
    "vehicle/camera",
    "vehicle/camera/rgb",
    "vehicle/camera/depth",
    "pilot/action",
    "pilot/map",
)
ACOUSTIC_ENTITIES = (
    "vehicle/sonar",
    "dvl/velocity/forward",
    "dvl/velocity/left",
    "dvl/velocity/up",
    "dvl/altitude",
    "reckoned",
    "reckoned/sigma",
)
_DVL_AXES = ("forward", "left", "up")  # the order of a DVL's velocity (body frame)
ROCK = (150, 135, 115)
MAP_SPAN_M = 32.0
CEILING_NORMAL_Z = -0.3  # a face whose inward normal points further down is ceiling
JPEG_QUALITY = 85


def _rerun() -> Any:  # noqa: ANN401 - the module
    try:
        import rerun
    except ImportError:
        raise DependencyError(
            "the Rerun view needs rerun-sdk: pip install -e '.[rerun]' (or pip install rerun-sdk)"
        ) from None
    return rerun


def open_recording(name: str, *, live: bool = False, save: Path | None = None) -> Any:  # noqa: ANN401
    """A Rerun recording that goes to a live viewer (``live``, spawned here), to ``save``
    (an .rrd file), or to both.

    Raises:
        ConfigError: no display for the viewer, no viewer, or a file that cannot be written.
    """
    rr = _rerun()
    recording = rr.RecordingStream("cavenav", recording_id=name)
    if live:
        _spawn(recording)
    sinks = [rr.GrpcSink()] if live else []
    try:
        if save is not None:
            check_recording_path(save)
            Path(save).parent.mkdir(parents=True, exist_ok=True)
            sinks.append(rr.FileSink(str(save)))
        recording.set_sinks(*sinks)  # opens the file: a full disk or a folder fails here
    except (OSError, RuntimeError) as exc:
        raise ConfigError(f"cannot write the Rerun recording {save}: {_first_line(exc)}") from None
    return recording


def check_recording_path(save: Path) -> None:
    """``save`` checked able to take an .rrd file before anything is opened or written
    (a live view connects, a vehicle is armed): not a folder, nor a device, and the
    nearest folder above it that exists is writable. Nothing is created.

    Raises:
        ConfigError: it cannot take the recording.
    """
    why = cannot_write(save)
    if why:
        raise ConfigError(f"cannot write the Rerun recording {save}: {why}")


def _first_line(error: BaseException) -> str:
    return str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__


def _spawn(recording: Any) -> None:  # noqa: ANN401
    """Start a Rerun viewer (not yet connected): the one rerun-sdk installed beside this
    Python (a virtual environment's bin folder need not be on PATH).

    Raises:
        ConfigError: no display to show it on, or no viewer could be started.
    """
    headless = not any(os.environ.get(name) for name in ("DISPLAY", "WAYLAND_DISPLAY"))
    if sys.platform.startswith("linux") and headless:
        raise ConfigError(
            "the Rerun viewer needs a display (DISPLAY is not set): save the recording to a "
            "file (--rerun-save, or --save with cavenav view) and open it with `rerun FILE` "
            "where there is one"
        )
    here = str(Path(sys.executable).parent)
    if (Path(here) / "rerun").is_file() and here not in os.environ.get("PATH", ""):
        os.environ["PATH"] = os.pathsep.join([here, os.environ.get("PATH", "")])
    try:
        recording.spawn(connect=False)
    except RuntimeError as exc:
        raise ConfigError(f"no Rerun viewer could be started ({_first_line(exc)})") from None


def _ceiling(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(m,) whether each face is ceiling: its normal, turned to face into the passage,
    points down (a closed cave mesh's signed volume says which way its normals face)."""
    a, b, c = (vertices[faces[:, k]].astype(np.float64) for k in range(3))
    normals = np.cross(b - a, c - a)
    inward = -1.0 if np.einsum("ij,ij->", a, np.cross(b, c)) > 0 else 1.0
    length = np.maximum(np.linalg.norm(normals, axis=1), 1e-12)
    return inward * normals[:, 2] / length < CEILING_NORMAL_Z


def log_cave(
    recording: Any,  # noqa: ANN401
    scenario: Scenario,
    *,
    sonar: bool = False,
    dvl: bool = False,
) -> None:
    """The cave's mesh, cut away above, and its exits, static; and the layout of the
    viewer's panels, the 3D view looking down on the whole cave, with a panel for the
    sonar's image (``sonar``) and a plot of the DVL and dead reckoning (``dvl`` or
    ``sonar``: either makes a reckoned path) where the vehicle carries them."""
    rr = _rerun()
    vertices, faces = scenario.mesh.vertices.astype(np.float32), scenario.mesh.faces
    ceiling = _ceiling(vertices, faces)
    for entity, part in (("cave", ~ceiling), ("cave/ceiling", ceiling)):
        mesh = rr.Mesh3D(
            vertex_positions=vertices,
            triangle_indices=faces[part].astype(np.uint32),
            albedo_factor=ROCK,
        )
        recording.log(entity, mesh, static=True)
    exits = np.array([portal.point for portal in scenario.exits], np.float32).reshape(-1, 3)
    recording.log("cave/exits", rr.Points3D(exits, radii=0.3, colors=(60, 200, 90)), static=True)
    low, high = vertices.min(axis=0), vertices.max(axis=0)
    recording.send_blueprint(_layout(low, high, sonar=sonar, dvl=dvl))


def _layout(low: np.ndarray, high: np.ndarray, *, sonar: bool, dvl: bool) -> Any:  # noqa: ANN401
    """The 3D view over the whole cave, beside the camera, the depth, the sonar (with
    ``sonar``), the pilot's map, the decisions, and the DVL's and dead reckoning's
    numbers over time (with either)."""
    import rerun.blueprint as rrb

    centre, span = (low + high) / 2, float(np.max(high - low))
    eye = rrb.EyeControls3D(
        position=centre + np.array([0.0, -0.4 * span, 1.1 * span]),
        look_target=centre,
        eye_up=[0.0, 0.0, 1.0],
    )
    # The sonar's image is 2D with no pinhole to place it in 3D: its own panel shows it.
    hidden = ["- /cave/ceiling", "- /pilot/**", "- /vehicle/sonar"]
    cave = rrb.Spatial3DView(origin="/", contents=["+ /**", *hidden], eye_controls=eye)
    images = [
        rrb.Spatial2DView(origin="vehicle/camera", contents="$origin/rgb", name="camera"),
        rrb.Spatial2DView(origin="vehicle/camera", contents="$origin/depth", name="depth"),
    ]
    if sonar:
        images.append(rrb.Spatial2DView(origin="vehicle/sonar", name="sonar"))
    rows: list[rrb.Container | rrb.View] = [
        rrb.Horizontal(*images),
        rrb.Horizontal(
            rrb.Spatial2DView(origin="pilot/map", name="pilot's map"),
            rrb.TextLogView(origin="pilot/action", name="decisions"),
        ),
    ]
    if sonar or dvl:
        contents = ["/dvl/**", "/reckoned/sigma"]
        rows.append(rrb.TimeSeriesView(contents=contents, name="DVL and dead reckoning"))
    senses = rrb.Vertical(*rows)
    return rrb.Blueprint(rrb.Horizontal(cave, senses, column_shares=[3, 2]), collapse_panels=True)


def _yaw_quaternion(pose: Pose) -> list[float]:
    """The rotation (x, y, z, w) that points the body's +x along the pose's heading."""
    angle = pose.psi - math.pi / 2  # heading psi = 0 looks along -y
    return [0.0, 0.0, math.sin(angle / 2), math.cos(angle / 2)]


def log_pose(
    recording: Any,  # noqa: ANN401
    step: int,
    pose: Pose,
    path: np.ndarray,
    camera: CameraIntrinsics,
    camera_offset_m: float,
) -> None:
    """The vehicle at ``pose``, its camera's frustum and the ``path`` (n, 3) flown so far."""
    rr = _rerun()
    recording.set_time("step", sequence=step)
    recording.log(
        "vehicle",
        rr.Transform3D(translation=pose.position, quaternion=_yaw_quaternion(pose)),
    )
    body = VehicleBody()
    recording.log(
        "vehicle/body",
        rr.Boxes3D(half_sizes=[[body.length / 2, body.width / 2, body.height / 2]]),
    )
    recording.log("vehicle/camera", rr.Transform3D(translation=[camera_offset_m, 0.0, 0.0]))
    recording.log(
        "vehicle/camera",
        rr.Pinhole(
            focal_length=camera.focal_px,
            width=camera.width,
            height=camera.height,
            camera_xyz=rr.ViewCoordinates.FLU,
            image_plane_distance=0.5,
        ),
    )
    recording.log("path", rr.LineStrips3D([path], colors=(230, 60, 40)))


def log_senses(
    recording: Any,  # noqa: ANN401
    step: int,
    rgb: np.ndarray | None,
    depth_m: np.ndarray | None,
    d_top: float | None,
    d_bottom: float | None,
) -> None:
    """What the vehicle sensed at ``step``: the images where there are some, and the
    sounders' rays (body frame: up and down)."""
    rr = _rerun()
    recording.set_time("step", sequence=step)
    if rgb is not None:
        recording.log("vehicle/camera/rgb", rr.Image(rgb).compress(jpeg_quality=JPEG_QUALITY))
    if depth_m is not None:
        finite = np.where(np.isfinite(depth_m), np.clip(depth_m, 0.0, 65.0), 0.0)
        millimetres = np.round(finite * 1000.0).astype(np.uint16)
        recording.log("vehicle/camera/depth", rr.DepthImage(millimetres, meter=1000.0))
    ranges = [r if r is not None and math.isfinite(r) else 0.0 for r in (d_top, d_bottom)]
    recording.log(
        "vehicle/sounders",
        rr.Arrows3D(
            origins=[[0.0, 0.0, 0.0], [0.0, 0.0, 0.0]],
            vectors=[[0.0, 0.0, ranges[0]], [0.0, 0.0, -ranges[1]]],
            colors=[(90, 160, 255), (255, 190, 60)],
            labels=[f"d_top {ranges[0]:.2f} m", f"d_bottom {ranges[1]:.2f} m"],
        ),
    )


def log_sonar(recording: Any, step: int, fan: np.ndarray) -> None:  # noqa: ANN401
    """The imaging sonar's image at ``step``: ``fan`` (H, W) uint8 as the device's
    software draws it, heading up."""
    rr = _rerun()
    recording.set_time("step", sequence=step)
    recording.log("vehicle/sonar", rr.Image(fan).compress(jpeg_quality=JPEG_QUALITY))


def log_dvl(
    recording: Any,  # noqa: ANN401
    step: int,
    velocity_m_s: Sequence[float | None],
    altitude_m: float | None,
) -> None:
    """The DVL's reading at ``step``: its velocity (forward, left, up; m/s) and altitude
    (m), each left out where it measured none (None or NaN: no bottom lock), so that the
    plot never shows a lost lock as a stop."""
    rr = _rerun()
    recording.set_time("step", sequence=step)
    entities = [f"dvl/velocity/{axis}" for axis in _DVL_AXES] + ["dvl/altitude"]
    for entity, value in zip(entities, [*velocity_m_s, altitude_m], strict=True):
        if value is not None and math.isfinite(value):
            recording.log(entity, rr.Scalars(float(value)))


def log_reckoned(
    recording: Any,  # noqa: ANN401
    step: int,
    reckoned: Mapping[str, float],
    path: list[np.ndarray],
) -> None:
    """Where dead reckoning put the vehicle at ``step`` (a step record's ``reckoned``:
    x, y, z and sigma_m in metres), added to ``path``, the positions it gave before; drawn
    beside the true path, the two part as the reckoning drifts."""
    rr = _rerun()
    recording.set_time("step", sequence=step)
    path.append(np.array([reckoned["x"], reckoned["y"], reckoned["z"]], np.float32))
    recording.log("reckoned", rr.LineStrips3D([np.array(path)], colors=(60, 140, 230)))
    recording.log("reckoned/sigma", rr.Scalars(float(reckoned["sigma_m"])))


def log_decision(recording: Any, step: int, record: Mapping[str, Any]) -> None:  # noqa: ANN401
    """The action the step flew and why, as the pilot said it (or how the pilot failed)."""
    rr = _rerun()
    recording.set_time("step", sequence=step)
    if record.get("action") is None:
        text, level = f"pilot failed: {record.get('failure')}", rr.TextLogLevel.ERROR
    else:
        text = f"{record['action']} | {record.get('justification') or ''}".rstrip(" |")
        level = rr.TextLogLevel.WARN if record.get("collision") else rr.TextLogLevel.INFO
    recording.log("pilot/action", rr.TextLog(text, level=level))


class RerunWatcher:
    """Logs an episode to Rerun as it flies: give it to `run_episode` as a watcher."""

    def __init__(self, recording: Any, camera: CameraIntrinsics) -> None:  # noqa: ANN401
        self.recording, self.camera = recording, camera
        self._path: list[np.ndarray] = []
        self._reckoned: list[np.ndarray] = []
        self._pilot: Any = None

    def started(self, scenario: Scenario, pilot: object, info: Mapping[str, Any]) -> None:
        """The cave, the start pose and the first observation."""
        self._pilot, self._path, self._reckoned = pilot, [], []
        first: Observation = info["observation"]
        sonar, dvl = first.sonar is not None, first.dvl is not None
        log_cave(self.recording, scenario, sonar=sonar, dvl=dvl)
        self._arrived(0, info)

    def stepped(self, record: Mapping[str, Any], info: Mapping[str, Any]) -> None:
        """A step's decision, then where it left the vehicle and what it sensed there."""
        step = int(record["step"])
        log_decision(self.recording, step, record)
        self._log_map(step)
        if record.get("reckoned"):  # where the vehicle was reckoned when the step began
            log_reckoned(self.recording, step, record["reckoned"], self._reckoned)
        if info:  # the pilot failed: nothing moved
            self._arrived(step + 1, info)

    def _arrived(self, step: int, info: Mapping[str, Any]) -> None:
        pose: Pose = info["vehicle_pose"]
        observation: Observation = info["observation"]
        self._path.append(pose.position)
        path = np.array(self._path, np.float32)
        log_pose(self.recording, step, pose, path, self.camera, observation.camera_offset_m)
        depth = observation.depth_m if observation.has_depth else None
        log_senses(
            self.recording, step, observation.rgb, depth, observation.d_top, observation.d_bottom
        )
        if observation.sonar is not None:
            log_sonar(self.recording, step, observation.sonar.fan)
        if (dvl := observation.dvl) is not None:
            log_dvl(self.recording, step, list(dvl.velocity_m_s), dvl.altitude_m)

    def _log_map(self, step: int) -> None:
        cave_map = getattr(self._pilot, "map", None)
        if cave_map is not None and hasattr(cave_map, "top_down"):
            self.recording.set_time("step", sequence=step)
            image = cave_map.top_down(span_m=MAP_SPAN_M)
            self.recording.log("pilot/map", _rerun().Image(image))

    def close(self) -> None:
        """Send what is left. A viewer that went away loses the view, not the episode
        (its run folder is written): said as a warning."""
        try:
            self.recording.flush()
        except RuntimeError as exc:
            warnings.warn(f"the Rerun view was cut short: {exc}", CavenavWarning, stacklevel=2)


def log_run_folder(
    recording: Any,  # noqa: ANN401
    run_dir: Path,
    summary: Mapping[str, Any],
    steps: Sequence[Mapping[str, Any]],
    scenario: Scenario | None,
) -> None:
    """A recorded episode: its cave (when known), and every step's pose, the frames the
    folder kept, the sounder readings, the sonar, DVL and dead reckoning where the
    vehicle carried them, and the decision."""
    sensors = (summary.get("config") or {}).get("sensors") or {}
    camera = CameraIntrinsics(**(sensors.get("camera") or {}))
    offset = float(sensors.get("camera_offset_m", 0.2))
    if scenario is not None:
        sonar = any("sonar_png" in (record.get("frames") or {}) for record in steps)
        dvl = any(record.get("dvl") for record in steps)
        log_cave(recording, scenario, sonar=sonar, dvl=dvl)
    path: list[np.ndarray] = []
    reckoned: list[np.ndarray] = []
    for record in steps:
        step, pose = int(record["step"]), Pose.from_dict(record["pose"])
        path.append(pose.position)
        log_pose(recording, step, pose, np.array(path, np.float32), camera, offset)
        rgb, depth = _frames(run_dir, record.get("frames") or {})
        log_senses(recording, step, rgb, depth, record.get("d_top_m"), record.get("d_bottom_m"))
        _log_instruments(recording, run_dir, record, reckoned)
        log_decision(recording, step, record)
    final = summary.get("final_pose")
    if steps and final and not steps[-1].get("collision"):
        path.append(Pose.from_dict(final).position)
        log_pose(recording, len(steps), Pose.from_dict(final), np.array(path), camera, offset)
    recording.flush()


def _log_instruments(
    recording: Any,  # noqa: ANN401
    run_dir: Path,
    record: Mapping[str, Any],
    reckoned: list[np.ndarray],
) -> None:
    """A recorded step's sonar image (where the folder kept it), DVL reading and reckoned
    position (added to ``reckoned``, the path reckoned before it)."""
    step, files = int(record["step"]), record.get("frames") or {}
    if "sonar_png" in files and (run_dir / files["sonar_png"]).is_file():
        from PIL import Image

        with Image.open(run_dir / files["sonar_png"]) as image:
            log_sonar(recording, step, np.asarray(image.convert("L")))
    if dvl := record.get("dvl"):
        velocity = dvl.get("velocity_m_s") or [None] * len(_DVL_AXES)
        log_dvl(recording, step, velocity, dvl.get("altitude_m"))
    if record.get("reckoned"):
        log_reckoned(recording, step, record["reckoned"], reckoned)


def _frames(run_dir: Path, files: Mapping[str, str]) -> tuple[np.ndarray | None, ...]:
    """The colour image and the depth in metres a step's frames hold, where kept."""
    from PIL import Image

    rgb = depth = None
    if "rgb" in files and (run_dir / files["rgb"]).is_file():
        with Image.open(run_dir / files["rgb"]) as image:
            rgb = np.asarray(image.convert("RGB"))
    if "depth_exr" in files and (run_dir / files["depth_exr"]).is_file():
        depth = read_exr(run_dir / files["depth_exr"])
    return rgb, depth
