"""Fly a vehicle on its own sensors: no cave model and no simulator, only what it senses.

`cavenav fly` without ``--sim`` comes here. Each step the pilot gets what a BlueROV2
gives: the camera's first frame after the last move ended, a depth image from a
monocular model or none at all (`Observation.has_depth`; the prompt then says so), and
the two echo sounders' ranges (NaN where a sounder is missing or unsure). The shield, on
by default, judges each action on the same observations; the vehicle carries it out
(`cavenav.vehicle.mavlink.ArduSubMotion`, met here only through `VehicleMotion`).

Without a cave model there is no exit to reach, no wall to touch and no clearance to
measure, so the run folder records what can be known: the pose as the vehicle reports
or reckons it (with ``position_sigma_m``, the reckoning's uncertainty), the frames it
got, the sounder ranges, the actions and justifications, and ``progress_m``, the
horizontal distance from the start (the diver's penetration). An episode ends at the
step budget (``budget``) or when the pilot fails (``pilot_failure``); ``success`` is
null, there being no exit to judge it by. The folder is written step by step, as every
run folder is, so Ctrl-C or a lost link leaves a valid, recognisably incomplete record.
"""

from __future__ import annotations

import math
import os
import platform
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from cavenav import __version__
from cavenav.core.errors import CavenavError, PilotFailure
from cavenav.core.types import (
    STEP_BUDGET,
    Action,
    Decision,
    DvlReading,
    Observation,
    Pose,
    SonarImage,
    Usage,
)
from cavenav.episode.metrics import path_length
from cavenav.episode.record import acoustic_fields
from cavenav.episode.records import EpisodeSummary, StepRecord
from cavenav.episode.run_folder import LostStep, RunFolder
from cavenav.episode.settings import EpisodeConfig
from cavenav.motion.actions import DEFAULT_SPACE, TWIST_KEYS, format_action, to_twist
from cavenav.pilots.base import Pilot
from cavenav.safety.reckoning import ReckonedPose
from cavenav.safety.shield import Shield, ShieldConfig
from cavenav.sensors.camera import CameraIntrinsics
from cavenav.sensors.depth import DEPTH_RANGE_M, normalise_depth, unknown_depth
from cavenav.sim.env import read_action

__all__ = ["Flight", "VehicleMotion", "VehicleSenses", "fly_on_sensors"]


class Camera(Protocol):
    def frame_after(self, moment: float) -> np.ndarray:
        """The first RGB frame that arrived after the monotonic time ``moment``."""
        ...


class Sounders(Protocol):
    def read(self) -> tuple[float, float]:
        """(d_top, d_bottom) in metres; NaN where unknown."""
        ...


class VehicleMotion(Protocol):
    """A vehicle that carries out actions and says where it is (`ArduSubMotion`)."""

    @property
    def position(self) -> str:
        """Whether the vehicle's position is "reported" or "reckoned"."""

    @property
    def position_sigma_m(self) -> float | None:
        """The reckoned position's horizontal uncertainty (1 sigma, m); None when reported."""

    @property
    def depth_source(self) -> str | None:
        """Where a reckoned depth comes from; None: the position."""

    @property
    def flown(self) -> Action:
        """The last move's action as flown (cut at the depth limits)."""

    def start(self, pose: Pose) -> Pose: ...

    def move(self, pose: Pose, action: Action) -> Pose: ...


@dataclass
class VehicleSenses:
    """The vehicle's camera, sounders and depth source, as one observation a step.

    Attributes:
        depth: metres from the colour image (`cavenav.sensors.monocular`), or None for
            a vehicle with no depth source.
        camera: the camera's lens; its horizontal field of view goes to the pilot.
        sonar: the imaging sonar's image as swept so far (`own_acoustics.SweptSonar`);
            None: not fitted.
        dvl: the DVL's mean velocity since the last step (`own_acoustics.DvlFeed`);
            None: not fitted.
    """

    camera: Camera
    sounders: Sounders
    depth: Callable[[np.ndarray], np.ndarray] | None = None
    intrinsics: CameraIntrinsics = field(default_factory=CameraIntrinsics)
    camera_offset_m: float = 0.0
    sonar: Callable[[], SonarImage] | None = None
    dvl: Callable[[], DvlReading | None] | None = None

    def sense(self, after: float, step: int, previous: Action | None) -> Observation:
        """The observation of the first frame after the monotonic time ``after``."""
        rgb = self.camera.frame_after(after)
        d_top, d_bottom = self.sounders.read()
        if self.depth is None:
            depth_m, depth_png = unknown_depth(*rgb.shape[:2])
        else:
            depth_m = self.depth(rgb)
            depth_png = normalise_depth(np.nan_to_num(depth_m, nan=0.0), *DEPTH_RANGE_M)
        return Observation(
            rgb=rgb,
            depth_m=depth_m,
            depth_png=depth_png,
            d_top=d_top,
            d_bottom=d_bottom,
            depth_range=DEPTH_RANGE_M,
            hfov_deg=self.intrinsics.hfov_deg,
            camera_offset_m=self.camera_offset_m,
            step=step,
            previous_action=previous,
            has_depth=self.depth is not None,
            depth_source="none" if self.depth is None else "monocular",
            sonar=None if self.sonar is None else self.sonar(),
            dvl=None if self.dvl is None else self.dvl(),
        )


@dataclass(frozen=True)
class Flight:
    """A flight on a vehicle's own sensors: how it is flown, and what flies it.

    Attributes:
        config: the episode's configuration, of which a flight with no cave model uses
            the step budget (`max_steps`), the shield (it judges each action on the
            observations before the vehicle flies it) and ``save_frames`` (each step's
            colour and depth images; the EXR only with a depth source).
        vehicle: what flew and how it sensed (address, mode, camera, sounders, depth
            model), recorded as given in summary.json.
    """

    config: EpisodeConfig = field(default_factory=lambda: EpisodeConfig(shield=True))
    vehicle: Mapping[str, Any] = field(default_factory=dict)

    @property
    def max_steps(self) -> int:
        """The step budget: the configuration's, else SPEC's."""
        return self.config.max_steps or STEP_BUDGET


class _Log:
    """The steps and the summary of a flight, as they happen."""

    def __init__(self, pilot: str, flight: Flight, start: Pose, depth_source: bool):
        self.pilot, self.flight, self.poses = pilot, flight, [start]
        # With a DVL: the position reckoned from its velocity (`acoustic_fields`).
        self.reckoning = ReckonedPose.launched(start.x, start.y, start.z, start.psi)
        self.steps: list[dict[str, Any]] = []
        self.usage: list[Usage] = []
        self.termination: str | None = None
        self.failure: str | None = None
        self._started = time.perf_counter()
        self._meta = {
            "cavenav_version": __version__,
            "python": platform.python_version(),
            "host": platform.node(),
            "pid": os.getpid(),
            "started_at": datetime.now(UTC).isoformat(timespec="seconds"),
            "vehicle": {**flight.vehicle, "depth_image": depth_source},
            "config": {"max_steps": flight.max_steps, "shield": flight.config.shield},
        }

    def mark(self) -> tuple:
        """Where the log stands, to `rewind` to when a step cannot be recorded."""
        return len(self.steps), len(self.poses), len(self.usage), self.termination, self.failure

    def rewind(self, mark: tuple) -> None:
        """Forget what was logged since ``mark``: the summary then agrees with the folder."""
        steps, poses, usage, self.termination, self.failure = mark
        del self.steps[steps:], self.poses[poses:], self.usage[usage:]

    def record(self, step: dict[str, Any], timing_ms: dict[str, float]) -> dict[str, Any]:
        step["timing_ms"] = {k: round(v, 2) for k, v in timing_ms.items()}
        record = StepRecord.model_validate(step).to_dict()
        self.steps.append(record)
        return record

    def summary(self, status: str, motion: VehicleMotion) -> dict[str, Any]:
        sigma = motion.position_sigma_m
        senses = [s["timing_ms"]["sense"] for s in self.steps]
        pilots = [s["timing_ms"]["pilot"] for s in self.steps]
        return EpisodeSummary.model_validate(
            {
                "scenario": "vehicle",
                "pilot": self.pilot,
                "seed": None,
                "status": status,
                "success": None,  # no exit to judge it by
                "termination": self.termination,
                "terminated": self.termination == "pilot_failure",
                "truncated": self.termination == "budget",
                "shield": self.flight.config.shield,
                "shield_interventions": sum(1 for s in self.steps if s.get("shield")),
                "invalid_actions": sum(1 for s in self.steps if s.get("invalid_action")),
                "steps": len(self.steps),
                "path_length_m": round(path_length(self.poses), 4),
                "progress_m": round(_from_start(self.poses[0], self.poses[-1]), 4),
                "final_pose": self.poses[-1].to_dict(),
                "position": motion.position,
                "depth_source": motion.depth_source,
                "position_sigma_m": None if sigma is None else round(sigma, 4),
                "failure": self.failure,
                "wall_time_s": round(time.perf_counter() - self._started, 3),
                "first_sense_ms": senses[0] if senses else None,
                "mean_sense_ms": _mean(senses[1:] or senses),
                "mean_pilot_ms": _mean(pilots),
                "usage": Usage.total(self.usage),
                **self._meta,
            }
        ).to_dict()


def _mean(values: list[float]) -> float | None:
    return round(sum(values) / len(values), 2) if values else None


def _from_start(start: Pose, pose: Pose) -> float:
    return math.hypot(pose.x - start.x, pose.y - start.y)


def fly_on_sensors(
    pilot: Pilot,
    senses: VehicleSenses,
    motion: VehicleMotion,
    flight: Flight,
    run_dir: str | Path,
    on_step: Callable[[dict[str, Any]], None] | None = None,
) -> dict[str, Any]:
    """Fly ``pilot`` on the vehicle until the budget is spent or the pilot fails; the
    run folder ``run_dir`` (empty, or holding only the command log) is written step by
    step. Returns the summary as written.

    Raises:
        VehicleError: the vehicle, the camera or a sounder failed (the record so far
            stays, status "crashed").
        RecordingError: a step could not be written.
    """
    start = motion.start(Pose(0.0, 0.0, 0.0, 0.0))  # the map frame: where it began
    folder = RunFolder(run_dir, flight.config.save_frames, save_exr=senses.depth is not None)
    log = _Log(pilot.name, flight, start, senses.depth is not None)
    shield = Shield(ShieldConfig()) if flight.config.shield else None
    status = "crashed"
    try:
        pilot.reset()
        folder.write_json("summary.json", log.summary("running", motion))
        _fly(pilot, senses, motion, shield, log, folder, on_step)
        try:
            folder.flush()
        except LostStep as lost:
            raise lost.taken_back(log, folder.path) from lost.error
        status = "finished"
    except KeyboardInterrupt:
        status = "interrupted"
        raise
    except Exception as exc:  # a vehicle's, camera's or sounder's error says itself
        log.failure = str(exc) if isinstance(exc, CavenavError) else f"{type(exc).__name__}: {exc}"
        raise
    finally:
        summary, cut_short = log.summary(status, motion), False
        if status == "finished" and log.steps:
            try:
                summary["plots"] = _plotted(summary, log, folder.path)
            except KeyboardInterrupt:  # the flight is whole: its summary says so, no plots
                cut_short = True
        folder.finish(summary, log, None, plots=False)  # type: ignore[arg-type]
        if cut_short:
            raise KeyboardInterrupt
    return summary


def _plotted(summary: dict[str, Any], log: _Log, where: Path) -> dict[str, str]:
    """topdown.png and side.png of the flight (`plot_flight`); none on a full disk."""
    from cavenav.episode.plots import plot_flight  # matplotlib, once the flight is over

    ending = f"{summary['termination']} after {len(log.steps)} steps"
    title = f"vehicle · {summary['pilot']} · {ending}"
    try:
        return plot_flight(log.steps, title, where, summary.get("position_sigma_m") or 0.0)
    except OSError:
        return {}


def _fly(
    pilot: Pilot,
    senses: VehicleSenses,
    motion: VehicleMotion,
    shield: Shield | None,
    log: _Log,
    folder: RunFolder,
    on_step: Callable[[dict[str, Any]], None] | None,
) -> None:
    moved_at, previous = time.monotonic(), None
    for step in range(log.flight.max_steps):
        mark, started = log.mark(), time.perf_counter()
        observation = senses.sense(moved_at, step, previous)
        timing = {"sense": 1e3 * (time.perf_counter() - started)}
        if shield is not None:
            shield.observe(observation)
        record = _begin(step, log, motion, observation)
        started = time.perf_counter()
        try:
            decision = pilot.decide(observation)
        except PilotFailure as failure:
            timing["pilot"] = 1e3 * (time.perf_counter() - started)
            _failed(failure, log, record)
            step_record = log.record(record, timing)
            _hand_over(folder, log, mark, step_record, observation, failure, motion)
            return
        timing["pilot"] = 1e3 * (time.perf_counter() - started)
        started = time.perf_counter()
        previous = _carry_out(decision, shield, motion, log, record)
        moved_at = time.monotonic()  # the camera's clock
        timing["physics"] = 1e3 * (time.perf_counter() - started)
        if step + 1 == log.flight.max_steps:
            log.termination = "budget"
        step_record = log.record(record, timing)
        _hand_over(folder, log, mark, step_record, observation, decision, motion)
        if on_step:
            on_step(step_record)


def _failed(failure: PilotFailure, log: _Log, record: dict[str, Any]) -> None:
    """The pilot gave up: the flight ends there, with what the failed step cost."""
    log.termination, log.failure = "pilot_failure", str(failure)
    record.update(action=None, failure=str(failure), failure_cause=failure.cause)
    if isinstance(failure.usage, Usage):
        log.usage.append(failure.usage)
        record["vlm"] = failure.usage.to_dict()


def _begin(step: int, log: _Log, motion: VehicleMotion, obs: Observation) -> dict[str, Any]:
    sigma = motion.position_sigma_m
    record = {"step": step, "pose": log.poses[-1].to_dict()}
    if sigma is not None:
        record["position_sigma_m"] = round(sigma, 4)
    acoustic, log.reckoning = acoustic_fields(obs, log.reckoning, obs.previous_action)
    return {
        **record, "d_top_m": _rounded(obs.d_top), "d_bottom_m": _rounded(obs.d_bottom),
        **acoustic,
    }  # fmt: skip


def _rounded(metres: float) -> float | None:
    return round(metres, 4) if math.isfinite(metres) else None


def _carry_out(
    decision: Decision,
    shield: Shield | None,
    motion: VehicleMotion,
    log: _Log,
    record: dict[str, Any],
) -> Action:
    """Fly the pilot's action (a hold when inadmissible, the shield's when it objects);
    the action flown."""
    proposed, invalid = read_action(decision.action_text, DEFAULT_SPACE)
    verdict = None if invalid or shield is None else shield.judge(proposed)
    pose = motion.move(log.poses[-1], verdict.action if verdict is not None else proposed)
    executed = motion.flown
    log.poses.append(pose)
    record.update(
        action=format_action(executed),
        justification=decision.justification,
        twist=dict(zip(TWIST_KEYS, to_twist(executed), strict=True)),
        next_pose=pose.to_dict(),
        progress_m=round(_from_start(log.poses[0], pose), 4),
        **decision.extra,
    )
    if verdict is not None and verdict.intervened:
        record["shield"] = verdict.to_dict()
    if invalid:
        record.update(invalid_action=invalid, proposed=decision.action_text)
    if decision.usage is not None:
        log.usage.append(decision.usage)
        record["vlm"] = decision.usage.to_dict()
    return executed


def _hand_over(
    folder: RunFolder,
    log: _Log,
    mark: tuple,
    record: dict[str, Any],
    observation: Observation,
    answer: Decision | PilotFailure,
    motion: VehicleMotion,
) -> None:
    """Queue the step just logged for the folder (with the pilot's exchanges with its
    model), as `cavenav.episode.loop` does: a step the folder could not write is taken
    back from the log with every step after it, and so is one that Ctrl-C kept from the
    queue, so that the summary agrees with the folder."""
    summary = log.summary("running", motion)
    try:
        folder.record(record, observation, answer.exchanges, summary, undo=mark)
    except LostStep as lost:
        raise lost.taken_back(log, folder.path) from lost.error
    except KeyboardInterrupt:
        log.rewind(mark)
        raise
