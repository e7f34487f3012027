"""Success against current: the geometric pilot, with and without the shield, as the
discharge rises.

    .venv/bin/python benchmarks/currents.py          # 50 caves a cell: about 25 minutes on 2 cores
    .venv/bin/python benchmarks/currents.py --discharges 0,4,8 --seeds 1000-1001

Each discharge is one `cavenav eval` sweep per pilot over the held-out caves (S1-S5 by
default) at 84 x 84 pixels, frames off, with the method's budget of 150 steps. A positive
discharge flows against the vehicle, from the exit toward the start, as out of a spring.
It prints a Markdown table: success with its 95% interval, collisions, how the others
ended, the water's mean and fastest speed met, the mean drift a step and the energy an
episode took. The sweeps stay in --out for `cavenav report` and `cavenav compare`.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

PILOTS = {"geometric": [], "geometric + shield": ["--shield"]}


def sweep(out: Path, discharge: float, shield: list[str], args: argparse.Namespace) -> dict:
    """The "all" group of one sweep's aggregate.json, flown now unless already there."""
    if not (out / "aggregate.json").is_file():
        command = [sys.executable, "-m", "cavenav.cli", "eval", "--pilot", "geometric",
                   "--scenarios", args.scenarios, "--seeds", args.seeds,
                   "--discharge", str(discharge), "--resolution", "84x84", "--frames", "none",
                   "--no-report", "--workers", "2", "--out", str(out), *shield]  # fmt: skip
        subprocess.run(command, check=True, capture_output=True, text=True)
    groups = json.loads((out / "aggregate.json").read_text())["groups"]
    return next(g for g in groups if g["scenario"] == "all")


def speeds(out: Path) -> tuple[float, float]:
    """The mean and the fastest water speed met, over every step of the sweep."""
    met = []
    for steps in (out / "episodes").glob("*/steps.jsonl"):
        met += [json.loads(line).get("current_m_s") for line in steps.read_text().splitlines()]
    met = [m for m in met if m is not None]
    return (sum(met) / len(met), max(met)) if met else (0.0, 0.0)


def row(discharge: float, pilot: str, group: dict, out: Path) -> str:
    low, high = group["success_ci95"] or (0.0, 0.0)
    others = {k: v for k, v in group["outcomes"].items() if k not in ("success", "collision")}
    mean_speed, top_speed = speeds(out)
    drift = _mean_column(out, "mean_drift_m")
    return (
        f"| {discharge:g} | {pilot} | {group['successes']}/{group['completed']} "
        f"({100 * low:.0f}-{100 * high:.0f}%) | {group['collisions']} | "
        f"{', '.join(f'{k} {v}' for k, v in others.items()) or '-'} | "
        f"{mean_speed:.2f} / {top_speed:.2f} | {drift:.2f} | {group['energy_wh']:.2f} |"
    )


def _mean_column(out: Path, column: str) -> float:
    import csv

    with (out / "results.csv").open() as table:
        values = [float(r[column]) for r in csv.DictReader(table) if r[column]]
    return sum(values) / len(values) if values else 0.0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--discharges", default="0,1,2,3,4,6", help="m³/s, comma-separated")
    parser.add_argument("--scenarios", default="S1,S2,S3,S4,S5")
    parser.add_argument("--seeds", default="1000-1009")
    parser.add_argument("--out", type=Path, default=None, help="keep the sweeps here")
    args = parser.parse_args()
    root = args.out or Path(tempfile.mkdtemp(prefix="currents-"))
    print(f"sweeps in {root}; scenarios {args.scenarios}, seeds {args.seeds}\n")
    print("| discharge (m³/s) | pilot | success (95% CI) | collisions | other endings "
          "| current mean / max (m/s) | drift a step (m) | energy (Wh) |")  # fmt: skip
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    started = time.perf_counter()
    for discharge in (float(q) for q in args.discharges.split(",")):
        for pilot, shield in PILOTS.items():
            out = root / f"q{discharge:g}-{'shield' if shield else 'bare'}"
            print(row(discharge, pilot, sweep(out, discharge, shield, args), out), flush=True)
    print(f"\n{time.perf_counter() - started:.0f} s")


if __name__ == "__main__":
    main()
