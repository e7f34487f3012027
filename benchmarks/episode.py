"""What a whole episode costs, phase by phase: where `cavenav run` spends its time.

Prints, in one run (S4, seed 0, the geometric pilot, caves and kernels cached):

- per step, the median of each phase in warm episodes with and without frames:
  sense (the observation), physics (move, clearance, swept collision), pilot, frames
  (encoding and writing the PNG and EXR images, on the run folder's writer thread, off
  the loop), recording (what the loop itself waits for to hand a step to the writer),
  and the loop's whole step (its wall time over its steps);
- the start-up of a fresh process (imports, the cave, importing Open3D and checking the
  start, the sensor rig with its lighting tables, the first observation and the first
  decision, which load their compiled kernels) and the end (plots, final summary);
- the whole process, `cavenav run S4` from the shell, with and without frames (median of
  3 runs);
- in-episode sense + physics against the isolated full step of `sensor_step.py` (the
  same work: observation, clearance and swept collision), measured in this run: both its
  repeated-pose median and its median the first time at each pose, right after the
  pilot (as in an episode).

Run: python benchmarks/episode.py [--repeats N]
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from collections.abc import Callable
from pathlib import Path
from typing import Any

SCENARIO = "S4"

# A fresh process: what `cavenav run` pays before its first step, phase by phase, in the
# order it pays them (caves, lighting tables and compiled kernels cached, as after one run).
_STARTUP = """
import time
t0 = time.perf_counter()
import cavenav.cli
from cavenav.episode.loop import make_env
from cavenav.episode.settings import EpisodeConfig
from cavenav.pilots.geometric import GeometricPilot
from cavenav.sensors.rig import SensorConfig, SensorRig
from cavenav.core.types import VehicleBody
from cavenav.world.raycast import RayCaster
from cavenav.world.scenarios import load_scenario, validate_start
t1 = time.perf_counter()
cave = load_scenario("{scenario}")
t2 = time.perf_counter()
caster = RayCaster(cave.mesh)
validate_start(cave, caster, VehicleBody())
t3 = time.perf_counter()
rig = SensorRig(caster, SensorConfig())
t4 = time.perf_counter()
observation = rig.observe(cave.start)
t5 = time.perf_counter()
GeometricPilot().decide(observation)
t6 = time.perf_counter()
print(t1 - t0, t2 - t1, t3 - t2, t4 - t3, t5 - t4, t6 - t5)
"""
_STARTUP_PHASES = (
    "imports",
    "cave",
    "Open3D and the start check",
    "sensor rig",
    "first observation",
    "first decision",
)


def _timed(phases: dict[str, list[float]], name: str, fn: Callable[..., Any]) -> Callable[..., Any]:
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        started = time.perf_counter()
        try:
            return fn(*args, **kwargs)
        finally:
            phases[name].append(1e3 * (time.perf_counter() - started))

    return wrapper


def warm_episode(frames: bool, folder: Path) -> dict[str, list[float]]:
    """One episode in this (warm) process; each phase's milliseconds, step by step."""
    from cavenav.episode import run_folder
    from cavenav.episode.loop import run_episode
    from cavenav.episode.run_folder import read_jsonl
    from cavenav.episode.settings import EpisodeConfig
    from cavenav.pilots.geometric import GeometricPilot
    from cavenav.world.scenarios import load_scenario

    phases: dict[str, list[float]] = defaultdict(list)
    folder_class = run_folder.RunFolder
    write_frames, record = folder_class.write_frames, folder_class.record
    folder_class.write_frames = _timed(phases, "frames", write_frames)  # type: ignore[method-assign]
    folder_class.record = _timed(phases, "record", record)  # type: ignore[method-assign]
    try:
        config = EpisodeConfig(save_frames=frames, plots=False)
        run_dir = folder / f"{'frames' if frames else 'no-frames'}-{time.monotonic_ns()}"
        run_episode(load_scenario(SCENARIO), GeometricPilot(), config, run_dir)
    finally:
        folder_class.write_frames, folder_class.record = write_frames, record  # type: ignore[method-assign]
    for step in read_jsonl(run_dir / "steps.jsonl"):
        for key in ("sense", "physics", "pilot"):
            if key in step["timing_ms"]:
                phases[key].append(step["timing_ms"][key])
    phases["recording"] = phases.pop("record")
    if not frames:
        phases["frames"] = [0.0] * len(phases["recording"])
    summary = json.loads((run_dir / "summary.json").read_text())
    phases["step"] = [1e3 * summary["wall_time_s"] / summary["steps"]]
    return phases


def end_of_episode(folder: Path) -> tuple[float, float]:
    """Milliseconds of the plots and of the final summary, for a flown S4 episode."""
    from cavenav.episode.loop import run_episode
    from cavenav.episode.plots import plot_episode
    from cavenav.episode.run_folder import write_json
    from cavenav.episode.settings import EpisodeConfig
    from cavenav.pilots.geometric import GeometricPilot
    from cavenav.world.raycast import RayCaster
    from cavenav.world.scenarios import load_scenario

    cave = load_scenario(SCENARIO)
    result = run_episode(cave, GeometricPilot(), EpisodeConfig(save_frames=False, plots=False))
    started = time.perf_counter()
    plot_episode(
        result.summary, result.poses, result.clearances, cave, RayCaster(cave.mesh), folder
    )
    plots = 1e3 * (time.perf_counter() - started)
    started = time.perf_counter()
    write_json(folder / "summary.json", result.summary)
    return plots, 1e3 * (time.perf_counter() - started)


def whole_process(frames: bool, folder: Path) -> float:
    """Seconds of `cavenav run S4` from the shell."""
    flag = "--frames" if frames else "--no-frames"
    started = time.perf_counter()
    subprocess.run(
        [sys.executable, "-m", "cavenav.cli", "run", SCENARIO, flag, "--out", str(folder)],
        check=True,
        capture_output=True,
    )
    return time.perf_counter() - started


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--repeats", type=int, default=2, help="warm episodes of each kind")
    args = parser.parse_args()
    sys.path.insert(0, str(Path(__file__).parent))
    from sensor_step import bench

    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        warm_episode(False, folder)  # load the kernels, build the cave: later ones are warm
        print(f"{SCENARIO} seed 0, geometric pilot: median ms a step, {args.repeats} warm episodes")
        print(
            f"{'':<10} {'sense':>7} {'physics':>8} {'pilot':>7} {'frames':>7} {'recording':>10} "
            f"{'whole step':>11}"
        )
        medians = {}
        for frames in (True, False):
            merged: dict[str, list[float]] = defaultdict(list)
            for _ in range(args.repeats):
                for key, values in warm_episode(frames, folder).items():
                    merged[key] += values
            m = {key: statistics.median(values) for key, values in merged.items()}
            medians[frames] = m
            kind = "frames" if frames else "no frames"
            print(
                f"{kind:<10} {m['sense']:>7.1f} {m['physics']:>8.1f} {m['pilot']:>7.1f} "
                f"{m['frames']:>7.1f} {m['recording']:>10.1f} {m['step']:>11.1f}"
            )

        _, isolated, *_, fresh = bench(SCENARIO, poses=8, repeats=5)
        for frames in (True, False):
            m = medians[frames]
            in_episode = m["sense"] + m["physics"]
            print(
                f"in-episode sense + physics {'with' if frames else 'without'} frames: "
                f"{in_episode:.1f} ms; isolated full step {isolated:.1f} ms, ratio "
                f"{in_episode / isolated:.2f} (target <= 1.1); the same step the first time at "
                f"each pose {fresh:.1f} ms, ratio {in_episode / fresh:.2f}"
            )

        done = subprocess.run(
            [sys.executable, "-c", _STARTUP.format(scenario=SCENARIO)],
            check=True,
            capture_output=True,
            text=True,
        )
        seconds = [float(x) for x in done.stdout.split()]
        print(
            "start-up of a fresh process, s: "
            + ", ".join(f"{name} {s:.2f}" for name, s in zip(_STARTUP_PHASES, seconds, strict=True))
        )
        plots, summary = end_of_episode(folder)
        print(f"end of an episode, ms: plots {plots:.0f}, final summary {summary:.1f}")
        for frames in (True, False):
            wall = statistics.median(whole_process(frames, folder / "runs") for _ in range(3))
            print(
                f"whole process, cavenav run {SCENARIO} {'--frames' if frames else '--no-frames'}: "
                f"{wall:.1f} s" + (" (target <= 8 s)" if frames else "")
            )


if __name__ == "__main__":
    main()
