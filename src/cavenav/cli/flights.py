"""How the command line flies: an episode, a sweep or a vehicle, with a progress bar, and
what Ctrl-C, SIGTERM or a refused start leave behind (the exit statuses of `cavenav.cli`).
"""

from __future__ import annotations

import contextlib
import math
import signal
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import click
import typer
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    ProgressColumn,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)

from cavenav.cli.output import console, errors, print_summary
from cavenav.cli.vehicle_flags import LiveView, OwnSensors
from cavenav.core.errors import CavenavError

if TYPE_CHECKING:
    from cavenav.evaluation.results import ResultRow

__all__ = ["fly_episode", "fly_on_own_sensors", "fly_sweep", "fly_vehicle", "open_sensors"]


def fly_episode(
    cave: Any,  # noqa: ANN401 - lazy imports
    flyer: Any,  # noqa: ANN401
    config: Any,  # noqa: ANN401
    run_dir: Path,
    motion: Any = None,  # noqa: ANN401
    view: LiveView | None = None,
) -> None:
    """Fly the episode with a progress bar, print its summary, and exit with the status
    docs/guides/faults.md gives; ``view`` shows it as it flies."""
    from cavenav.episode.loop import run_episode, step_budget
    from cavenav.episode.records import EpisodeSummary

    try:
        watchers = _watchers(view, config, run_dir)
    except CavenavError:
        _remove_if_empty(run_dir)  # refused before anything was flown
        raise
    with Progress(*_bar(), console=console) as progress:
        # Before the first step: the kernels load (the first run on a machine compiles
        # them, about a minute), the lighting tables are built and the start is checked.
        task = progress.add_task(
            f"preparing {cave.name}",
            total=step_budget(cave, config),
            status="sensors, lighting, start check",
        )

        def on_step(record: dict) -> None:
            status = f"clearance {record['clearance_m']:.2f} m  {record.get('action') or ''}"
            progress.update(task, advance=1, description=f"flying {cave.name}", status=status[:60])

        try:
            result = run_episode(cave, flyer, config, run_dir, on_step, motion, watchers)
        except KeyboardInterrupt:
            progress.stop()
            errors.print(_interrupted(run_dir), soft_wrap=True)
            raise typer.Exit(130) from None
        except CavenavError as exc:
            progress.stop()
            _remove_if_empty(run_dir)  # refused before anything was written (the start)
            if (run_dir / "summary.json").is_file():
                exc.args = (f"{exc} (the record so far is in {run_dir})",)
            raise
    summary = EpisodeSummary.model_validate(result.summary)
    print_summary(summary)
    # soft_wrap: paths stay on one line, whatever the terminal width, for copy and paste.
    console.print(f"run folder: [bold]{run_dir}[/]", soft_wrap=True)
    for name in summary.plots.values():
        console.print(f"plot:       {run_dir / name}", soft_wrap=True)
    if view and view.rerun_save:
        console.print(f"rerun:      {view.rerun_save}", soft_wrap=True)
    if summary.termination == "pilot_failure":
        raise typer.Exit(1)


def _watchers(view: LiveView | None, config: Any, run_dir: Path) -> list[Any]:  # noqa: ANN401
    """The live view ``view`` asks for, as the episode loop's watchers."""
    if view is None or not view.wanted:
        return []
    from cavenav.episode.rerun_log import RerunWatcher, open_recording

    save = Path(view.rerun_save) if view.rerun_save else None
    recording = open_recording(run_dir.name, live=view.rerun, save=save)
    return [RerunWatcher(recording, config.sensors.camera)]


def _bar() -> tuple[ProgressColumn, ...]:
    """A progress bar's columns: what, how far, a status line and the time spent."""
    return (
        TextColumn("[progress.description]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("{task.fields[status]}"),
        TimeElapsedColumn(),
    )


def _interrupted(run_dir: Path) -> str:
    """What Ctrl-C left: a partial record, or a whole episode without its SPL or plots."""
    from cavenav.core.errors import RecordError
    from cavenav.episode.records import load_summary

    try:
        summary = load_summary(run_dir / "summary.json")
    except RecordError:  # none yet, or cut short
        summary = None
    if summary is None or summary.status != "finished":
        return f"interrupted: the partial record is in {run_dir}"
    missing = " and ".join(
        name
        for name, left_out in (
            ("SPL", bool(summary.success) and summary.spl is None),  # a success's alone
            ("plots", not summary.plots),
        )
        if left_out
    )
    return f"interrupted after the episode ended: its record is whole in {run_dir}" + (
        f", without {missing}" if missing else ""
    )


def _remove_if_empty(folder: Path) -> None:
    with contextlib.suppress(OSError):  # not empty: it holds the record
        folder.rmdir()


def fly_sweep(
    config: Any,  # noqa: ANN401
    out: Path,
    executor: Any,  # noqa: ANN401
    on_row: Callable[[ResultRow], None] | None = None,
) -> list[ResultRow]:
    """`run_sweep` with a progress bar; Ctrl-C or SIGTERM stop it with the tables written.
    ``on_row`` sees each episode's results row as it ends (`cavenav eval --wandb`)."""
    from cavenav.core.errors import RecordingError
    from cavenav.evaluation.sweep import run_sweep

    counts = {"done": 0, "success": 0}
    with Progress(*_bar(), TextColumn("ETA"), TimeRemainingColumn(), console=console) as progress:
        task = progress.add_task("episodes", total=None, status="")

        def started(left: int, grid: int) -> None:
            if left < grid:
                progress.console.print(f"resuming {out}: {grid - left} of {grid} episodes done")
            progress.update(task, total=left)

        def done(row: ResultRow) -> None:
            counts["done"] += 1
            counts["success"] += row.get("outcome") == "success"
            status = f"{counts['success']}/{counts['done']} succeeded  last: {row['episode']} "
            progress.update(task, advance=1, status=status + str(row.get("outcome")))
            if on_row is not None:
                on_row(row)

        terminated: list[int] = []
        try:
            with _sigterm_as_ctrl_c(terminated):
                return run_sweep(config, out, executor, done, started)
        except KeyboardInterrupt:
            progress.stop()
            errors.print(
                f"interrupted after {counts['done']} episodes: results so far are in {out}; "
                "run the same command again to resume"
            )
            raise typer.Exit(143 if terminated else 130) from None
        except RecordingError as exc:
            progress.stop()
            raise RecordingError(
                f"{exc}; the sweep stopped after {counts['done']} episodes, each record whole: "
                "make room, then run the same command again to resume"
            ) from None


@contextlib.contextmanager
def _sigterm_as_ctrl_c(caught: list[int]) -> Iterator[None]:
    """SIGTERM (kill, a batch scheduler's stop) ends the block as Ctrl-C does: the workers
    are stopped and the tables written; ``caught`` gets the signal, for the exit status
    (143 = 128 + SIGTERM). A second SIGTERM while stopping is ignored."""

    def stop(signum: int, frame: object) -> None:
        caught.append(signum)
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, stop)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def fly_vehicle(
    bridge: Any,  # noqa: ANN401 - lazy imports
    cave: Any,  # noqa: ANN401
    flyer: Any,  # noqa: ANN401
    episode: Any,  # noqa: ANN401
    run_dir: Path,
    confirm: Any,  # noqa: ANN401
    view: LiveView | None = None,
) -> None:
    """Fly the episode through the MAVLink bridge; a failed connection leaves no folder."""
    from cavenav.vehicle.mavlink import ArduSubMotion

    motion = ArduSubMotion(bridge, run_dir / "mavlink.jsonl", confirm=confirm)
    try:
        listening = motion.listen()  # with udpin:HOST:0, the port the system chose
        where = f", listening on {listening[0]}:{listening[1]}" if listening else ""
        depth = f"{bridge.start_depth_m:g} m" if bridge.start_depth_m is not None else "depth"
        console.print(
            f"[bold]{cave.name}[/] through MAVLink ({bridge.mode} mode, {bridge.connect}{where}): "
            f"waiting for the vehicle's heartbeat and position, then to its start {depth}",
            soft_wrap=True,
            highlight=False,
        )
        fly_episode(cave, flyer, episode, run_dir, motion, view)
    except CavenavError:
        motion.close()  # closes the command log
        if not (run_dir / "summary.json").exists():  # failed to connect: nothing was flown,
            (run_dir / "mavlink.jsonl").unlink(missing_ok=True)  # so no folder looks like a run
            _remove_if_empty(run_dir)
        raise
    finally:
        motion.close()
    console.print(f"commands:   {run_dir / 'mavlink.jsonl'}", soft_wrap=True)


def open_sensors(own: OwnSensors, size: tuple[int, int], stack: contextlib.ExitStack) -> Any:  # noqa: ANN401 - a VehicleSenses, imported lazily
    """Open every sensor ``own`` names (each closed by ``stack``), the slow depth model
    last; the camera's frames come at ``size`` (width, height)."""
    from cavenav.episode.on_vehicle import VehicleSenses
    from cavenav.sensors.camera import CameraIntrinsics
    from cavenav.vehicle.camera import CameraAddress, VideoCamera
    from cavenav.vehicle.ping import PingSounders

    address = CameraAddress.parse(own.camera)
    sounders = PingSounders.connect(own.ping_up, own.ping_down)
    stack.callback(sounders.close)
    with console.status(f"opening the camera stream {address}"):
        camera = VideoCamera(address, size, latency_s=own.camera_latency)
    stack.callback(camera.close)
    depth = None
    if own.depth_model is not None:
        from cavenav.sensors.monocular import MonocularDepth

        with console.status(f"loading the depth model {own.depth_model}"):
            depth = MonocularDepth(own.depth_model)
    hfov = camera.hfov_deg(own.camera_hfov)  # less where the stream's sides are cropped
    focal_mm = 18.0 / math.tan(math.radians(hfov) / 2)  # on a 36 mm sensor
    intrinsics = CameraIntrinsics(*size, focal_mm=focal_mm)
    sonar, dvl = _open_acoustics(own, stack)
    return VehicleSenses(camera, sounders, depth, intrinsics, sonar=sonar, dvl=dvl)


def _open_acoustics(own: OwnSensors, stack: contextlib.ExitStack) -> tuple[Any, Any]:
    """The Ping360's image and the DVL's reading, as callables (None: not fitted)."""
    from cavenav.episode.own_acoustics import DvlFeed, SweptSonar

    sonar = dvl = None
    if own.sonar_address is not None:
        from cavenav.sensors.sonar import PING360
        from cavenav.vehicle.ping360 import Ping360Settings, Ping360Sonar

        # As the simulated one sweeps: the range and the sector ahead of `--sonar ping360`.
        settings = Ping360Settings(range_m=PING360.range_m, sector_deg=PING360.sector_deg)
        with console.status(f"opening the Ping360 {own.sonar_address}"):
            swept = SweptSonar(Ping360Sonar.connect(own.sonar_address, settings))
        stack.callback(swept.close)
        sonar = swept.image
    if own.dvl_address is not None:
        from cavenav.vehicle.waterlinked import WaterLinkedDvl

        with console.status(f"waiting for the DVL {own.dvl_address}"):
            feed = DvlFeed(WaterLinkedDvl.connect(own.dvl_address))
        stack.callback(feed.close)
        dvl = feed.reading
    return sonar, dvl


def fly_on_own_sensors(
    bridge: Any,  # noqa: ANN401 - lazy imports
    flyer: Any,  # noqa: ANN401
    flight: Any,  # noqa: ANN401
    sensors: tuple[OwnSensors, tuple[int, int]],
    new_run_dir: Callable[[], Path],
    confirm: Any,  # noqa: ANN401
) -> None:
    """Fly a vehicle on its camera, sounders and depth source (``sensors``: which, and
    the camera's frame size), with no simulator. The sensors open before the run folder
    is made (`new_run_dir`); a start that fails or is interrupted before the first step
    leaves no folder."""
    with contextlib.ExitStack() as stack:
        senses = open_sensors(*sensors, stack)
        run_dir = new_run_dir()
        try:
            summary = _fly_on(bridge, flyer, flight, senses, run_dir, confirm)
        except (KeyboardInterrupt, click.Abort):  # Abort: Ctrl-C at "arm the vehicle?"
            if _forget_if_unflown(run_dir):
                errors.print("interrupted before the flight began: nothing was recorded")
            else:
                errors.print(_interrupted(run_dir), soft_wrap=True)
            raise typer.Exit(130) from None
        except CavenavError as exc:
            if not _forget_if_unflown(run_dir):
                exc.args = (f"{exc} (the record so far is in {run_dir})",)
            raise
    _print_flight(summary, run_dir)


def _fly_on(
    bridge: Any,  # noqa: ANN401
    flyer: Any,  # noqa: ANN401
    flight: Any,  # noqa: ANN401
    senses: Any,  # noqa: ANN401
    run_dir: Path,
    confirm: Any,  # noqa: ANN401
) -> dict[str, Any]:
    """`fly_on_sensors` through the MAVLink bridge, with a progress bar; the vehicle is
    released (neutral sticks, disarmed, the link closed) before this returns or raises."""
    from cavenav.episode.on_vehicle import fly_on_sensors
    from cavenav.vehicle.mavlink import ArduSubMotion

    motion = ArduSubMotion(bridge, run_dir / "mavlink.jsonl", confirm=confirm, reckon=True)
    try:
        console.print(
            f"[bold]vehicle[/] through MAVLink ({bridge.mode} mode, {bridge.connect}): "
            "waiting for the vehicle's heartbeat",
            soft_wrap=True,
            highlight=False,
        )
        with Progress(*_bar(), console=console) as progress:
            task = progress.add_task("flying", total=flight.max_steps, status="")

            def on_step(record: dict) -> None:
                progress.update(task, advance=1, status=f"{record.get('action') or ''}"[:60])

            return fly_on_sensors(flyer, senses, motion, flight, run_dir, on_step)
    finally:
        motion.close()


def _forget_if_unflown(run_dir: Path) -> bool:
    """Remove ``run_dir`` if no flight began there (no summary.json: only the command log
    of a connection that failed or was stopped); whether it did."""
    if (run_dir / "summary.json").exists():
        return False
    (run_dir / "mavlink.jsonl").unlink(missing_ok=True)
    _remove_if_empty(run_dir)
    return True


def _print_flight(summary: dict[str, Any], run_dir: Path) -> None:
    sigma = summary.get("position_sigma_m")
    where = f" (reckoned, +/- {sigma:.2f} m)" if sigma is not None else ""
    console.print(
        f"{summary['termination']} after {summary['steps']} steps: "
        f"{summary['path_length_m']:.2f} m flown, {summary['progress_m']:.2f} m from the "
        f"start{where}",
        highlight=False,
    )
    console.print(f"run folder: [bold]{run_dir}[/]", soft_wrap=True)
    console.print(f"commands:   {run_dir / 'mavlink.jsonl'}", soft_wrap=True)
    if summary["termination"] == "pilot_failure":
        raise typer.Exit(1)
