"""What an episode recorded, step by step, and the summary it adds up to.

The driver hands each step's observation, decision and environment info to an
`EpisodeLog`; the log turns them into the steps.jsonl records and the summary.json
fields (SPEC section 7), so the run folder, the progress bar and the plots all read the
same values.
"""

from __future__ import annotations

import math
import os
import platform
import time
import warnings
from collections import Counter
from dataclasses import asdict
from datetime import UTC, datetime
from typing import Any

from cavenav import SCENARIO_SET, __version__
from cavenav.core.errors import CavenavWarning, PilotFailure
from cavenav.core.types import Action, Decision, Observation, Pose, Rules, Usage
from cavenav.episode.metrics import path_length, summarise_clearance
from cavenav.episode.records import TERMINATED, TERMINATIONS, TRUNCATED, EpisodeSummary, StepRecord
from cavenav.motion.actions import TWIST_KEYS, format_action, to_twist
from cavenav.safety.reckoning import ReckonedPose
from cavenav.world.geodesic import NoPath, shortest_path_of
from cavenav.world.scenarios import Scenario

__all__ = ["TERMINATIONS", "EpisodeLog", "acoustic_fields"]


def acoustic_fields(
    observation: Observation, reckoning: ReckonedPose, last: Action | None
) -> tuple[dict[str, Any], ReckonedPose]:
    """A step record's ``sonar``, ``dvl`` and ``reckoned`` (`StepRecord`), with the
    reckoning moved by the move before ``observation`` (``last``: the action of the step
    before); nothing for a vehicle without a sonar or a DVL."""
    record: dict[str, Any] = {}
    if (sonar := observation.sonar) is not None:
        record["sonar"] = {"kind": sonar.kind, "fresh_beams": int(sonar.fresh.sum())}
    if (dvl := observation.dvl) is not None:
        record["dvl"] = {
            "velocity_m_s": [_finite(v, 5) for v in dvl.velocity_m_s],
            "locked": dvl.locked,
            "altitude_m": _finite(dvl.altitude_m, 4),
            "sigma_m_s": round(dvl.sigma_m_s, 5),
        }
    if record:
        reckoning = reckoning.after(observation, last)
        record["reckoned"] = reckoning.to_dict()
    return record, reckoning


def _finite(value: float, digits: int) -> float | None:
    return round(float(value), digits) if math.isfinite(value) else None


class EpisodeLog:
    """The trajectory, the per-step records and the episode's ending, as they happen."""

    def __init__(
        self,
        scenario: Scenario,
        pilot: str,
        rules: Rules,
        shielded: bool,
        start: Pose,
        start_clearance: float,
        config: Any,
        pilot_seed: int | None = None,
    ):
        """``config`` is the episode's `EpisodeConfig`; ``pilot_seed`` seeds the pilot's
        own draws (None for a pilot that draws nothing)."""
        self.scenario = scenario
        self.pilot = pilot
        self.seeds = {"noise_seed": config.seed, "pilot_seed": pilot_seed}
        self.rules = rules
        self.shielded = shielded
        self.poses = [start]
        self.reckoning = ReckonedPose.launched(start.x, start.y, start.z, start.psi)
        self._executed: Action | None = None  # the action of the step before
        self.clearances = [start_clearance]
        self.steps: list[dict[str, Any]] = []
        self.usage: list[Usage] = []
        self.termination: str | None = None
        self.failure: str | None = None
        self.failure_cause: str | None = None
        self.collision_pose: dict[str, float] | None = None
        self.progress_m = 0.0
        self.vehicle_start: dict[str, Any] | None = None  # how a vehicle reached its start
        self._started = time.perf_counter()
        self._meta = {
            "cavenav_version": __version__,
            "scenario_set": SCENARIO_SET,
            "python": platform.python_version(),
            "host": platform.node(),
            "pid": os.getpid(),  # which sweep worker flew it
            "started_at": datetime.now(UTC).isoformat(timespec="seconds"),
            "scenario_description": scenario.description,
            "difficulty": scenario.difficulty.to_dict() if scenario.difficulty else None,
            "guideline": scenario.guideline.to_dict() if scenario.guideline else None,
            "mesh": scenario.mesh.name,
            "triangles": scenario.mesh.triangle_count,
            "start_pose": scenario.start.to_dict(),
            "exits": [asdict(portal) for portal in scenario.exits],
            "entrances": [asdict(portal) for portal in scenario.entrances],
            "config": asdict(config),
        }

    def _begin(self, observation: Observation) -> dict[str, Any]:
        record: dict[str, Any] = {
            "step": len(self.steps),
            "pose": self.poses[-1].to_dict(),
            "clearance_m": round(self.clearances[-1], 4),
            "d_top_m": round(observation.d_top, 4),
            "d_bottom_m": round(observation.d_bottom, 4),
        }
        acoustic, self.reckoning = acoustic_fields(observation, self.reckoning, self._executed)
        record.update(acoustic)
        return record

    def stepped(
        self,
        observation: Observation,
        decision: Decision,
        info: dict[str, Any],
        executed: Action,
        pose: Pose,
        truncated: bool,
        timing_ms: dict[str, float],
    ) -> dict[str, Any]:
        """Record a step the environment executed.

        Args:
            executed: the action carried out (after any shield; hold when inadmissible).
            pose: where the step left the vehicle.
        """
        record = self._begin(observation)
        self._executed = executed
        if info["collision"]:
            self.collision_pose = info["collision_pose"]
            self.termination = "collision"
        else:
            self.poses.append(pose)
            self.clearances.append(info["clearance_m"])
            if info["exit"]:
                self.termination = "exit"
            elif info.get("entrance"):
                self.termination = "exited_entrance"
            elif info.get("termination") == "battery":
                self.termination = "battery"
        if self.termination is None and info.get("stuck"):
            self.termination = "stuck"
        if self.termination is None and truncated:
            self.termination = "budget"
        self.progress_m = info["progress_m"]
        twist = to_twist(executed)
        record.update(
            action=format_action(executed),
            justification=decision.justification,
            twist=dict(zip(TWIST_KEYS, twist, strict=True)),
            next_pose=info["collision_pose"] or info["pose"],
            collision=info["collision"],
            progress_m=round(self.progress_m, 4),
            **decision.extra,
            **_carried_out(info),
        )
        if info["invalid_action"]:
            record["invalid_action"] = info["invalid_action"]
            record["proposed"] = decision.action_text
        if decision.usage is not None:
            self.usage.append(decision.usage)
            record["vlm"] = decision.usage.to_dict()
        return self._append(record, timing_ms)

    def _append(self, record: dict[str, Any], timing_ms: dict[str, float]) -> dict[str, Any]:
        """Log a step's record, timings last, as steps.jsonl holds it (a `StepRecord`)."""
        record["timing_ms"] = {k: round(v, 2) for k, v in timing_ms.items()}
        record = StepRecord.model_validate(record).to_dict()
        self.steps.append(record)
        return record

    def pilot_failed(
        self, observation: Observation, failure: PilotFailure, timing_ms: dict[str, float]
    ) -> dict[str, Any]:
        """Record the step at which the pilot gave up; the episode ends there."""
        record = self._begin(observation)
        self.termination, self.failure = "pilot_failure", str(failure)
        if isinstance(failure.usage, Usage):
            self.usage.append(failure.usage)
            record["vlm"] = failure.usage.to_dict()
        self.failure_cause = getattr(failure, "cause", "reply")
        record.update(action=None, failure=self.failure, failure_cause=self.failure_cause)
        return self._append(record, timing_ms)

    def mark(self) -> tuple:
        """Where the log stands, to `rewind` to when a step cannot be recorded."""
        lengths = (len(self.poses), len(self.clearances), len(self.steps), len(self.usage))
        return lengths, self.termination, self.failure, self.collision_pose, self.progress_m

    def rewind(self, mark: tuple) -> None:
        """Forget what was logged since ``mark``: the summary then agrees with the folder."""
        lengths, self.termination, self.failure, self.collision_pose, self.progress_m = mark
        kept: tuple[list[Any], ...] = (self.poses, self.clearances, self.steps, self.usage)
        for items, length in zip(kept, lengths, strict=True):
            del items[length:]

    def crashed(self, error: str) -> None:
        """Note why the episode stopped without an ending (status "crashed")."""
        self.failure, self.failure_cause = error, None

    def summary(self, status: str, *, spl: bool = True) -> dict[str, Any]:
        """summary.json as written (`summary_record` as its file holds it)."""
        return self.summary_record(status, spl=spl).to_dict()

    def summary_record(self, status: str, *, spl: bool = True) -> EpisodeSummary:
        """The episode's summary: ``status`` is running, finished, interrupted or crashed;
        ``spl`` False leaves SPL out of a finished one (its shortest path can take seconds
        to find in a new cave)."""
        end, flown = self.poses[-1].position, path_length(self.poses)
        interventions = sum(1 for s in self.steps if s.get("shield"))
        return EpisodeSummary.model_validate(
            {
                "scenario": self.scenario.name,
                "pilot": self.pilot,
                "seed": self.scenario.seed,
                **self.seeds,
                "status": status,
                "success": self.termination == "exit",
                "termination": self.termination,
                "terminated": self.termination in TERMINATED,
                "truncated": self.termination in TRUNCATED,
                "collisions": int(self.collision_pose is not None),
                "shield": self.shielded,
                "shield_interventions": interventions,
                "invalid_actions": sum(1 for s in self.steps if s.get("invalid_action")),
                "steps": len(self.steps),
                "path_length_m": round(flown, 4),
                "progress_m": round(self.progress_m, 4),
                "passage_length_m": round(self.scenario.passage_length_m, 4),
                **(self._spl(status, flown) if spl else {}),
                **summarise_clearance(self.clearances, self.rules.standoff_m),
                "final_pose": self.poses[-1].to_dict(),
                "collision_pose": self.collision_pose,
                "exit_distance_m": round(self.scenario.exit_distance(end), 4),
                "failure": self.failure,
                "failure_cause": self.failure_cause,
                "wall_time_s": round(time.perf_counter() - self._started, 3),
                # The first sensing pays one-off costs (loading or compiling the kernels, cold
                # caches): reported apart so that the mean is what a step costs.
                "first_sense_ms": self.steps[0]["timing_ms"]["sense"] if self.steps else None,
                "mean_sense_ms": _mean_timing(self.steps[1:] or self.steps, "sense"),
                "mean_pilot_ms": _mean_timing(self.steps, "pilot"),
                "usage": Usage.total(self.usage),
                **_drift(self.steps),
                **_move_endings(self.steps),
                "vehicle_start": self.vehicle_start,
                **_energy(self.steps),
                **self._meta,
            }
        )

    def _spl(self, status: str, flown: float) -> dict[str, float | None]:
        """SPL (Anderson et al. 2018) once the episode is over: for a success, the
        shortest path (`cavenav.world.geodesic`, found at a cave's first success)
        over the longer of it and ``flown``; 0 for a finished failure; unknown where
        no shortest path was found."""
        if status != "finished":
            return {}
        if self.termination != "exit":
            return {"spl": 0.0}
        try:
            shortest = shortest_path_of(self.scenario).length_m
        except NoPath as exc:
            warnings.warn(f"no SPL for this episode: {exc}", CavenavWarning, stacklevel=2)
            return {}
        return {"shortest_path_m": shortest, "spl": round(shortest / max(flown, shortest), 4)}


def _carried_out(info: dict[str, Any]) -> dict[str, Any]:
    """What the environment says of how the move went, where it says it: the drift (a
    vehicle or a current), the energy and time it took, the water's speed, the silt
    hanging in the water and the shield's intervention."""
    found: dict[str, Any] = {}
    if "drift_m" in info:
        found.update(
            commanded_pose=info["commanded_pose"],
            drift_m=round(info["drift_m"], 4),
            drift_deg=round(info["drift_deg"], 3),
        )
    if "step_energy_wh" in info:
        found.update(energy_wh=round(info["step_energy_wh"], 6), move_s=round(info["move_s"], 3))
    if info.get("current_m_s") is not None:
        found["current_m_s"] = round(info["current_m_s"], 4)
    if info.get("silt_g") is not None:
        found["silt_g"] = info["silt_g"]
    if info.get("shield"):
        found["shield"] = info["shield"]
    if info.get("vehicle_move") is not None:
        found["vehicle"] = info["vehicle_move"]
    return found


def _move_endings(steps: list[dict[str, Any]]) -> dict[str, Any]:
    """How a vehicle's moves ended (reached, settled, timeout), counted, and how many its
    depth limits cut; nothing when no vehicle flew."""
    moves = [s["vehicle"] for s in steps if "vehicle" in s]
    if not moves:
        return {}
    endings = Counter(m["ended"] for m in moves)
    return {
        "move_endings": dict(sorted(endings.items())),
        "depth_limited_moves": sum(1 for m in moves if m["depth_limited"]),
    }


def _drift(steps: list[dict[str, Any]]) -> dict[str, float]:
    """Mean and largest drift between commanded and reached poses, when a vehicle flew."""
    metres = [s["drift_m"] for s in steps if "drift_m" in s]
    if not metres:
        return {}
    degrees = [s["drift_deg"] for s in steps if "drift_deg" in s]
    return {
        "mean_drift_m": round(sum(metres) / len(metres), 4),
        "max_drift_m": round(max(metres), 4),
        "mean_drift_deg": round(sum(degrees) / len(degrees), 3),
        "max_drift_deg": round(max(degrees), 3),
        "mean_physics_ms": _mean_timing(steps, "physics"),
    }


def _energy(steps: list[dict[str, Any]]) -> dict[str, float]:
    """The energy and time the moves took, and the water's speed where it flowed."""
    found: dict[str, float] = {
        "energy_wh": round(sum(s.get("energy_wh") or 0.0 for s in steps), 4),
        "moving_s": round(sum(s.get("move_s") or 0.0 for s in steps), 2),
    }
    speeds = [s["current_m_s"] for s in steps if s.get("current_m_s") is not None]
    if speeds:
        found["mean_current_m_s"] = round(sum(speeds) / len(speeds), 4)
        found["max_current_m_s"] = round(max(speeds), 4)
    return found


def _mean_timing(steps: list[dict[str, Any]], key: str) -> float | None:
    values = [s["timing_ms"][key] for s in steps if key in s["timing_ms"]]
    return round(sum(values) / len(values), 2) if values else None
