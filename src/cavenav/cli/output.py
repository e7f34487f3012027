"""What the command line prints, and where: the two consoles, and the tables of an
episode's summary, a sweep's groups and a comparison of two sweeps, drawn with rich from
the records as written.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from rich.console import Console
from rich.markup import escape
from rich.measure import Measurement
from rich.table import Table

if TYPE_CHECKING:
    from cavenav.episode.records import EpisodeSummary
    from cavenav.evaluation.results import ResultRow

__all__ = [
    "console",
    "errors",
    "print_comparison",
    "print_groups",
    "print_leaderboard",
    "print_summary",
]

console = Console()
errors = Console(stderr=True, soft_wrap=True)


def _print_table(table: Table) -> None:
    """On a terminal (or with COLUMNS set) a table fits the width; printed to a file or a
    pipe it keeps every cell whole, where rich would cut it to 80 columns ("51%-1…")."""
    if console.is_terminal or "COLUMNS" in os.environ:
        console.print(table)
        return
    whole = Measurement.get(console, console.options.update_width(1000), table).maximum
    Console(width=max(console.width, whole), file=console.file).print(table)


# Caves of each side listed under a comparison; all of them go to --json FILE.
SHOWN_CAVES = 12


def _metres(value: float | None) -> str:
    """A distance for the tables: two decimals and the unit, "-" where none was measured."""
    return "-" if value is None else f"{value:.2f} m"


def print_summary(summary: EpisodeSummary) -> None:
    """An episode's summary as a two-column table."""
    table = Table(title="episode summary", show_header=False)
    table.add_column(style="bold")
    table.add_column()
    for key, value in _summary_rows(summary):
        # Escaped: a failure quoting a server or a reply ("[redacted]", "[/]") is text,
        # not rich markup, which would swallow it or fail on it.
        table.add_row(key, "-" if value is None else escape(str(value)))
    _print_table(table)


def _spl(s: EpisodeSummary) -> str:
    if s.spl is None:
        return "-"
    if s.shortest_path_m is None:  # a failure: 0, whatever the shortest path
        return f"{s.spl:.3f}"
    return f"{s.spl:.3f} (shortest path {_metres(s.shortest_path_m)})"


def _summary_rows(s: EpisodeSummary) -> list[tuple[str, Any]]:
    rows = [
        ("scenario", s.scenario),
        ("pilot", s.pilot),
        ("seed", s.seed),
        ("termination", s.termination),
        ("success", "yes" if s.success else "no"),
        ("steps", s.steps),
        ("collisions", s.collisions),
        ("path length", f"{s.path_length_m:.1f} m"),
        ("SPL", _spl(s)),
        ("min clearance", _metres(s.min_clearance_m)),
        ("mean clearance", _metres(s.mean_clearance_m)),
        ("steps below standoff", s.steps_below_standoff),
        ("sensing per step", f"{s.mean_sense_ms} ms"),
        ("first sensing", f"{s.first_sense_ms} ms (with loading the kernels)"),
        ("pilot per step", f"{s.mean_pilot_ms} ms"),
    ]
    if s.shield:
        rows.append(("shield interventions", s.shield_interventions))
    if s.invalid_actions:
        rows.append(("invalid actions (held)", s.invalid_actions))
    usage = s.usage
    if usage:
        rows += [
            ("prompt tokens", usage.prompt_tokens),
            ("completion tokens", usage.completion_tokens),
            ("mean model latency", f"{usage.mean_latency_s:.2f} s"),
            ("re-queries", usage.requeries),
            ("transport retries", usage.transport_retries),
            ("cost", "-" if usage.cost_usd is None else f"${usage.cost_usd:.4f}"),
        ]
    if s.energy_wh is not None:
        rows.append(("energy", f"{s.energy_wh:.2f} Wh over {s.moving_s:.0f} s of moves"))
    if s.mean_current_m_s is not None:
        rows.append(("current met", f"{s.mean_current_m_s:.2f} m/s mean, "
                     f"{s.max_current_m_s:.2f} m/s max"))  # fmt: skip
    if s.mean_drift_m is not None:  # flown on a vehicle (cavenav fly) or in a current
        rows.append(("drift from command", f"{s.mean_drift_m:.3f} m mean, "
                     f"{s.max_drift_m:.3f} m max, {s.max_drift_deg:.1f} deg max"))  # fmt: skip
    if s.mean_drift_m is not None and s.mean_current_m_s is None and s.mean_physics_ms:  # a vehicle
        rows.append(("action on the vehicle", f"{s.mean_physics_ms / 1e3:.2f} s mean"))
    if s.failure:
        rows.append(("failure", s.failure))
    return rows


def print_groups(rows: Sequence[ResultRow]) -> None:
    """A sweep's results, one line per scenario (`cavenav.evaluation.results.aggregate`)."""
    from cavenav.evaluation.results import aggregate

    groups = aggregate(rows)
    pilots = sorted({g["pilot"] for g in groups})
    trials = any(g["caves"] not in (0, g["completed"]) for g in groups)
    interval = "Wilson interval, trials of a cave alike" if trials else "Wilson interval"
    table = Table(title=f"{', '.join(pilots)}: success with its 95% {interval}")
    for column in ("scenario", "done", "success", "95% CI", "collided", "other outcomes",
                   "min clear.", "path eff.", "steps"):  # fmt: skip
        table.add_column(column)
    for g in groups:
        ci = g["success_ci95"]
        others = ", ".join(
            f"{k} {v}" for k, v in g["outcomes"].items() if k not in ("success", "collision")
        )
        table.add_row(
            g["scenario"],
            f"{g['completed']}/{g['episodes']}",
            "-" if g["success_rate"] is None else f"{g['success_rate']:.0%}",
            "-" if ci is None else f"{ci[0]:.0%}-{ci[1]:.0%}",
            str(g["collisions"]),
            others or "-",
            _metres(g["min_clearance_m"]["min"]),
            "-" if g["path_efficiency"] is None else f"{g['path_efficiency']:.2f}",
            "-" if g["steps"] is None else f"{g['steps']:.0f}",
        )
    _print_table(table)


def print_comparison(result: Mapping[str, Any], title: str, folders: tuple[Path, Path]) -> None:
    """Two sweeps paired by cave (`cavenav.evaluation.results.compare`): per scenario and
    overall, then the caves only one of them got through, under ``folders`` (A, B)."""
    table = Table(title=title)
    trials = result.get("trials")
    for column in ("scenario", "pairs", "A success", "B success", "A - B (95% CI)",
                   *_side_columns(trials)):  # fmt: skip
        table.add_column(column)
    entries = [*result["per_scenario"].items(), ("all", result["overall"])]
    for name, r in entries:
        if not r["pairs"]:
            continue
        table.add_row(
            name,
            str(r["pairs"]),
            f"{r['success_rate_a']:.0%}",
            f"{r['success_rate_b']:.0%}",
            f"{r['difference']:+.0%} ({r['difference_ci95'][0]:+.0%} to "
            f"{r['difference_ci95'][1]:+.0%})",
            str(len(r["only_a"])),
            str(len(r["only_b"])),
            f"{r['p']:.4g}",
        )
    _print_table(table)
    if result["unpaired"]:
        console.print(f"{result['unpaired']} caves were completed in one sweep only (left out)")
    for side, folder in zip(("a", "b"), folders, strict=True):
        caves = result["overall"][f"only_{side}"]
        if caves:
            heading = (
                f"{side.upper()} did better in {len(caves)} caves"
                if trials
                else f"only {side.upper()} got through ({len(caves)})"
            )
            console.print(f"[bold]{heading}:[/]")
            for cave in caves[:SHOWN_CAVES]:
                console.print(f"  {cave['cave']}: {folder / cave[side]}", soft_wrap=True)
            if len(caves) > SHOWN_CAVES:
                console.print(
                    f"  ... {len(caves) - SHOWN_CAVES} more (all of them with --json FILE)"
                )


def print_leaderboard(result: Mapping[str, Any]) -> None:
    """Several sweeps (`cavenav.evaluation.comparison`): the leaderboard, then every pair's
    difference in success with its interval and McNemar's exact p."""
    from cavenav.evaluation.comparison import board

    table = Table(title="leaderboard (success with its 95% Wilson interval)")
    headers, rows = board(result)
    for column in headers:
        table.add_column(column)
    for row in rows:
        table.add_row(*map(escape, row))
    _print_table(table)
    if not result["pairs"]:
        return
    pairs = Table(title="pairs, over the caves both completed")
    for column in ("A", "B", "caves", "A - B (95% CI)", *_side_columns(result.get("trials"))):
        pairs.add_column(column)
    for pair in result["pairs"]:
        o = pair["overall"]
        if not o["pairs"]:
            continue
        low, high = o["difference_ci95"]
        pairs.add_row(
            escape(pair["a"]),
            escape(pair["b"]),
            str(o["pairs"]),
            f"{o['difference']:+.0%} ({low:+.0%} to {high:+.0%})",
            str(len(o["only_a"])),
            str(len(o["only_b"])),
            f"{o['p']:.4g}",
        )
    _print_table(pairs)


def _side_columns(trials: bool | None) -> tuple[str, str, str]:
    """The columns of the caves that favour each side, and of the test of success."""
    if trials:
        return "A better", "B better", "Wilcoxon p (caves' rates)"
    return "only A", "only B", "McNemar exact p"
