"""The closed loop of SPEC section 1: sense, decide, move, check, record.

Each episode ends in exactly one of four ways: ``exit`` (the exit portal was reached),
``collision`` (the body touched a surface along the move), ``budget`` (out of steps) or
``pilot_failure`` (the pilot could not produce a valid action). The first three carry
Gymnasium's distinction: ``budget`` is a truncation, the others terminate the task.
"""

from __future__ import annotations

import platform
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from cavenav import __version__
from cavenav.actions import to_twist
from cavenav.episode.metrics import path_length, summarise_clearance
from cavenav.episode.run_folder import RunFolder
from cavenav.errors import PilotFailure
from cavenav.kinematics import apply
from cavenav.pilots.base import Pilot
from cavenav.sensors.rig import SensorConfig, SensorRig
from cavenav.types import Pose
from cavenav.world.collision import VehicleBody, clearance, swept_collision
from cavenav.world.raycast import RayCaster
from cavenav.world.scenarios import Scenario, validate_start

__all__ = ["TERMINATIONS", "EpisodeConfig", "EpisodeResult", "run_episode"]

TERMINATIONS = ("exit", "collision", "budget", "pilot_failure")


@dataclass(frozen=True)
class EpisodeConfig:
    """Settings of one episode.

    Attributes:
        max_steps: step budget (SPEC: 150).
        standoff_m: clearance under which a step counts as "below standoff" (SPEC: 2.0).
        save_frames: write the RGB, depth PNG and depth EXR of every step (about 1.5 MB a
            step); sweeps can turn this off.
        plots: draw topdown.png and side.png at the end.
    """

    max_steps: int = 150
    standoff_m: float = 2.0
    save_frames: bool = True
    plots: bool = True
    sensors: SensorConfig = field(default_factory=SensorConfig)
    body: VehicleBody = field(default_factory=VehicleBody)


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


def run_episode(
    scenario: Scenario,
    pilot: Pilot,
    config: EpisodeConfig | None = None,
    run_dir: str | Path | None = None,
    on_step: Callable[[dict[str, Any]], None] | None = None,
) -> EpisodeResult:
    """Fly ``pilot`` through ``scenario`` until exit, collision, budget or pilot failure.

    Args:
        run_dir: where to write the run folder (must not exist); None records nothing.
        on_step: called with each step's record, e.g. to advance a progress bar.

    Raises:
        ScenarioError: the start pose is not inside the passage or touches a wall.
    """
    config = config or EpisodeConfig()
    caster = RayCaster(scenario.mesh)
    validate_start(scenario, caster, config.body)
    rig = SensorRig(caster, config.sensors)
    folder = RunFolder(run_dir, config.save_frames) if run_dir is not None else None
    pilot.reset()

    pose = scenario.start
    poses, clearances = [pose], [clearance(caster, pose)]
    steps: list[dict[str, Any]] = []
    termination: str | None = None
    failure: str | None = None
    collision_pose: Pose | None = None
    started = time.perf_counter()
    meta = {
        "cavenav_version": __version__,
        "python": platform.python_version(),
        "started_at": datetime.now(UTC).isoformat(timespec="seconds"),
        "scenario_description": scenario.description,
        "mesh": scenario.mesh.name,
        "triangles": scenario.mesh.triangle_count,
        "start_pose": scenario.start.to_dict(),
        "exits": [asdict(portal) for portal in scenario.exits],
        "config": asdict(config),
    }

    def summary(status: str) -> dict[str, Any]:
        return {
            "scenario": scenario.name,
            "pilot": pilot.name,
            "seed": scenario.seed,
            "status": status,
            "success": termination == "exit",
            "termination": termination,
            "terminated": termination in ("exit", "collision", "pilot_failure"),
            "truncated": termination == "budget",
            "collisions": int(collision_pose is not None),
            "steps": len(steps),
            "path_length_m": round(path_length(poses), 4),
            **summarise_clearance(clearances, config.standoff_m),
            "final_pose": poses[-1].to_dict(),
            "collision_pose": collision_pose.to_dict() if collision_pose else None,
            "exit_distance_m": round(scenario.exit_distance(poses[-1].position), 4),
            "failure": failure,
            "wall_time_s": round(time.perf_counter() - started, 3),
            "mean_sense_ms": _mean_timing(steps, "sense"),
            "mean_pilot_ms": _mean_timing(steps, "pilot"),
            "usage": total_usage([s["vlm"] for s in steps if "vlm" in s]),
            **meta,
        }

    status = "crashed"
    try:
        if folder:
            folder.write_json("summary.json", summary("running"))
        for step in range(config.max_steps):
            t0 = time.perf_counter()
            obs = rig.observe(pose, step)
            t1 = time.perf_counter()
            record: dict[str, Any] = {
                "step": step,
                "pose": pose.to_dict(),
                "clearance_m": round(clearances[-1], 4),
                "d_top_m": round(obs.d_top, 4),
                "d_bottom_m": round(obs.d_bottom, 4),
            }
            try:
                decision = pilot.decide(obs)
            except PilotFailure as exc:
                failure = str(exc)
                termination = "pilot_failure"
                if exc.exchanges:
                    record["vlm"] = exchange_usage(exc.exchanges)
                    if folder:
                        folder.record_exchanges(step, exc.exchanges)
            else:
                if folder and decision.exchanges:
                    folder.record_exchanges(step, decision.exchanges)
            t2 = time.perf_counter()
            if termination is None:
                new_pose = apply(pose, decision.action)
                hit = swept_collision(caster, config.body, pose, new_pose, clearances[-1])
                record.update(
                    action=decision.action_text,
                    justification=decision.justification,
                    twist=dict(
                        zip(
                            ("linear_x", "linear_y", "linear_z", "angular_z"),
                            to_twist(decision.action),
                            strict=True,
                        )
                    ),
                    next_pose=new_pose.to_dict(),
                    collision=hit,
                    **decision.extra,
                )
                if hit:
                    termination, collision_pose = "collision", new_pose
                else:
                    pose = new_pose
                    poses.append(pose)
                    clearances.append(clearance(caster, pose))
                    if scenario.exited(pose.position):
                        termination = "exit"
            else:
                record.update(action=None, failure=failure)
            t3 = time.perf_counter()
            record["timing_ms"] = {
                "sense": round(1e3 * (t1 - t0), 2),
                "pilot": round(1e3 * (t2 - t1), 2),
                "physics": round(1e3 * (t3 - t2), 2),
            }
            if folder:
                record["frames"] = folder.write_frames(step, obs)
                folder.append_step(record)
            steps.append(record)
            if folder:
                folder.write_json("summary.json", summary("running"))
            if on_step:
                on_step(record)
            if termination is not None:
                break
        else:
            termination = "budget"
        status = "finished"
    except KeyboardInterrupt:
        status = "interrupted"
        raise
    finally:
        result = EpisodeResult(
            summary(status), poses, clearances, steps, folder.path if folder else None
        )
        if folder:
            if status == "finished" and config.plots:
                from cavenav.episode.plots import plot_episode

                result.summary["plots"] = plot_episode(result, scenario, caster, folder.path)
            folder.write_json("summary.json", result.summary)
            folder.close()
    return result


def exchange_usage(exchanges: tuple) -> dict[str, Any]:
    """Token and latency totals of a step's model exchanges (used for failed steps)."""
    return {
        "prompt_tokens": sum(e.completion.prompt_tokens for e in exchanges),
        "completion_tokens": sum(e.completion.completion_tokens for e in exchanges),
        "latency_s": round(sum(e.completion.latency_s for e in exchanges), 4),
        "requeries": max(len(exchanges) - 1, 0),
        "transport_retries": sum(e.completion.retries for e in exchanges),
    }


def total_usage(per_step: list[dict[str, Any]]) -> dict[str, Any] | None:
    """Episode totals of the per-step model accounting; None for pilots without a model."""
    if not per_step:
        return None
    costs = [s["cost_usd"] for s in per_step if s.get("cost_usd") is not None]
    latencies = [s["latency_s"] for s in per_step]
    return {
        "model_steps": len(per_step),
        "prompt_tokens": sum(s["prompt_tokens"] for s in per_step),
        "completion_tokens": sum(s["completion_tokens"] for s in per_step),
        "requeries": sum(s["requeries"] for s in per_step),
        "transport_retries": sum(s["transport_retries"] for s in per_step),
        "mean_latency_s": round(sum(latencies) / len(latencies), 4),
        "cost_usd": round(sum(costs), 6) if costs else None,
    }


def _mean_timing(steps: list[dict[str, Any]], key: str) -> float | None:
    values = [s["timing_ms"][key] for s in steps]
    return round(sum(values) / len(values), 2) if values else None
