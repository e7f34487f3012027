"""`cavenav fly --sim` against ArduSub's own software-in-the-loop build (the real autopilot
with its own vehicle physics), from the surface, in manual and guided modes (issue 46).

Each flight starts a fresh SITL (the vehicle floats at the surface, disarmed), runs
``cavenav fly --sim CAVE --yes --mode MODE --no-frames`` against it with the geometric
pilot and the shield, and reads the run folder: how the episode ended, its collisions and
clearance, the drift between each move asked and the pose reached, how the moves ended
(reached, settled off target, timeout), the way to the start depth, and whether the
vehicle's last heartbeat said disarmed.

Needs the SITL binary, which cavenav does not ship: ``CAVENAV_ARDUSUB=PATH`` (the binary
or its folder, with ArduPilot's sub.parm beside it).

Run: CAVENAV_ARDUSUB=../shared/sitl python benchmarks/ardusub_sitl.py
         [--caves S4,S1] [--modes manual,guided] [--trials 3] [--parallel 2] [--out DIR]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from queue import Queue

from cavenav.vehicle.sitl import ARDUSUB_ENV, ardusub_binary, ardusub_sitl

ARMED = 128  # MAV_MODE_FLAG_SAFETY_ARMED


def _last_heartbeat_armed(log: Path) -> bool | None:
    """Whether the vehicle's last HEARTBEAT in the command log said armed."""
    armed = None
    for line in log.read_text().splitlines():
        message = json.loads(line)
        heard = message.get("dir") == "received" and message.get("mavpackettype") == "HEARTBEAT"
        if heard and message.get("type") == 12:  # MAV_TYPE_SUBMARINE
            armed = bool(message["base_mode"] & ARMED)
    return armed


def _fly(binary: Path, flight: tuple[str, str, int], instances: Queue[int], out: Path) -> dict:
    cave, mode, trial = flight
    instance = instances.get()
    folder = out / f"{cave}-{mode}-{trial}"
    began = time.monotonic()
    try:
        with ardusub_sitl(binary, instance, folder / "sitl") as address:
            command = [
                sys.executable, "-m", "cavenav.cli", "fly", "--sim", cave, "--seed", "0",
                "--yes", "--connect", address, "--mode", mode, "--no-frames",
                "--out", str(folder / "runs"),
            ]  # fmt: skip
            done = subprocess.run(command, capture_output=True, text=True, check=False)
    finally:
        instances.put(instance)
    runs = sorted((folder / "runs").glob("*/summary.json"))
    row = {"cave": cave, "mode": mode, "trial": trial, "exit_status": done.returncode,
           "minutes": (time.monotonic() - began) / 60}  # fmt: skip
    if not runs:
        row["error"] = (done.stderr.strip().splitlines() or ["no run folder"])[-1]
        return row
    summary = json.loads(runs[-1].read_text())
    row.update(
        summary=summary, disarmed=not _last_heartbeat_armed(runs[-1].parent / "mavlink.jsonl")
    )
    return row


def _line(row: dict) -> str:
    head = f"{row['cave']:<4} {row['mode']:<7} {row['trial']:>2}"
    if "summary" not in row:
        return f"{head}  failed ({row['exit_status']}): {row.get('error')}"
    s = row["summary"]
    endings = [(s.get("move_endings") or {}).get(e, 0) for e in ("reached", "settled", "timeout")]
    start = s.get("vehicle_start") or {}
    nan = float("nan")
    return (
        f"{head}  {s['termination']:<10} {s['steps']:>5} {s['collisions']:>4} "
        f"{s.get('min_clearance_m') or 0:>7.2f} {s.get('mean_drift_m') or 0:>7.3f} "
        f"{s.get('max_drift_m') or 0:>7.3f} "
        f"{endings[0]:>4}/{endings[1]}/{endings[2]}"
        f"  {start.get('from_depth_m', nan):>5.2f}->{start.get('depth_m', nan):<5.2f}"
        f" {'yes' if row['disarmed'] else 'NO':>8} {row['minutes']:>6.1f}"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--caves", default="S4,S1")
    parser.add_argument("--modes", default="manual,guided")
    parser.add_argument("--trials", type=int, default=3)
    parser.add_argument("--parallel", type=int, default=2, help="SITLs flying at once")
    parser.add_argument("--out", type=Path, default=None, help="keep the run folders here")
    args = parser.parse_args()
    binary = ardusub_binary()
    if binary is None:
        sys.exit(f"set {ARDUSUB_ENV} to ArduSub's SITL binary (or its folder) to run this")
    out = args.out or Path(tempfile.mkdtemp(prefix="ardusub-sitl-"))
    flights = [
        (cave, mode, trial)
        for cave in args.caves.split(",")
        for mode in args.modes.split(",")
        for trial in range(1, args.trials + 1)
    ]
    instances: Queue[int] = Queue()
    for instance in range(args.parallel):
        instances.put(instance)
    print(f"{len(flights)} flights from the surface against {binary}, {args.parallel} at once; "
          f"run folders in {out}", flush=True)  # fmt: skip
    print(
        "cave mode    #  ending     steps coll. min_clr mean_dr max_dr  moves r/s/t  "
        "start depth disarmed   min"
    )
    with ThreadPoolExecutor(args.parallel) as pool:
        for row in pool.map(lambda f: _fly(binary, f, instances, out), flights):
            print(_line(row), flush=True)


if __name__ == "__main__":
    main()
