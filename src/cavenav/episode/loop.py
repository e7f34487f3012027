"""The episode driver of SPEC section 1: an environment, a pilot and recorders.

The step itself (sense, move, check) lives in `cavenav.sim.env.CaveNavEnv`; this driver asks
the pilot for each action, hands it to the environment (behind the safety shield when
asked), and lets the recorders keep what happened: the `EpisodeLog` (records and
summary), the run folder, the progress callback. It drives the environment as any
Gymnasium user would, through `reset` and `step` alone: what the pilot sees, where the
vehicle is and how long each stage took come back in ``info``.

Each episode ends in exactly one of seven ways: ``exit`` (the exit portal was reached),
``collision`` (the body touched a surface along the move), ``exited_entrance`` (it left
the cave the way it came in: a failure), ``battery`` (the moves spent the energy budget,
`EpisodeConfig.battery_wh`), ``budget`` (out of steps: Gymnasium's
truncation), ``stuck`` (no headway for `EpisodeConfig.stuck_after` steps: turning on the
spot, going to and fro, or circling over old ground) or ``pilot_failure`` (the pilot could
not produce a valid action).
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import gymnasium as gym
from gymnasium.wrappers import TimeLimit

from cavenav.core.errors import CavenavError, PilotFailure, RecordingError
from cavenav.core.types import STEP_BUDGET, Observation, Pose
from cavenav.episode.record import TERMINATIONS, EpisodeLog
from cavenav.episode.run_folder import LostStep, RunFolder
from cavenav.episode.settings import EpisodeConfig
from cavenav.motion.kinematics import Motion
from cavenav.pilots.base import Pilot
from cavenav.sim.env import CaveNavEnv, Timings
from cavenav.sim.wrappers import SafetyShield, StuckLimit
from cavenav.world.scenarios import Scenario

__all__ = [
    "DEFAULT_STEPS",
    "TERMINATIONS",
    "EpisodeResult",
    "Watcher",
    "make_env",
    "run_episode",
    "step_budget",
]

DEFAULT_STEPS = STEP_BUDGET  # the old name, kept for scripts that import it


@dataclass
class EpisodeResult:
    """What an episode produced: the summary (as in summary.json) and the trajectory."""

    summary: dict[str, Any]
    poses: list[Pose]
    clearances: list[float]
    steps: list[dict[str, Any]]
    run_dir: Path | None

    @property
    def success(self) -> bool:
        return bool(self.summary["success"])

    @property
    def termination(self) -> str | None:
        return self.summary["termination"]


class Watcher(Protocol):
    """Watches an episode as it flies, e.g. a live 3D view (`cavenav.episode.rerun_log`)."""

    def started(self, scenario: Scenario, pilot: Pilot, info: Mapping[str, Any]) -> None:
        """The episode begins: the reset's ``info`` (the start pose, the first observation)."""
        ...

    def stepped(self, record: Mapping[str, Any], info: Mapping[str, Any]) -> None:
        """A step was logged as ``record``; ``info`` is the environment's after it (empty
        when the pilot failed)."""
        ...

    def close(self) -> None:
        """The episode is over, however it ended."""
        ...


def step_budget(scenario: Scenario, config: EpisodeConfig) -> int:
    """The steps an episode of ``config`` gets in ``scenario`` (`EpisodeConfig.steps_in`)."""
    return config.steps_in(scenario)


def make_env(scenario: Scenario, config: EpisodeConfig, motion: Motion | None = None) -> gym.Env:
    """The environment an episode of ``config`` flies (`EpisodeConfig.for_episode`):
    budget, the stuck limit, then the shield if asked; the cave with the guideline it
    asks for (`EpisodeConfig.cave`)."""
    config = config.for_episode(scenario)
    env: gym.Env = CaveNavEnv(
        config.cave(scenario),
        sensors=config.sensors,
        body=config.body,
        rules=config.rules,
        motion=motion,
        current=config.current,
        battery_wh=config.battery_wh,
    )
    env = TimeLimit(env, max_episode_steps=config.steps_in(scenario))
    if config.stuck_after:
        env = StuckLimit(env, config.stuck_after)
    return SafetyShield(env) if config.shield else env


def run_episode(
    scenario: Scenario,
    pilot: Pilot,
    config: EpisodeConfig | None = None,
    run_dir: str | Path | None = None,
    on_step: Callable[[dict[str, Any]], None] | None = None,
    motion: Motion | None = None,
    watchers: Sequence[Watcher] = (),
) -> EpisodeResult:
    """Fly ``pilot`` through ``scenario`` until one of the seven endings (module docstring).

    Args:
        run_dir: where to write the run folder (must not exist); None records nothing.
        on_step: called with each step's record, e.g. to advance a progress bar.
        motion: who carries out the actions (`CaveNavEnv`'s ``motion``): the kinematics
            by default, or a vehicle, e.g. over MAVLink (`cavenav fly`).
        watchers: shown the episode as it flies (`Watcher`).

    Raises:
        ScenarioError: the start pose is not inside the passage or touches a wall.
    """
    config = (config or EpisodeConfig()).for_episode(scenario)  # recorded as flown
    scenario = config.cave(scenario)  # with the guideline it asks for
    env = make_env(scenario, config, motion)
    _, info = env.reset(seed=config.seed)  # checks the start before any folder is written
    log = _episode_log(scenario, pilot, config, info)
    folder = _run_folder(run_dir, config)
    status = "crashed"
    try:
        pilot.reset()
        if folder:
            _write(folder.write_json, folder.path, "summary.json", log.summary("running"))
        for watcher in watchers:
            watcher.started(scenario, pilot, info)
        _fly(env, pilot, log, info, folder, _telling(on_step, watchers))
        status = "finished"
    except KeyboardInterrupt:
        status = "interrupted"
        raise
    except Exception as exc:
        log.crashed(
            f"{type(exc).__name__}: {exc}" if not isinstance(exc, CavenavError) else str(exc)
        )
        raise
    finally:
        summary, cut_short = _final_summary(log, status)
        if folder:
            caster = env.get_wrapper_attr("caster")
            plots = config.plots and status == "finished" and not cut_short
            folder.finish(summary, log, caster, plots=plots)
        env.close()
        for watcher in watchers:
            watcher.close()
        if cut_short:
            raise KeyboardInterrupt
    return EpisodeResult(
        summary, log.poses, log.clearances, log.steps, folder.path if folder else None
    )


def _episode_log(
    scenario: Scenario, pilot: Pilot, config: EpisodeConfig, reset_info: Mapping[str, Any]
) -> EpisodeLog:
    """The episode's log, begun at the start the environment's reset reports."""
    start, clearance = reset_info["vehicle_pose"], reset_info["clearance_m"]
    pilot_seed = getattr(pilot, "seed", None)  # a pilot that draws (random) keeps its seed
    log = EpisodeLog(
        scenario, pilot.name, config.rules, config.shield, start, clearance, config, pilot_seed
    )
    log.vehicle_start = reset_info.get("vehicle_start")
    return log


def _final_summary(log: EpisodeLog, status: str) -> tuple[dict[str, Any], bool]:
    """The summary the episode ends with, and whether Ctrl-C cut it short.

    Finding a finished episode's shortest path for SPL can take seconds in a new cave:
    Ctrl-C then leaves the whole episode finished without its SPL (and without plots),
    rather than no final summary at all.
    """
    try:
        return log.summary(status), False
    except KeyboardInterrupt:
        return log.summary(status, spl=False), True


def _telling(
    on_step: Callable[[dict[str, Any]], None] | None, watchers: Sequence[Watcher]
) -> Callable[[dict[str, Any], dict[str, Any]], None]:
    """One callback for each step: ``on_step`` with its record, the watchers with its
    record and the environment's ``info`` after it."""

    def tell(record: dict[str, Any], info: dict[str, Any]) -> None:
        if on_step:
            on_step(record)
        for watcher in watchers:
            watcher.stepped(record, info)

    return tell


def _run_folder(run_dir: str | Path | None, config: EpisodeConfig) -> RunFolder | None:
    """The run folder ``config`` asks for at ``run_dir``; None records nothing."""
    if run_dir is None:
        return None
    return RunFolder(
        run_dir, config.save_frames, config.save_exr, exr_compression=config.exr_compression
    )


def _fly(
    env: gym.Env,
    pilot: Pilot,
    log: EpisodeLog,
    info: dict[str, Any],
    folder: RunFolder | None,
    on_step: Callable[[dict[str, Any], dict[str, Any]], None],
) -> None:
    """Step until the episode ends, from the ``info`` of the reset, and settle the folder.

    However the loop stops, even on Ctrl-C, the folder keeps the steps handed to it, whole
    (`_settle`), so that it agrees with the log: a lost step was reported once, and
    settling again after it finds nothing new.

    Raises:
        RecordingError: a step could not be written.
    """
    try:
        while log.termination is None:
            mark = log.mark()
            observation = info["observation"]
            record, exchanges, info = _step(env, pilot, log, observation, info["timings"])
            if folder:
                _hand_over(folder, log, mark, record, observation, exchanges)
            on_step(record, info)
        if folder:
            _settle(folder, log)
    except (KeyboardInterrupt, Exception):
        if folder:
            with contextlib.suppress(RecordingError):
                _settle(folder, log)
        raise


def _step(
    env: gym.Env, pilot: Pilot, log: EpisodeLog, observation: Observation, sensed: Timings
) -> tuple[dict[str, Any], Sequence[Mapping[str, Any]], dict[str, Any]]:
    """The pilot decides on ``observation`` (sensed in ``sensed``), the environment
    carries it out and the log records the step.

    Returns:
        The step's record, the pilot's exchanges with its model, and the environment's
        ``info`` (empty when the pilot failed: the episode ends there).
    """
    timing = {"sense": sensed.sense_ms}
    started = time.perf_counter()
    try:
        decision = pilot.decide(observation)
    except PilotFailure as failure:
        timing["pilot"] = 1e3 * (time.perf_counter() - started)
        return log.pilot_failed(observation, failure, timing), failure.exchanges, {}
    timing["pilot"] = 1e3 * (time.perf_counter() - started)
    _, _, _, truncated, info = env.step(decision.action_text)
    timing["physics"] = info["timings"].physics_ms
    executed, pose = info["observation"].previous_action, info["vehicle_pose"]
    record = log.stepped(observation, decision, info, executed, pose, truncated, timing)
    return record, decision.exchanges, info


def _hand_over(
    folder: RunFolder,
    log: EpisodeLog,
    mark: tuple,
    record: dict[str, Any],
    observation: Observation,
    exchanges: Sequence[Mapping[str, Any]],
) -> None:
    """Queue the step just logged for ``folder``, with the log's ``mark`` from before it.

    The folder writes steps behind the loop: a step it could not write (a full disk)
    surfaces a step or a few later, and is taken back from the log with all after it
    (`_taken_back`). A step that never reached the queue (Ctrl-C while the queue was
    full) is taken back at once: either way the summary agrees with the folder.

    Raises:
        RecordingError: a step could not be written.
    """
    try:
        folder.record(record, observation, exchanges, log.summary("running"), undo=mark)
    except LostStep as lost:
        raise lost.taken_back(log, folder.path) from lost.error
    except KeyboardInterrupt:
        log.rewind(mark)
        raise


def _settle(folder: RunFolder, log: EpisodeLog) -> None:
    """Wait until the folder holds every step handed over (see `_hand_over`).

    Raises:
        RecordingError: a step could not be written.
    """
    try:
        folder.flush()
    except LostStep as lost:
        raise lost.taken_back(log, folder.path) from lost.error


def _write(write: Callable[..., None], where: Path, *args: Any) -> None:
    """Call a run-folder writer; a full disk or a lost folder becomes a `RecordingError`."""
    try:
        write(*args)
    except OSError as exc:
        raise RecordingError.cannot_write(f"the run folder {where}", exc) from None
