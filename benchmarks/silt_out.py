"""A silt-out: the crawl family with the silt raised by the vehicle's own thrusters, and
the geometric pilot on a stereo depth camera that the silt blinds: with its depth alone,
with the scanning sonar (Ping360) too, and with the forward multibeam too; and, for
reference, on the simulator's exact depth, which no silt blinds (as every flight was
before there was a stereo camera).

Flies four `cavenav eval` sweeps over the same caves (seeds 1000-1004 by default: held
out from the training seeds), then `cavenav compare` of the four, and prints the table
(success, collisions, progress, steps) and where the comparison page is.

Run: python benchmarks/silt_out.py [--seeds 1000-1004] [--workers 2] [--out DIR]
"""

from __future__ import annotations

import argparse
import csv
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

SENSORS = {
    "exact depth (blind to silt, as before)": ["--depth-source", "exact"],
    "stereo depth only": ["--depth-source", "stereo"],
    "stereo + Ping360": ["--depth-source", "stereo", "--sonar", "ping360"],
    "stereo + multibeam": ["--depth-source", "stereo", "--sonar", "multibeam"],
}


def sweep(label: str, flags: list[str], seeds: str, workers: int, out: Path) -> Path:
    folder = out / label.split(" (")[0].replace(" + ", "-").replace(" ", "-")
    command = [
        sys.executable, "-m", "cavenav.cli", "eval", "--scenarios", "crawl", "--seeds", seeds,
        "--pilot", "geometric", "--silt-out", *flags,
        "--frames", "none", "--no-report", "--workers", str(workers), "--out", str(folder),
    ]  # fmt: skip
    subprocess.run(command, check=True, stdout=subprocess.DEVNULL)
    return folder


def row(label: str, folder: Path) -> str:
    with open(folder / "results.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    success = sum(r["success"] == "True" for r in rows)
    collisions = sum(int(r["collisions"]) for r in rows)
    progress = statistics.mean(float(r["progress_m"]) for r in rows)
    steps = statistics.mean(int(r["steps"]) for r in rows)
    return f"| {label} | {success}/{len(rows)} | {collisions} | {progress:.1f} | {steps:.0f} |"


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--seeds", default="1000-1004")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    out = args.out or Path(tempfile.mkdtemp(prefix="silt-out-"))
    folders = {
        label: sweep(label, flags, args.seeds, args.workers, out)
        for label, flags in SENSORS.items()
    }
    header = ("sensors (silt-out on)", "success", "collisions", "progress, m", "steps")
    print("| " + " | ".join(header) + " |")
    print("| --- | --- | --- | --- | --- |")
    for label, folder in folders.items():
        print(row(label, folder))
    compare = [sys.executable, "-m", "cavenav.cli", "compare", *map(str, folders.values())]
    subprocess.run([*compare, "--out", str(out / "compare")], check=True)
    print(f"comparison page: {out / 'compare' / 'index.html'}")


if __name__ == "__main__":
    main()
