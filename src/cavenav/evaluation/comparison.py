"""Pilots side by side: several sweeps over the same caves, as a page and the JSON behind it.

`cavenav compare SWEEP SWEEP [SWEEP ...] --out DIR` writes ``DIR/compare.json`` and
``DIR/index.html``: which sweeps (path, pilot, model, settings, cavenav version), a
leaderboard (one row per sweep), every pair's paired tests
(`cavenav.evaluation.results.compare`: Newcombe's interval for the difference in
success, McNemar's exact test, Wilcoxon's signed-rank test on clearance, steps, tokens
and cost), the same per family, and the caves where exactly one of a pair got through,
each linking to both episodes. ``DIR/leaderboard.md`` and ``DIR/leaderboard.tex`` hold
the leaderboard to paste into a paper.
"""

from __future__ import annotations

import itertools
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from cavenav.core.errors import CavenavError, ConfigError, RecordingError
from cavenav.episode.run_folder import write_atomic, write_json
from cavenav.evaluation.report import page_name, render_page
from cavenav.evaluation.results import ResultRow, compare, group, priced
from cavenav.evaluation.sweep import read_rows, read_sweep

__all__ = [
    "BOARD_HEADERS",
    "Compared",
    "board",
    "board_cells",
    "comparison",
    "latex_table",
    "load_sweeps",
    "markdown_table",
    "write",
]

METHODS = (
    "Success rates with their 95% Wilson intervals. For each pair of sweeps, only the caves "
    "both completed are paired: the difference in success (A - B) has Newcombe's 95% "
    "interval for paired proportions (1998, method 10, with the continuity-corrected "
    "correlation), and its p-value is McNemar's exact test (a two-sided binomial test of "
    "the caves only one got through). Minimum clearance, steps, tokens and cost are "
    "compared by Wilcoxon's signed-rank test over the caves where both recorded them "
    "(scipy; zero differences dropped); a median difference is A - B."
)
# How the same is done where a sweep flew each cave several times (--trials).
TRIAL_METHODS = (
    "Where caves were flown several times (--trials), trials of one cave tend to end "
    "alike, so the episodes are not independent: each success rate's 95% interval is Wilson's at "
    "the effective sample size, p(1 - p) over the rate's variance between caves, held "
    "between the number of caves and of episodes (Kish's design effect; the caves' number "
    "for a rate of 0 or 1). For each such pair, the difference in pooled success (A - B) has "
    "Newcombe's interval built from those two intervals and the correlation of the two "
    "rates between caves (the MOVER of Zou and Donner 2008), and its p-value is Wilcoxon's "
    "signed-rank test of the caves' success rates. Minimum clearance, steps, tokens and "
    "cost are compared by Wilcoxon's test of each cave's mean over its trials; a median "
    "difference is A - B."
)


# What the page calls each of `cavenav.evaluation.results.PAIRED_MEASURES`.
MEASURE_NAMES = {
    "min_clearance_m": "minimum clearance (m)",
    "steps": "steps",
    "tokens": "tokens",
    "cost_usd": "cost (USD)",
    "calls_per_m": "model calls per m",
}


@dataclass(frozen=True)
class Compared:
    """One sweep of a comparison: its folder, its pilot's label, sweep.json and its rows."""

    path: Path
    label: str
    config: Mapping[str, Any]
    rows: list[ResultRow]


def load_sweeps(
    folders: Sequence[Path],
    prices: Mapping[str, tuple[float, float]] | None = None,
    allow_unpaired: bool = False,
) -> list[Compared]:
    """Every sweep, read from its run folders; two sweeps with one label are told apart
    by their folders' names. ``prices`` ({model: (USD in, out per million tokens)}) price
    the recorded tokens of the sweeps flown by that model (`priced`).

    Raises:
        CavenavError: fewer than two sweeps, sweeps over different caves (other
            difficulty knobs), or a price for a model no sweep flew.
        ConfigError: sweeps that cannot be paired (`unpaired_reason`), unless
            ``allow_unpaired``.
    """
    if len(folders) < 2:
        raise CavenavError("compare needs two sweep folders or more")
    prices = prices or {}
    read = [(Path(f), *read_sweep(Path(f))) for f in folders]
    knobs = {str(f): dict(config.settings.difficulty) for f, config, _ in read}
    if len({repr(k) for k in knobs.values()}) > 1:
        listed = ", ".join(f"{k} in {f}" for f, k in knobs.items())
        raise CavenavError(f"the sweeps flew different caves: difficulty {listed}")
    models = [
        config.pilot.vlm.model if config.pilot.name == "vlm" else None for _, config, _ in read
    ]
    unknown = sorted(set(prices) - set(models))
    if unknown:
        flown = ", ".join(sorted({m for m in models if m})) or "none"
        raise CavenavError(f"--price for {', '.join(unknown)}: no sweep flew it (models: {flown})")
    labels = [config.pilot.label for _, config, _ in read]
    sweeps = []
    for (folder, _, meta), label, model in zip(read, labels, models, strict=True):
        rows = read_rows(folder, write=False)
        if model is not None and model in prices:
            rows = priced(rows, prices[model])
        label = label if labels.count(label) == 1 else f"{label} ({folder.name})"
        sweeps.append(Compared(folder, label, meta, rows))
    reason = unpaired_reason(sweeps)
    if reason and not allow_unpaired:
        raise ConfigError(
            f"{reason}: nothing to pair, so no test would mean anything; "
            "--allow-unpaired shows them side by side without tests"
        )
    return sweeps


def unpaired_reason(sweeps: Sequence[Compared]) -> str | None:
    """Why ``sweeps`` cannot be compared cave by cave, or None: they flew different
    scenario sets (the same family name is another cave in each), or two of them
    completed no cave in common (S1 against S2, seeds 0-19 against 1000-1019)."""
    sets = {str(s.path): s.config.get("scenario_set") for s in sweeps}
    if len(set(sets.values())) > 1:
        listed = ", ".join(f"{v} in {k}" for k, v in sets.items())
        return f"the sweeps flew different scenario sets ({listed})"
    caves = [{(str(r["scenario"]), str(r["seed"])) for r in s.rows if r["outcome"] != "incomplete"}
             for s in sweeps]  # fmt: skip
    for (i, a), (j, b) in itertools.combinations(enumerate(caves), 2):
        if not a & b:
            return f"{sweeps[i].path} and {sweeps[j].path} completed no cave in common"
    return None


def _sweep_facts(sweep: Compared) -> dict[str, Any]:
    pilot = dict(sweep.config.get("pilot") or {})
    options = pilot.get("options") or {}
    return {
        "path": str(sweep.path),
        "label": sweep.label,
        "pilot": pilot.get("name"),
        "model": options.get("model") or pilot.get("policy"),
        "pilot_settings": pilot,
        "episode": sweep.config.get("episode"),
        "sensors": sweep.config.get("sensors"),
        "difficulty": sweep.config.get("difficulty"),
        "cavenav_version": sweep.config.get("cavenav_version"),
        "scenario_set": sweep.config.get("scenario_set"),
        "trials": sweep.config.get("trials", 1),
        "episodes": len(sweep.rows),
    }


def comparison(sweeps: Sequence[Compared]) -> dict[str, Any]:
    """compare.json: the sweeps, the leaderboard (best success first), each family's
    standings, and every pair of sweeps' paired tests (A before B in the order given);
    sweeps that cannot be paired (`unpaired_reason`) get no tests ("pairs" empty, and
    "unpaired" says why)."""
    scenarios = list(dict.fromkeys(str(r["scenario"]) for s in sweeps for r in s.rows))
    board = [group("all", s.label, s.rows) for s in sweeps]
    order = sorted(range(len(sweeps)), key=lambda k: -(board[k]["success_rate"] or 0.0))
    unpaired = unpaired_reason(sweeps)
    pairs = []
    for i, j in [] if unpaired else itertools.combinations(range(len(sweeps)), 2):
        a, b = sweeps[i], sweeps[j]
        pairs.append({"a": a.label, "b": b.label, **compare(a.rows, b.rows)})
    trials = any(pair["trials"] for pair in pairs)
    return {
        "unpaired": unpaired,
        "sweeps": [_sweep_facts(s) for s in sweeps],
        "leaderboard": [board[k] for k in order],
        "per_family": {
            name: [
                group(name, s.label, [r for r in s.rows if r["scenario"] == name]) for s in sweeps
            ]
            for name in scenarios
        },
        "pairs": pairs,
        "trials": trials,
        "methods": f"{METHODS} {TRIAL_METHODS}" if trials else METHODS,
    }


def _rate(standing: Mapping[str, Any]) -> str:
    rate, ci = standing["success_rate"], standing["success_ci95"]
    if rate is None:
        return "-"
    return f"{rate:.0%} ({ci[0]:.0%}-{ci[1]:.0%})"


def board_cells(standing: Mapping[str, Any]) -> list[str]:
    clearance = standing["min_clearance_m"]["mean"]
    cost, p50 = standing["cost_per_success_usd"], standing["model_p50_s"]
    calls, without = standing.get("calls_per_m"), standing.get("steps_without_call_share")
    return [
        standing["pilot"],
        f"{standing['successes']}/{standing['completed']}",
        _rate(standing),
        "-" if standing["spl"] is None else f"{standing['spl']:.3f}",
        str(standing["collisions"]),
        "-" if clearance is None else f"{clearance:.2f}",
        "-" if standing["steps"] is None else f"{standing['steps']:.0f}",
        "-" if calls is None else f"{calls:.2f}",
        "-" if without is None else f"{without:.0%}",
        "-" if standing["tokens_per_success"] is None else f"{standing['tokens_per_success']:.0f}",
        "-" if cost is None else f"{cost:.4f}",
        "-" if p50 is None else f"{p50:.2f} / {standing['model_p95_s']:.2f}",
    ]


BOARD_HEADERS = (
    "pilot",
    "successes",
    "success (95% CI)",
    "SPL",
    "collisions",
    "mean min. clearance (m)",
    "mean steps",
    "model calls per m",
    "steps without a call",
    "tokens per success",
    "USD per success",
    "model s p50 / p95",
)


def board(result: Mapping[str, Any]) -> tuple[list[str], list[list[str]]]:
    """The leaderboard's headers and rows, best first, without the columns no pilot has
    a value in (tokens and cost where no model flew)."""
    rows = [board_cells(standing) for standing in result["leaderboard"]]
    kept = [k for k in range(len(BOARD_HEADERS)) if any(row[k] != "-" for row in rows)]
    return [BOARD_HEADERS[k] for k in kept], [[row[k] for k in kept] for row in rows]


def markdown_table(result: Mapping[str, Any]) -> str:
    """The leaderboard as a Markdown table."""
    headers, rows = board(result)
    lines = ["| " + " | ".join(headers) + " |", "|" + "---|" * len(headers)]
    lines += ["| " + " | ".join(c.replace("|", "\\|") for c in row) + " |" for row in rows]
    return "\n".join(lines) + "\n"


def latex_table(result: Mapping[str, Any]) -> str:
    """The leaderboard as a LaTeX tabular (booktabs rules)."""

    def tex(text: str) -> str:
        for char, escaped in (("\\", r"\textbackslash{}"), ("%", r"\%"), ("_", r"\_"),
                              ("&", r"\&"), ("#", r"\#"), ("$", r"\$")):  # fmt: skip
            text = text.replace(char, escaped)
        return text

    headers, rows = board(result)
    lines = [
        r"\begin{tabular}{l" + "r" * (len(headers) - 1) + "}",
        r"\toprule",
        " & ".join(tex(h) for h in headers) + r" \\",
        r"\midrule",
    ]
    lines += [" & ".join(tex(c) for c in row) + r" \\" for row in rows]
    lines += [r"\bottomrule", r"\end{tabular}"]
    return "\n".join(lines) + "\n"


def _episode_href(sweep: Compared, run_dir: str, out: Path) -> str:
    """The episode's page in its sweep's report where there is one, else its run folder."""
    page = sweep.path / "report" / "episodes" / page_name(Path(run_dir).name)
    target = page if page.is_file() else sweep.path / run_dir
    return Path(os.path.relpath(target.absolute(), out.absolute())).as_posix()


def _discordant(sweeps: Sequence[Compared], result: Mapping[str, Any], out: Path) -> list:
    """Per pair, the caves only one got through: the cave and both episodes' links."""
    by_label = {s.label: s for s in sweeps}
    listed = []
    for pair in result["pairs"]:
        a, b = by_label[pair["a"]], by_label[pair["b"]]
        caves = [
            {
                "cave": cave["cave"],
                "winner": side,
                "a": _episode_href(a, cave["a"], out),
                "b": _episode_href(b, cave["b"], out),
                "outcome_a": cave["outcome_a"],
                "outcome_b": cave["outcome_b"],
            }
            for side in ("a", "b")
            for cave in pair["overall"][f"only_{side}"]
        ]
        listed.append({"a": pair["a"], "b": pair["b"], "caves": caves})
    return listed


def write(sweeps: Sequence[Compared], result: Mapping[str, Any], out: Path) -> Path:
    """Write the `comparison` ``result`` of ``sweeps`` to ``out``: compare.json,
    index.html, leaderboard.md and leaderboard.tex; returns the page.

    Raises:
        RecordingError: ``out`` cannot be written (every file whole or not at all).
    """
    out, (headers, rows) = Path(out), board(result)
    markdown, latex = markdown_table(result), latex_table(result)
    try:
        out.mkdir(parents=True, exist_ok=True)
        write_json(out / "compare.json", result)
        write_atomic(out / "leaderboard.md", markdown)
        write_atomic(out / "leaderboard.tex", latex)
        reports = {
            s.label: Path(os.path.relpath(s.path / "report" / "index.html", out)).as_posix()
            for s in sweeps
            if (s.path / "report" / "index.html").is_file()
        }
        render_page(
            "compare.html.j2",
            out / "index.html",
            title=f"{len(sweeps)} pilots side by side",
            result=result,
            headers=headers,
            board=list(zip(result["leaderboard"], rows, strict=True)),
            reports=reports,
            discordant=_discordant(sweeps, result, out),
            measures=MEASURE_NAMES,
            markdown=markdown,
            latex=latex,
        )
    except OSError as exc:
        raise RecordingError.cannot_write(f"the comparison in {out}", exc) from None
    return out / "index.html"
