"""What a sweep found: one row per episode, aggregates with intervals, paired comparisons.

Everything here reads run folders (summary.json and steps.jsonl), never the live sweep,
so `cavenav report` and `cavenav compare` work on any sweep folder, finished or not, and
the tables always agree with the episodes they summarise.

Outcomes (the failure taxonomy, one per episode):
    success        the vehicle passed the exit portal
    collision      it touched a surface
    pilot_failure  the pilot could not produce a valid action (e.g. persistent bad replies)
    exited_entrance  it left the cave through its entrance, the way it came in
    budget         out of steps while still making headway: one of the last `WINDOW`
                   steps made headway as `cavenav.headway` counts it (too slow, not lost)
    stuck          ended by the driver for want of headway (termination ``stuck``, by
                   that same count), or out of steps without headway over the last
                   `WINDOW` steps, having barely moved during them
    oscillating    out of steps without headway over the last `WINDOW` steps, having
                   moved during them: back and forth, or round in circles
    error          the episode raised an error (recorded in its summary), its worker died,
                   or the model server failed it (no answer in time, a refused key, a
                   proxy's page): not the model's fault, so a resumed sweep flies it again;
                   also an episode whose record is damaged (a summary.json or steps.jsonl
                   that does not read back), with a warning naming the file and the field
    incomplete     not flown yet, or cut short by Ctrl-C or a kill (re-run to finish it)
"""

from __future__ import annotations

import csv
import io
import math
import warnings
from collections import Counter
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from scipy.stats import binomtest

from cavenav.episode.records import (
    OUTCOMES,
    TERMINATIONS,
    EpisodeSummary,
    Outcome,
    StepRecord,
    load_steps,
    load_summary,
)
from cavenav.episode.run_folder import write_atomic, write_json
from cavenav.errors import CavenavWarning, RecordError
from cavenav.headway import Headway

__all__ = [
    "COLUMNS",
    "OUTCOMES",
    "WINDOW",
    "aggregate",
    "compare",
    "episode_row",
    "outcome",
    "read_episode",
    "server_failed",
    "wilson",
    "write_results",
]

# A budget ending is judged on the last WINDOW steps: none of them making headway means the
# pilot was no longer getting anywhere; a path below MOVED_M there means it barely moved
# (scaled down for a budget shorter than the window).
WINDOW = 30
MOVED_M = 1.5
# Every termination but the exit (a success) and the budget (judged by the last steps)
# is an outcome of its own: collision, pilot_failure, exited_entrance, stuck.
_OWN_OUTCOMES: tuple[Outcome, ...] = tuple(
    o for o in OUTCOMES if o in TERMINATIONS and o not in ("exit", "budget")
)

COLUMNS = (
    "episode",
    "scenario",
    "seed",
    "scenario_set",
    "pilot",
    "status",
    "success",
    "termination",
    "outcome",
    "steps",
    "collisions",
    "progress_m",
    "passage_length_m",
    "path_length_m",
    "path_efficiency",
    "min_clearance_m",
    "mean_clearance_m",
    "steps_below_standoff",
    "shield_interventions",
    "invalid_actions",
    "requeries",
    "transport_retries",
    "prompt_tokens",
    "completion_tokens",
    "cost_usd",
    "mean_model_latency_s",
    "mean_pilot_ms",
    "mean_sense_ms",
    "wall_time_s",
    "error",
    "run_dir",
)


def server_failed(summary: EpisodeSummary | Mapping[str, Any]) -> bool:
    """The pilot failed because its model server did (`PilotFailure.cause`), not its replies."""
    summary = EpisodeSummary.model_validate(summary)
    return summary.termination == "pilot_failure" and summary.failure_cause in ("backend", "auth")


def outcome(
    summary: EpisodeSummary | Mapping[str, Any],
    steps: Sequence[StepRecord | Mapping[str, Any]],
) -> Outcome:
    """The episode's place in the failure taxonomy (see the module docstring)."""
    summary = EpisodeSummary.model_validate(summary)
    if summary.status == "crashed" or summary.error or server_failed(summary):
        return "error"
    if summary.status != "finished":
        return "incomplete"
    termination = summary.termination
    if termination == "exit":
        return "success"
    if termination in _OWN_OUTCOMES:
        return termination
    moves = [_step(s) for s in steps]
    window = [s for s in moves if s.action][-WINDOW:]
    if len(window) < 2:
        return "stuck"
    if any(_made_headway(moves)[-len(window) :]):
        return "budget"
    positions = np.array([[s.pose.x, s.pose.y, s.pose.z] for s in window if s.pose])
    moved = float(np.linalg.norm(np.diff(positions, axis=0), axis=1).sum())
    # A budget shorter than the window scales the path down.
    return "oscillating" if moved >= MOVED_M * len(window) / WINDOW else "stuck"


def _step(step: StepRecord | Mapping[str, Any]) -> StepRecord:
    """A step record, from a dict as well (a step number is not needed to judge it)."""
    if isinstance(step, StepRecord):
        return step
    return StepRecord.model_validate({"step": -1, **step})


def _made_headway(steps: Sequence[StepRecord]) -> list[bool]:
    """Whether each step that flew an action made headway, as `StuckLimit` counts it:
    from where the first one started, at the progress the first one reached."""
    moves = [s for s in steps if s.action and s.pose and s.progress_m is not None]
    if not moves:
        return []
    headway = Headway(moves[0].progress_m, _position(moves[0].pose))
    return [headway.advance(s.progress_m, _position(s.next_pose or s.pose)) for s in moves]


def _position(pose: Any) -> tuple[float, float, float]:  # noqa: ANN401 - a recorded pose
    return pose.x, pose.y, pose.z


def read_episode(run_dir: Path) -> tuple[EpisodeSummary, list[StepRecord]]:
    """A run folder's summary.json and steps.jsonl, as every judge of an episode reads
    them: its results row, and a resumed sweep deciding what to fly again.

    Raises:
        RecordError: either is missing or damaged (`cavenav.episode.records`).
    """
    return load_summary(run_dir / "summary.json"), load_steps(run_dir / "steps.jsonl")


def episode_row(run_dir: Path, root: Path | None = None) -> dict[str, Any]:
    """One results.csv row for the run folder ``run_dir`` (``root``: paths relative to it).

    A folder with no summary (never started, or killed before its first write) gives an
    ``incomplete`` row. A damaged record (`cavenav.episode.records`) gives an ``error``
    row, status ``damaged``, with a warning naming the file and the field: one damaged
    episode never stops a report or a comparison of the others.
    """
    run_dir = Path(run_dir)
    relative = str(run_dir.relative_to(root)) if root else str(run_dir)
    if not (run_dir / "summary.json").is_file():
        return {"episode": run_dir.name, "status": "missing", "outcome": "incomplete",
                "run_dir": relative}  # fmt: skip
    try:
        summary, steps = read_episode(run_dir)
    except RecordError as exc:
        warnings.warn(f"{exc}; the episode counts as an error", CavenavWarning, stacklevel=2)
        return {"episode": run_dir.name, "status": "damaged", "outcome": "error",
                "error": str(exc), "run_dir": relative}  # fmt: skip
    return {
        "episode": run_dir.name,
        **_summary_columns(summary),
        "outcome": outcome(summary, steps),
        **_usage_columns(summary),
        "error": summary.error or (summary.failure if server_failed(summary) else None),
        "run_dir": relative,
    }


def _summary_columns(s: EpisodeSummary) -> dict[str, Any]:
    """The columns a summary gives as it stands, and the path efficiency (metres of
    centre line per metre flown)."""
    efficiency = None
    if s.path_length_m and s.progress_m is not None:
        efficiency = round(max(s.progress_m, 0.0) / s.path_length_m, 4)
    return {
        "scenario": s.scenario,
        "seed": s.seed,
        "scenario_set": s.scenario_set or "1",  # written from set 2 on
        "pilot": s.pilot,
        "status": s.status,
        "success": s.success,
        "termination": s.termination,
        "steps": s.steps,
        "collisions": s.collisions,
        "progress_m": s.progress_m,
        "passage_length_m": s.passage_length_m,
        "path_length_m": s.path_length_m,
        "path_efficiency": efficiency,
        "min_clearance_m": s.min_clearance_m,
        "mean_clearance_m": s.mean_clearance_m,
        "steps_below_standoff": s.steps_below_standoff,
        "shield_interventions": s.shield_interventions if s.shield else None,
        "invalid_actions": s.invalid_actions,
        "mean_pilot_ms": s.mean_pilot_ms,
        "mean_sense_ms": s.mean_sense_ms,
        "wall_time_s": s.wall_time_s,
    }


def _usage_columns(s: EpisodeSummary) -> dict[str, Any]:
    """What the model cost, for a model pilot (empty columns for the others)."""
    usage = s.usage
    return {
        "requeries": usage and usage.requeries,
        "transport_retries": usage and usage.transport_retries,
        "prompt_tokens": usage and usage.prompt_tokens,
        "completion_tokens": usage and usage.completion_tokens,
        "cost_usd": usage and usage.cost_usd,
        "mean_model_latency_s": usage and usage.mean_latency_s,
    }


def wilson(successes: int, trials: int, confidence: float = 0.95) -> tuple[float, float] | None:
    """The Wilson score interval of a success rate (scipy's binomtest), None for no trials."""
    if trials == 0:
        return None
    ci = binomtest(successes, trials).proportion_ci(confidence_level=confidence, method="wilson")
    return round(float(ci.low), 4), round(float(ci.high), 4)


def _mean(values: Iterable[Any]) -> float | None:
    numbers = [float(v) for v in values if v is not None and v != ""]
    numbers = [v for v in numbers if math.isfinite(v)]
    return round(sum(numbers) / len(numbers), 4) if numbers else None


def _total(values: Iterable[Any]) -> float | None:
    numbers = [float(v) for v in values if v is not None and v != ""]
    return round(sum(numbers), 6) if numbers else None


def _group(scenario: str, pilot: str, rows: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """The aggregate of one (scenario, pilot) cell over its completed episodes.

    Rates and their intervals count every completed episode (errors included: a pilot
    that crashes the episode did not get through); incomplete ones are left out.
    """
    done = [r for r in rows if r["outcome"] != "incomplete"]
    successes = sum(1 for r in done if r["outcome"] == "success")
    collisions = sum(1 for r in done if r["outcome"] == "collision")
    n = len(done)
    clearance_minima = [r["min_clearance_m"] for r in done if r.get("min_clearance_m") is not None]
    return {
        "scenario": scenario,
        "pilot": pilot,
        "episodes": len(rows),
        "completed": n,
        "successes": successes,
        "success_rate": round(successes / n, 4) if n else None,
        "success_ci95": wilson(successes, n),
        "collisions": collisions,
        "collision_rate": round(collisions / n, 4) if n else None,
        "collision_ci95": wilson(collisions, n),
        "outcomes": {k: v for k in OUTCOMES if (v := sum(r["outcome"] == k for r in rows))},
        "terminations": dict(Counter(str(r["termination"]) for r in done if r.get("termination"))),
        "min_clearance_m": {
            "min": round(min(map(float, clearance_minima)), 4) if clearance_minima else None,
            "mean": _mean(clearance_minima),
        },
        "mean_clearance_m": _mean(r.get("mean_clearance_m") for r in done),
        "steps_below_standoff": _mean(r.get("steps_below_standoff") for r in done),
        "path_efficiency": _mean(
            r.get("path_efficiency") for r in done if r["outcome"] == "success"
        ),
        "steps": _mean(r.get("steps") for r in done),
        "shield_interventions": _mean(r.get("shield_interventions") for r in done),
        "mean_pilot_ms": _mean(r.get("mean_pilot_ms") for r in done),
        "mean_model_latency_s": _mean(r.get("mean_model_latency_s") for r in done),
        "prompt_tokens": _total(r.get("prompt_tokens") for r in done),
        "completion_tokens": _total(r.get("completion_tokens") for r in done),
        "cost_usd": _total(r.get("cost_usd") for r in done),
        "requeries": _total(r.get("requeries") for r in done),
    }


def aggregate(rows: Sequence[Mapping[str, Any]]) -> list[dict[str, Any]]:
    """One group per (scenario, pilot) in order of appearance, then "all" per pilot.

    ``path_efficiency`` is averaged over successful episodes only (metres of centre line
    per metre flown); clearances, steps and costs over every completed episode.
    """
    cells: dict[tuple[str, str], list[Mapping[str, Any]]] = {}
    for row in rows:
        cells.setdefault((str(row.get("scenario")), str(row.get("pilot"))), []).append(row)
    groups = [_group(scenario, pilot, members) for (scenario, pilot), members in cells.items()]
    for pilot in dict.fromkeys(pilot for _, pilot in cells):
        everything = [r for (_, p), members in cells.items() if p == pilot for r in members]
        groups.append(_group("all", pilot, everything))
    return groups


def write_results(folder: Path, rows: Sequence[Mapping[str, Any]], meta: Mapping[str, Any]) -> None:
    """results.csv (one row per episode) and aggregate.json (``meta`` under "sweep")."""
    table = io.StringIO(newline="")
    writer = csv.DictWriter(table, COLUMNS, extrasaction="ignore")
    writer.writeheader()
    for row in rows:
        writer.writerow({k: "" if row.get(k) is None else row.get(k) for k in COLUMNS})
    write_atomic(folder / "results.csv", table.getvalue())
    write_json(folder / "aggregate.json", {"sweep": meta, "groups": aggregate(rows)})


def compare(rows_a: Sequence[Mapping[str, Any]], rows_b: Sequence[Mapping[str, Any]]) -> dict:
    """Two sweeps paired by (scenario, seed): success rates and the exact McNemar test.

    Only caves completed in both sweeps are paired. McNemar's exact test is the two-sided
    binomial test of the discordant pairs (A succeeded where B failed, and the reverse)
    against an even split: the concordant caves say nothing about which pilot is better.

    Returns:
        "overall" and "per_scenario" entries with the pairs, both success rates, their
        difference (A - B), the exact p-value, and the caves only A ("only_a") or only
        B ("only_b") got through: {"cave", "a", "b"} with both run folders.
    """

    def completed(rows: Sequence[Mapping[str, Any]]) -> dict[tuple[str, int], Mapping]:
        return {
            (str(r["scenario"]), int(r["seed"])): r
            for r in rows
            if r["outcome"] != "incomplete" and r.get("seed") not in (None, "")
        }

    a, b = completed(rows_a), completed(rows_b)
    paired = sorted(set(a) & set(b))

    def won(row: Mapping[str, Any]) -> bool:
        return row["outcome"] == "success"

    def cave(key: tuple[str, int]) -> dict[str, Any]:
        return {"cave": f"{key[0]} seed {key[1]}", "a": a[key]["run_dir"], "b": b[key]["run_dir"]}

    def test(keys: Sequence[tuple[str, int]]) -> dict[str, Any]:
        only_a = [k for k in keys if won(a[k]) and not won(b[k])]
        only_b = [k for k in keys if won(b[k]) and not won(a[k])]
        discordant = len(only_a) + len(only_b)
        n = len(keys)
        rate_a = sum(won(a[k]) for k in keys) / max(n, 1)
        rate_b = sum(won(b[k]) for k in keys) / max(n, 1)
        p = binomtest(len(only_a), discordant, 0.5).pvalue if discordant else 1.0
        return {
            "pairs": n,
            "success_rate_a": round(rate_a, 4) if n else None,
            "success_rate_b": round(rate_b, 4) if n else None,
            "difference": round(rate_a - rate_b, 4) if n else None,
            "mcnemar_p": float(p),
            "only_a": [cave(k) for k in only_a],
            "only_b": [cave(k) for k in only_b],
        }

    scenarios = dict.fromkeys(s for s, _ in paired)
    return {
        "overall": test(paired),
        "per_scenario": {s: test([k for k in paired if k[0] == s]) for s in scenarios},
        "unpaired": len(set(a) ^ set(b)),
    }
