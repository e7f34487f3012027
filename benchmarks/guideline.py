"""The cave line: flights with and without it, and what drawing it costs.

    .venv/bin/python benchmarks/guideline.py     # about 15 minutes on 2 cores

Flies the VLM pilot against the project's stand-in model server (tests/vlm_server.py: an
OpenAI-compatible server whose "model" is the geometric pilot reading each request's
depth image; it never looks at the colour image) and the geometric pilot itself, over S1
and S3 (seeds 0-2 by default), each cave with and without the guideline (``--guideline``:
the same rock, plus the line), and prints in one run:

- for each pilot, with and without the line: successes, collisions, mean steps and mean
  path length, and how many episodes flew the very same actions with the line as without
  it;
- what the line costs the sensor step: the rig's observation (640x480, every sensor) at
  the geometric pilot's poses through S1 seed 0 with the line, with and without it, the
  two timed in turn at each pose (median ms); how often the line was in view and how many
  pixels it touched; and how long laying it took.

Neither pilot looks at the colour image, and the VLM prompt's sentence about the line
means nothing to the stand-in: the line can change a flight only through the depth
image, which takes it where it covers half a pixel or more (within about 4 m of the
lens). The honest expectation is no difference, but where a flight passes within a metre
of the line, which the depth camera then sees as a thin obstacle.

    .venv/bin/python benchmarks/guideline.py --frame docs/guideline/s1-line.jpg

writes the guide's picture instead: S1 seed 0 where the line is 1.5-3 m away, with the
line and without it, and the part it crosses three times enlarged.
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from PIL import Image

from cavenav.core.types import Pose
from cavenav.episode.loop import EpisodeResult, run_episode
from cavenav.episode.settings import EpisodeConfig
from cavenav.evaluation.sweep import parse_seeds
from cavenav.pilots.factory import PilotSpec, VLMOptions
from cavenav.pilots.geometric import GeometricPilot
from cavenav.sensors.camera import camera_to_world
from cavenav.sensors.rig import SensorConfig, SensorRig
from cavenav.world.raycast import RayCaster
from cavenav.world.scenarios import load_scenario

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from tests.vlm_server import FakeVLM  # noqa: E402 - the project's stand-in model server

QUIET = EpisodeConfig(save_frames=False, plots=False)


def flights(
    pilot: str, base_url: str, families: list[str], seeds: tuple[int, ...]
) -> dict[bool, list[EpisodeResult]]:
    """Each cave flown by ``pilot`` ("geometric" or "stand-in"), without the line, then
    with it, in the same order every run (the stand-in remembers an episode's requests)."""
    flown: dict[bool, list[EpisodeResult]] = {False: [], True: []}
    for family in families:
        for seed in seeds:
            cave = load_scenario(family, seed)
            for line in (False, True):
                if pilot == "geometric":
                    flyer = GeometricPilot()
                else:
                    flyer = PilotSpec(
                        "vlm", VLMOptions(model="stand-in", base_url=base_url)
                    ).build()
                result = run_episode(cave, flyer, replace(QUIET, guideline=line))
                flown[line].append(result)
                print(
                    f"  {pilot} {family} seed {seed} {'with' if line else 'without'} the line: "
                    f"{result.termination}, {result.summary['steps']} steps",
                    flush=True,
                )
    return flown


def table_rows(pilot: str, flown: dict[bool, list[EpisodeResult]]) -> list[str]:
    """The README's rows for ``pilot``: without, then with the line."""
    rows = []
    for line in (False, True):
        results = flown[line]
        same = sum(
            [s["action"] for s in a.steps] == [s["action"] for s in b.steps]
            for a, b in zip(flown[False], results, strict=True)
        )
        steps = statistics.mean(r.summary["steps"] for r in results)
        path = statistics.mean(r.summary["path_length_m"] for r in results)
        rows.append(
            f"| {pilot} | {'on' if line else 'off'} | "
            f"{sum(r.success for r in results)}/{len(results)} | "
            f"{sum(r.summary['collisions'] for r in results)} | {steps:.1f} | {path:.1f} | "
            f"{same}/{len(results)} |"
        )
    return rows


def sensor_cost(poses_wanted: int, repeats: int) -> None:
    """Print the sensor step's cost with and without the line, along S1 seed 0."""
    cave = load_scenario("S1", 0)
    start = time.perf_counter()
    laid = cave.with_guideline()
    lay_s = time.perf_counter() - start
    poses = run_episode(laid, GeometricPilot(), QUIET).poses
    poses = poses[:: max(1, len(poses) // poses_wanted)][:poses_wanted]
    caster = RayCaster(cave.mesh)
    on, off = SensorRig(caster, SensorConfig(), laid.guideline), SensorRig(caster, SensorConfig())
    on.observe(poses[0]), off.observe(poses[0])  # compile, warm the caches
    with_line, without, touched = [], [], []
    for pose in poses:
        for _ in range(repeats):
            for rig, times in ((off, without), (on, with_line)):
                begin = time.perf_counter()
                rig.observe(pose)
                times.append(1e3 * (time.perf_counter() - begin))
        lined, bare = on.render(pose, radiance=True), off.render(pose, radiance=True)
        assert lined.radiance is not None and bare.radiance is not None
        touched.append(int((lined.radiance != bare.radiance).any(axis=2).sum()))
    off_ms, on_ms = statistics.median(without), statistics.median(with_line)
    print(
        f"\nsensor step, S1 seed 0, 640x480, {len(poses)} poses x {repeats}: without the line "
        f"{off_ms:.1f} ms, with it {on_ms:.1f} ms ({100 * (on_ms / off_ms - 1):+.1f}%); the "
        f"line in view at {sum(t > 0 for t in touched)}/{len(poses)} poses, touching "
        f"{int(np.median(touched))} pixels (median; most {max(touched)}); laying it "
        f"{1e3 * lay_s:.0f} ms ({len(laid.guideline.ties)} ties, "  # type: ignore[union-attr]
        f"{laid.guideline.length_m:.1f} m)"  # type: ignore[union-attr]
    )


def nearest_in_view(rig: SensorRig, pose: Pose, points: np.ndarray, rock: np.ndarray) -> float:
    """How far from the lens the nearest of ``points`` (n, 3) is that the camera at
    ``pose`` sees in front of the rock (planar depth ``rock``, (H, W)); inf for none."""
    camera = rig.config.camera
    local = (points - rig.camera_position(pose)) @ camera_to_world(pose)
    local = local[local[:, 2] > 0.05]
    col = (camera.focal_px * local[:, 0] / local[:, 2] + camera.width / 2).astype(int)
    row = (camera.focal_px * local[:, 1] / local[:, 2] + camera.height / 2).astype(int)
    inside = (col >= 0) & (col < camera.width) & (row >= 0) & (row < camera.height)
    depth, col, row = local[inside, 2], col[inside], row[inside]
    seen = depth < rock[row, col]
    return float(depth[seen].min()) if seen.any() else math.inf


def write_frame(path: Path) -> None:
    """Write the frame of S1 seed 0 at the pose of the geometric pilot's flight with the
    line 1.5-3 m away where it touches the most pixels: with the line, without it, and
    both of the part the line crosses, three times enlarged."""
    cave = load_scenario("S1", 0)
    laid = cave.with_guideline()
    assert laid.guideline is not None
    ties = laid.guideline.ties
    share = np.linspace(0.0, 1.0, 200)[:, None]
    points = np.concatenate([a + share * (b - a) for a, b in zip(ties[:-1], ties[1:], strict=True)])
    caster = RayCaster(cave.mesh)
    on, off = SensorRig(caster, SensorConfig(), laid.guideline), SensorRig(caster, SensorConfig())
    found = []
    for pose in run_episode(laid, GeometricPilot(), QUIET).poses:
        lined, bare = on.render(pose, radiance=True), off.render(pose, radiance=True)
        assert lined.radiance is not None and bare.radiance is not None
        touched = (lined.radiance != bare.radiance).any(axis=2)
        if 1.5 <= nearest_in_view(on, pose, points, bare.depth_m) <= 3.0:
            found.append((int(touched.sum()), lined, bare, touched))
    _, lined, bare, touched = max(found, key=lambda each: each[0])
    rows, cols = np.nonzero(touched)
    top = int(np.clip(np.median(rows) - 75, 0, lined.rgb.shape[0] - 150))
    left = int(np.clip(np.median(cols) - 107, 0, lined.rgb.shape[1] - 213))
    crop = np.concatenate([frame.rgb[top : top + 150, left : left + 213] for frame in (lined, bare)], axis=1)  # fmt: skip  # noqa: E501
    enlarged = np.asarray(Image.fromarray(crop).resize((1280, 450), Image.Resampling.NEAREST))
    full = np.concatenate([lined.rgb, bare.rgb], axis=1)
    Image.fromarray(np.concatenate([full, enlarged], axis=0)).save(path, quality=90)
    print(f"frame: {path} ({int(touched.sum())} pixels touched by the line)")


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--families", default="S1,S3", help="comma-separated families")
    parser.add_argument("--seeds", default="0-2", help="cave seeds, e.g. 0-2 or 0,4")
    parser.add_argument("--poses", type=int, default=20, help="poses timed for the cost")
    parser.add_argument("--repeats", type=int, default=3, help="timings per pose")
    parser.add_argument(
        "--frame", type=Path, help="only write a frame of S1 with the line, and without it"
    )
    args = parser.parse_args()
    if args.frame:
        write_frame(args.frame)
        return
    families, seeds = args.families.split(","), parse_seeds(args.seeds)
    rows = []
    with FakeVLM() as server:
        for pilot in ("stand-in", "geometric"):
            rows += table_rows(pilot, flights(pilot, server.base_url, families, seeds))
    print(f"\n{', '.join(families)}, seeds {args.seeds}:\n")
    print("| pilot | line | success | collisions | mean steps | mean path m | same actions |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    print("\n".join(rows))
    sensor_cost(args.poses, args.repeats)


if __name__ == "__main__":
    main()
