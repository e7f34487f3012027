"""What a sweep found: one row per episode, aggregates with intervals, paired comparisons.

Everything here reads run folders (summary.json and steps.jsonl), never the live sweep,
so `cavenav report` and `cavenav compare` work on any sweep folder, finished or not, and
the tables always agree with the episodes they summarise.

Outcomes (the failure taxonomy, one per episode):
    success        the vehicle passed the exit portal
    collision      it touched a surface
    pilot_failure  the pilot could not produce a valid action (e.g. persistent bad replies)
    exited_entrance  it left the cave through its entrance, the way it came in
    battery        its moves spent the energy budget (`cavenav eval --battery-wh`)
    budget         out of steps while still making headway: one of the last `WINDOW`
                   steps made headway as `cavenav.safety.headway` counts it (too slow, not lost)
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
from typing import Any, TypedDict, cast

import numpy as np
from scipy.stats import binomtest, norm, wilcoxon

from cavenav.core.errors import CavenavWarning, RecordError
from cavenav.core.types import model_time_percentiles
from cavenav.episode.records import (
    OUTCOMES,
    TERMINATIONS,
    EpisodeSummary,
    Outcome,
    StepRecord,
    Termination,
    UsageRecord,
    load_steps,
    load_summary,
)
from cavenav.episode.run_folder import write_atomic, write_json
from cavenav.safety.headway import Headway

__all__ = [
    "COLUMNS",
    "OUTCOMES",
    "ResultRow",
    "WINDOW",
    "aggregate",
    "cave_rates",
    "clustered_wilson",
    "compare",
    "episode_row",
    "group",
    "outcome",
    "paired_difference_ci",
    "priced",
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
# is an outcome of its own: collision, pilot_failure, exited_entrance, battery, stuck.
_OWN_OUTCOMES: tuple[Outcome, ...] = tuple(
    o for o in OUTCOMES if o in TERMINATIONS and o not in ("exit", "budget")
)


class ResultRow(TypedDict, total=False):
    """One episode's row of results.csv, its columns in order (`COLUMNS`), as every reader
    of results takes it: the report, the comparison, the exports and the progress line.

    A row of a folder with no summary or a damaged one holds only ``episode``,
    ``status``, ``outcome``, ``run_dir`` (and ``error``); every other value may be None.
    """

    episode: str
    scenario: str | None
    seed: int | None
    trial: int | None
    scenario_set: str
    pilot: str | None
    status: str | None  # running, finished, interrupted, crashed; missing or damaged
    success: bool | None
    termination: Termination | None
    outcome: Outcome
    steps: int | None
    collisions: int | None
    progress_m: float | None
    passage_length_m: float | None
    path_length_m: float | None
    path_efficiency: float | None
    shortest_path_m: float | None
    spl: float | None
    min_clearance_m: float | None
    mean_clearance_m: float | None
    steps_below_standoff: int | None
    shield_interventions: int | None
    invalid_actions: int | None
    energy_wh: float | None
    moving_s: float | None
    mean_current_m_s: float | None
    mean_drift_m: float | None
    requeries: int | None
    transport_retries: int | None
    prompt_tokens: int | None
    completion_tokens: int | None
    cost_usd: float | None
    model_calls: int | None  # requests to the model, re-queries included
    calls_per_m: float | None  # of them per metre flown
    steps_without_call: int | None  # steps a designed pilot's planner flew without one
    mean_model_latency_s: float | None
    model_p50_s: float | None
    model_p95_s: float | None
    mean_pilot_ms: float | None
    mean_sense_ms: float | None
    wall_time_s: float | None
    error: str | None
    run_dir: str
    # each model step's server time, for a group's percentiles (not a results.csv column)
    model_step_s: list[float | None]


COLUMNS = tuple(name for name in ResultRow.__annotations__ if name != "model_step_s")


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
    moves = [(s, s.progress_m) for s in steps if s.action and s.pose and s.progress_m is not None]
    if not moves:
        return []
    first, progress = moves[0]
    headway = Headway(progress, _position(first.pose))
    return [headway.advance(made, _position(s.next_pose or s.pose)) for s, made in moves]


def _position(pose: Any) -> tuple[float, float, float]:  # noqa: ANN401 - a recorded pose
    return pose.x, pose.y, pose.z


def read_episode(run_dir: Path) -> tuple[EpisodeSummary, list[StepRecord]]:
    """A run folder's summary.json and steps.jsonl, as every judge of an episode reads
    them: its results row, and a resumed sweep deciding what to fly again.

    Raises:
        RecordError: either is missing or damaged (`cavenav.episode.records`).
    """
    return load_summary(run_dir / "summary.json"), load_steps(run_dir / "steps.jsonl")


def episode_row(run_dir: Path, root: Path | None = None) -> ResultRow:
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
        "model_step_s": [
            step.vlm.get("model_s") for step in steps if step.vlm and not step.vlm.get("cached")
        ],
        "error": summary.error or (summary.failure if server_failed(summary) else None),
        "run_dir": relative,
    }


def _summary_columns(s: EpisodeSummary) -> ResultRow:
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
        "shortest_path_m": s.shortest_path_m,
        "spl": s.spl,
        "min_clearance_m": s.min_clearance_m,
        "mean_clearance_m": s.mean_clearance_m,
        "steps_below_standoff": s.steps_below_standoff,
        "shield_interventions": s.shield_interventions if s.shield else None,
        "invalid_actions": s.invalid_actions,
        "energy_wh": s.energy_wh,
        "moving_s": s.moving_s,
        "mean_current_m_s": s.mean_current_m_s,
        "mean_drift_m": s.mean_drift_m,
        "mean_pilot_ms": s.mean_pilot_ms,
        "mean_sense_ms": s.mean_sense_ms,
        "wall_time_s": s.wall_time_s,
    }


def _usage_columns(s: EpisodeSummary) -> ResultRow:
    """What the model cost, for a model pilot (empty columns for the others): tokens,
    money, time, and how often it was asked, per metre flown too."""
    usage = s.usage or UsageRecord()
    calls = None
    if usage.model_steps is not None:
        calls = usage.model_steps + (usage.requeries or 0)
    flown = s.path_length_m
    asked = usage.model_steps
    return {
        "requeries": usage.requeries,
        "transport_retries": usage.transport_retries,
        "prompt_tokens": usage.prompt_tokens,
        "completion_tokens": usage.completion_tokens,
        "cost_usd": usage.cost_usd,
        "model_calls": calls,
        "calls_per_m": round(calls / flown, 4) if calls is not None and flown else None,
        "steps_without_call": s.steps - asked
        if asked is not None and s.steps is not None
        else None,
        "mean_model_latency_s": usage.mean_latency_s,
        "model_p50_s": usage.model_p50_s,
        "model_p95_s": usage.model_p95_s,
    }


def priced(rows: Sequence[ResultRow], prices: tuple[float, float]) -> list[ResultRow]:
    """``rows`` with ``cost_usd`` worked out from their recorded tokens at ``prices`` (USD
    per million prompt and completion tokens), for a sweep flown without ``--price`` or
    at another price; a row that recorded no tokens keeps its cost."""
    price_in, price_out = prices
    out = []
    for row in rows:
        tokens_in, tokens_out = row.get("prompt_tokens"), row.get("completion_tokens")
        if tokens_in in (None, "") or tokens_out in (None, ""):
            out.append(ResultRow(**row))
            continue
        cost = (float(tokens_in) * price_in + float(tokens_out) * price_out) / 1e6
        out.append(ResultRow(**row, cost_usd=round(cost, 6)))
    return out


def wilson(successes: int, trials: int, confidence: float = 0.95) -> tuple[float, float] | None:
    """The Wilson score interval of a success rate (scipy's binomtest), None for no trials."""
    if trials == 0:
        return None
    low, high = _wilson_bounds(successes, trials, confidence)
    return round(low, 4), round(high, 4)


def _wilson_bounds(successes: int, trials: int, confidence: float) -> tuple[float, float]:
    """The Wilson score interval, unrounded (Newcombe's interval is built from two)."""
    ci = binomtest(successes, trials).proportion_ci(confidence_level=confidence, method="wilson")
    return float(ci.low), float(ci.high)


Cave = tuple[str, int]  # (scenario, seed): what pairs two sweeps' episodes, and trials repeat


def _by_cave(rows: Iterable[ResultRow], completed: bool = True) -> dict[Cave, list[ResultRow]]:
    """Completed episodes (``completed=False``: all) by cave, each cave's trials in order."""
    caves: dict[Cave, list[ResultRow]] = {}
    for r in rows:
        seed = r.get("seed")
        if (r["outcome"] != "incomplete" or not completed) and seed not in (None, ""):
            caves.setdefault((str(r["scenario"]), int(seed)), []).append(r)
    return caves


Trials = Mapping[Cave, Sequence[ResultRow]]  # a sweep's completed episodes by cave
Counts = Sequence[tuple[int, int]]  # per cave: (episodes with the event, episodes)


def _pooled(counts: Counts) -> float:
    """The rate over every cave's episodes together."""
    return sum(k for k, _ in counts) / sum(n for _, n in counts)


def _wilson_at(rate: float, n: float, confidence: float) -> tuple[float, float]:
    """Wilson's score interval of ``rate`` observed over ``n`` trials, for an ``n`` that
    need not be whole (an effective sample size), which scipy's binomtest cannot take."""
    z = float(norm.ppf(0.5 + confidence / 2))
    share = z * z / n
    centre = (rate + share / 2) / (1 + share)
    half = z / (1 + share) * math.sqrt(rate * (1 - rate) / n + share / (4 * n))
    return max(centre - half, 0.0), min(centre + half, 1.0)


def _cluster_covariance(a: Counts, b: Counts) -> float | None:
    """The between-cave (cluster-robust) covariance of two rates pooled over the same
    caves, sum over caves of (k_a - p_a n_a)(k_b - p_b n_b) / (N_a N_b), times C / (C - 1);
    with ``a`` as ``b``, the variance of one. None for fewer than two caves."""
    if len(a) < 2:
        return None
    rate_a, rate_b = _pooled(a), _pooled(b)
    spread = sum(
        (ka - rate_a * na) * (kb - rate_b * nb) for (ka, na), (kb, nb) in zip(a, b, strict=True)
    )
    scale = len(a) / (len(a) - 1) / (sum(n for _, n in a) * sum(n for _, n in b))
    return spread * scale


def _effective_trials(counts: Counts) -> float:
    """Kish's effective sample size of a rate pooled over caves flown several times each:
    p (1 - p) / V, V its between-cave variance (`_cluster_covariance`), held between the
    number of caves (every trial of a cave alike) and of episodes (every trial its own).
    The number of caves where V cannot tell: one cave, or a rate of 0 or 1 (Korn and
    Graubard 1998 bound it so; taking the caves is the cautious end)."""
    caves, episodes, rate = len(counts), sum(n for _, n in counts), _pooled(counts)
    variance = _cluster_covariance(counts, counts)
    if not variance or rate in (0.0, 1.0):
        return float(caves)
    return min(max(rate * (1 - rate) / variance, caves), episodes)


def clustered_wilson(counts: Counts, confidence: float = 0.95) -> tuple[float, float] | None:
    """The 95% interval of a rate pooled over caves flown several times each (``counts``:
    per cave, episodes with the event and episodes), allowing for a cave's trials being
    alike: Wilson's interval at the effective sample size (`_effective_trials`). With one
    trial a cave it is `wilson`. None for no episodes."""
    episodes = sum(n for _, n in counts)
    if episodes == 0:
        return None
    if episodes == len(counts):
        return wilson(sum(k for k, _ in counts), episodes, confidence)
    _, (low, high) = _clustered_side(counts, confidence)
    return round(low, 4), round(high, 4)


def _clustered_side(counts: Counts, confidence: float) -> tuple[float, tuple[float, float]]:
    """A rate pooled over caves and its unrounded interval at the effective sample size."""
    rate = _pooled(counts)
    return rate, _wilson_at(rate, _effective_trials(counts), confidence)


def _counts(trials: Iterable[Sequence[ResultRow]], event: str) -> list[tuple[int, int]]:
    """Per cave's completed ``trials``, the episodes whose outcome is ``event``, and all."""
    return [(sum(r["outcome"] == event for r in rows), len(rows)) for rows in trials]


def _interval(done: Sequence[ResultRow], event: str, caves: Trials) -> tuple[float, float] | None:
    """The 95% interval of the rate of ``event`` over ``done``, the same episodes by cave
    in ``caves``: Wilson's, or `clustered_wilson` where caves were flown several times."""
    if len(caves) in (0, len(done)):
        return wilson(sum(r["outcome"] == event for r in done), len(done))
    return clustered_wilson(_counts(caves.values(), event))


def _mean(values: Iterable[Any]) -> float | None:
    numbers = [float(v) for v in values if v is not None and v != ""]
    numbers = [v for v in numbers if math.isfinite(v)]
    return round(sum(numbers) / len(numbers), 4) if numbers else None


def _total(values: Iterable[Any]) -> float | None:
    numbers = [float(v) for v in values if v is not None and v != ""]
    return round(sum(numbers), 6) if numbers else None


def _spl(done: Sequence[ResultRow]) -> float | None:
    """SPL over completed episodes, a failure (an error too) scoring 0; unknown (None)
    where a success has none recorded (flown before SPL was, or no shortest path found),
    as a mean without it would be biased."""
    known = [0.0 if r["outcome"] != "success" else r.get("spl") for r in done]
    if not known or any(v in (None, "") for v in known):
        return None
    return _mean(known)


def group(scenario: str, pilot: str, rows: Sequence[ResultRow]) -> dict[str, Any]:
    """The aggregate of one (scenario, pilot) cell over its completed episodes.

    Rates and their intervals count every completed episode (errors included: a pilot
    that crashes the episode did not get through); incomplete ones are left out. Where
    caves were flown several times (``--trials``), the intervals allow for a cave's
    trials being alike (`clustered_wilson`).
    """
    done = [r for r in rows if r["outcome"] != "incomplete"]
    successes = sum(1 for r in done if r["outcome"] == "success")
    collisions = sum(1 for r in done if r["outcome"] == "collision")
    n = len(done)
    caves = _by_cave(done)
    clearance_minima = [c for r in done if (c := r.get("min_clearance_m")) is not None]
    return {
        "scenario": scenario,
        "pilot": pilot,
        "episodes": len(rows),
        "completed": n,
        "caves": len(caves),
        "successes": successes,
        "success_rate": round(successes / n, 4) if n else None,
        "success_ci95": _interval(done, "success", caves),
        "collisions": collisions,
        "collision_rate": round(collisions / n, 4) if n else None,
        "collision_ci95": _interval(done, "collision", caves),
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
        "path_efficiency_all": _mean(r.get("path_efficiency") for r in done),
        "spl": _spl(done),
        "steps": _mean(r.get("steps") for r in done),
        "shield_interventions": _mean(r.get("shield_interventions") for r in done),
        "energy_wh": _mean(r.get("energy_wh") for r in done),
        "mean_pilot_ms": _mean(r.get("mean_pilot_ms") for r in done),
        "mean_model_latency_s": _mean(r.get("mean_model_latency_s") for r in done),
        **model_time_percentiles(t for r in done for t in r.get("model_step_s") or []),
        "prompt_tokens": _total(r.get("prompt_tokens") for r in done),
        "completion_tokens": _total(r.get("completion_tokens") for r in done),
        "cost_usd": _total(r.get("cost_usd") for r in done),
        "requeries": _total(r.get("requeries") for r in done),
        **_per_success(done, successes),
        **_calls(done),
    }


def _calls(done: Sequence[ResultRow]) -> dict[str, float | None]:
    """How often a model pilot asked its model: calls per episode, per metre flown
    (over the episodes' metres together), and the share of steps flown without a call
    (a designed pilot's planner's); None for pilots without a model."""
    asked = [r for r in done if r.get("model_calls") is not None]
    calls = sum(int(r["model_calls"] or 0) for r in asked)
    flown = sum(float(r.get("path_length_m") or 0.0) for r in asked)
    steps = sum(int(r.get("steps") or 0) for r in asked)
    without = sum(int(r.get("steps_without_call") or 0) for r in asked)
    return {
        "calls_per_episode": round(calls / len(asked), 2) if asked else None,
        "calls_per_m": round(calls / flown, 4) if asked and flown else None,
        "steps_without_call_share": round(without / steps, 4) if asked and steps else None,
    }


def _per_success(done: Sequence[ResultRow], successes: int) -> dict[str, float | None]:
    """Tokens and cost per success: what one way out costs (None without a success, or
    for a pilot without a model)."""
    tokens = _total(_measure(r, "tokens") for r in done)
    cost = _total(r.get("cost_usd") for r in done)
    return {
        "tokens_per_success": round(tokens / successes, 1) if tokens and successes else None,
        "cost_per_success_usd": round(cost / successes, 6) if cost and successes else None,
    }


def aggregate(rows: Sequence[ResultRow]) -> list[dict[str, Any]]:
    """One group per (scenario, pilot) in order of appearance, then "all" per pilot.

    ``path_efficiency`` is averaged over successful episodes only (metres of centre line
    per metre flown), ``path_efficiency_all`` over every completed one; clearances,
    steps and costs over every completed episode.
    """
    cells: dict[tuple[str, str], list[ResultRow]] = {}
    for row in rows:
        cells.setdefault((str(row.get("scenario")), str(row.get("pilot"))), []).append(row)
    groups = [group(scenario, pilot, members) for (scenario, pilot), members in cells.items()]
    for pilot in dict.fromkeys(pilot for _, pilot in cells):
        everything = [r for (_, p), members in cells.items() if p == pilot for r in members]
        groups.append(group("all", pilot, everything))
    return groups


def cave_rates(rows: Sequence[ResultRow]) -> list[dict[str, Any]]:
    """Each cave's success rate over its completed trials, for a sweep that flew caves
    several times (``--trials``): scenario, seed, successes, completed, success_rate and
    its episodes (run folder names, in trial order, incomplete ones included)."""
    caves = []
    for key, trials in _by_cave(rows, completed=False).items():
        done = [r for r in trials if r["outcome"] != "incomplete"]
        successes = sum(map(_won, done))
        caves.append({
            "scenario": key[0],
            "seed": key[1],
            "successes": successes,
            "completed": len(done),
            "success_rate": round(successes / len(done), 4) if done else None,
            "episodes": [str(r["episode"]) for r in trials],
        })  # fmt: skip
    return caves


def write_results(folder: Path, rows: Sequence[ResultRow], meta: Mapping[str, Any]) -> None:
    """results.csv (one row per episode) and aggregate.json (``meta`` under "sweep"; with
    trials, each cave's rate under "caves")."""
    table = io.StringIO(newline="")
    writer = csv.DictWriter(table, COLUMNS, extrasaction="ignore")
    writer.writeheader()
    for row in rows:
        writer.writerow({k: "" if row.get(k) is None else row.get(k) for k in COLUMNS})
    write_atomic(folder / "results.csv", table.getvalue())
    trials = int(meta.get("trials", 1)) > 1
    caves = {"caves": cave_rates(rows)} if trials else {}
    write_json(folder / "aggregate.json", {"sweep": meta, "groups": aggregate(rows), **caves})


def paired_difference_ci(
    both: int, only_a: int, only_b: int, neither: int, confidence: float = 0.95
) -> tuple[float, float] | None:
    """Newcombe's interval (1998, method 10) for the difference of two paired success
    rates, A - B: each rate's Wilson interval, combined with the correlation of the pairs.

    The correlation's numerator is corrected for continuity when it is positive (so in
    Altman et al., Statistics with Confidence, and Fagerland et al. 2017, whose example
    59/6/16/80 gives -0.1186 to -0.0046). None for no pairs.
    """
    n = both + only_a + only_b + neither
    if n == 0:
        return None
    margins = (both + only_a) * (only_b + neither) * (both + only_b) * (only_a + neither)
    association: float = both * neither - only_a * only_b
    if association > n / 2:
        association -= n / 2
    elif association >= 0:
        association = 0
    return _combined(
        ((both + only_a) / n, _wilson_bounds(both + only_a, n, confidence)),
        ((both + only_b) / n, _wilson_bounds(both + only_b, n, confidence)),
        association / math.sqrt(margins) if margins else 0.0,
    )


def clustered_difference_ci(
    a: Counts, b: Counts, confidence: float = 0.95
) -> tuple[float, float] | None:
    """The interval of A - B for success rates pooled over the same caves, each flown
    several times (``a``, ``b``: per cave, successes and episodes): Newcombe's way of
    combining two rates' intervals (the MOVER of Zou and Donner 2008), with each rate's
    interval allowing for a cave's trials being alike (`clustered_wilson`) and the
    correlation of the two rates taken between caves (`_cluster_covariance`). None for no
    caves."""
    if not a:
        return None
    variance_a, variance_b = _cluster_covariance(a, a), _cluster_covariance(b, b)
    phi = 0.0
    if variance_a and variance_b:
        phi = (_cluster_covariance(a, b) or 0.0) / math.sqrt(variance_a * variance_b)
    return _combined(_clustered_side(a, confidence), _clustered_side(b, confidence), phi)


def _combined(
    a: tuple[float, tuple[float, float]], b: tuple[float, tuple[float, float]], phi: float
) -> tuple[float, float]:
    """Newcombe's interval for A - B from each rate and its interval, (rate, (low, high)),
    and ``phi``, the correlation of the two estimates."""
    (rate_a, (low_a, high_a)), (rate_b, (low_b, high_b)) = a, b
    difference = rate_a - rate_b
    below = (rate_a - low_a) ** 2 - 2 * phi * (rate_a - low_a) * (high_b - rate_b)
    above = (high_a - rate_a) ** 2 - 2 * phi * (high_a - rate_a) * (rate_b - low_b)
    below += (high_b - rate_b) ** 2
    above += (rate_b - low_b) ** 2
    return (
        round(max(difference - math.sqrt(max(below, 0.0)), -1.0), 4),
        round(min(difference + math.sqrt(max(above, 0.0)), 1.0), 4),
    )


# What the paired tests compare besides success, each over the caves both sweeps flew.
PAIRED_MEASURES = ("min_clearance_m", "steps", "tokens", "cost_usd", "calls_per_m")


def _measure(row: ResultRow, name: str) -> float | None:
    if name == "tokens":
        given = [row.get("prompt_tokens"), row.get("completion_tokens")]
        counts = [float(c) for c in given if c not in (None, "")]
        return sum(counts) if counts else None
    value = cast(Mapping[str, Any], row).get(name)  # a column named at run time
    return None if value in (None, "") else float(value)


def _cave_mean(trials: Sequence[ResultRow], name: str) -> float | None:
    """The mean of measure ``name`` over a cave's trials that recorded it."""
    values = [v for r in trials if (v := _measure(r, name)) is not None]
    return sum(values) / len(values) if values else None


def _signed_rank(pairs: Sequence[tuple[float, float]]) -> dict[str, Any] | None:
    """Wilcoxon's signed-rank test of paired values (scipy: exact for up to 50 pairs
    without ties or zeros, else the normal approximation; zero differences dropped),
    with the median difference A - B. None where no cave gave both values."""
    if not pairs:
        return None
    differences = [a - b for a, b in pairs]
    if not any(differences):
        p = 1.0  # every pair equal: nothing to tell them apart
    else:
        p = float(wilcoxon([a for a, _ in pairs], [b for _, b in pairs]).pvalue)
    return {
        "pairs": len(pairs),
        "median_difference": round(float(np.median(differences)), 4),
        "p": p,
    }


def _won(row: ResultRow) -> bool:
    return row["outcome"] == "success"


def _measure_tests(keys: Sequence[Cave], a: Trials, b: Trials) -> dict[str, Any]:
    """Wilcoxon's test of each of `PAIRED_MEASURES` over the caves ``keys`` (a cave's
    value: the mean over its trials)."""
    tests = {}
    for name in PAIRED_MEASURES:
        values = [(_cave_mean(a[k], name), _cave_mean(b[k], name)) for k in keys]
        tests[name] = _signed_rank([(x, y) for x, y in values if x is not None and y is not None])
    return tests


def _paired_test(keys: Sequence[Cave], a: Trials, b: Trials) -> dict[str, Any]:
    """`compare`'s figures over the caves ``keys``, flown once each by ``a`` and ``b``."""

    def cave(key: Cave) -> dict[str, Any]:
        return {
            "cave": f"{key[0]} seed {key[1]}",
            "a": a[key][0]["run_dir"],
            "b": b[key][0]["run_dir"],
            "outcome_a": a[key][0]["outcome"],
            "outcome_b": b[key][0]["outcome"],
        }

    only_a = [k for k in keys if _won(a[k][0]) and not _won(b[k][0])]
    only_b = [k for k in keys if _won(b[k][0]) and not _won(a[k][0])]
    discordant, n = len(only_a) + len(only_b), len(keys)
    both = sum(_won(a[k][0]) and _won(b[k][0]) for k in keys)
    rate_a, rate_b = (both + len(only_a)) / max(n, 1), (both + len(only_b)) / max(n, 1)
    p = float(binomtest(len(only_a), discordant, 0.5).pvalue) if discordant else 1.0
    return {
        "pairs": n,
        "success_rate_a": round(rate_a, 4) if n else None,
        "success_rate_b": round(rate_b, 4) if n else None,
        "difference": round(rate_a - rate_b, 4) if n else None,
        "difference_ci95": paired_difference_ci(
            both, len(only_a), len(only_b), n - both - discordant
        ),
        "success_test": "mcnemar",
        "p": p,
        "mcnemar_p": p,
        "paired_tests": _measure_tests(keys, a, b),
        "only_a": [cave(k) for k in only_a],
        "only_b": [cave(k) for k in only_b],
    }


def _paired_rates(keys: Sequence[Cave], a: Trials, b: Trials) -> dict[str, Any]:
    """`compare`'s figures over the caves ``keys`` where a sweep flew some of them
    several times (``--trials``): each cave's success rate in each sweep."""
    counts_a, counts_b = (
        _counts((a[k] for k in keys), "success"),
        _counts((b[k] for k in keys), "success"),
    )
    rates = [(ka / na, kb / nb) for (ka, na), (kb, nb) in zip(counts_a, counts_b, strict=True)]

    def cave(k: int) -> dict[str, Any]:
        """The ``k``-th cave, and from each side an episode that shows the difference: a
        success of the side that did better, a failure of the other."""
        key, (rate_a, rate_b) = keys[k], rates[k]
        better_a = rate_a > rate_b
        shown_a = next((r for r in a[key] if _won(r) == better_a), a[key][0])
        shown_b = next((r for r in b[key] if _won(r) != better_a), b[key][0])
        return {
            "cave": f"{key[0]} seed {key[1]}",
            "a": shown_a["run_dir"],
            "b": shown_b["run_dir"],
            "outcome_a": "{}/{} success".format(*counts_a[k]),
            "outcome_b": "{}/{} success".format(*counts_b[k]),
            "rate_a": round(rate_a, 4),
            "rate_b": round(rate_b, 4),
        }

    n = len(keys)
    pooled = [_pooled(c) if n else 0.0 for c in (counts_a, counts_b)]
    test = _signed_rank(rates)
    return {
        "pairs": n,
        "episodes_a": sum(m for _, m in counts_a),
        "episodes_b": sum(m for _, m in counts_b),
        "success_rate_a": round(pooled[0], 4) if n else None,
        "success_rate_b": round(pooled[1], 4) if n else None,
        "difference": round(pooled[0] - pooled[1], 4) if n else None,
        "difference_ci95": clustered_difference_ci(counts_a, counts_b),
        "success_test": "wilcoxon",
        "p": test["p"] if test else 1.0,
        "mcnemar_p": None,
        "paired_tests": _measure_tests(keys, a, b),
        "only_a": [cave(k) for k, (x, y) in enumerate(rates) if x > y],
        "only_b": [cave(k) for k, (x, y) in enumerate(rates) if y > x],
    }


def compare(rows_a: Sequence[ResultRow], rows_b: Sequence[ResultRow]) -> dict:
    """Two sweeps paired by cave (scenario, seed): success rates, their difference and
    the test of it, and paired tests of the other measures.

    Only caves completed in both sweeps are paired. Flown once each, McNemar's exact test
    is the two-sided binomial test of the discordant pairs (A succeeded where B failed,
    and the reverse) against an even split: the concordant caves say nothing about which
    pilot is better; the difference in success comes with Newcombe's paired interval
    (`paired_difference_ci`). Where a sweep flew caves several times (``--trials``),
    each cave has a success rate: the difference is of the pooled rates, its interval
    allows for a cave's trials being alike (`clustered_difference_ci`), and the test is
    Wilcoxon's signed-rank test of the caves' rates. Each of `PAIRED_MEASURES` gets
    Wilcoxon's test over the caves where both sweeps recorded it (a cave's value: the
    mean over its trials).

    Returns:
        "overall" and "per_scenario" entries with the pairs (caves), both success rates,
        their difference (A - B) and its 95% interval, the test ("success_test":
        "mcnemar" or "wilcoxon") and its p-value ("p"; "mcnemar_p" too, None with
        trials), the signed-rank tests ("paired_tests": {measure: {"pairs",
        "median_difference", "p"} or None}), and the caves where A ("only_a") or B
        ("only_b") did better: {"cave", "a", "b", "outcome_a", "outcome_b"} with an
        episode of each side and how it ended (with trials: "2/3 success", and "rate_a",
        "rate_b").
    """
    a, b = _by_cave(rows_a), _by_cave(rows_b)
    paired = sorted(set(a) & set(b))
    repeated = any(len(a[k]) > 1 or len(b[k]) > 1 for k in paired)
    test = _paired_rates if repeated else _paired_test
    scenarios = dict.fromkeys(s for s, _ in paired)
    return {
        "overall": test(paired, a, b),
        "per_scenario": {s: test([k for k in paired if k[0] == s], a, b) for s in scenarios},
        "unpaired": len(set(a) ^ set(b)),
        "trials": repeated,
    }
