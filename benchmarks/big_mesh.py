"""A 3-million-triangle user mesh, from the shell to the first step: issue 27's target.

Builds the mesh from the shipped DARPA SubT straight tile (`examples/osrf_cave_straight.toml`,
20,016 triangles): three rounds of midpoint subdivision, then one more on the first faces
until it holds ``--triangles`` (3,000,000 by default, to within two), written as binary
PLY with the tile's scenario file beside it. Where subdivided faces meet the others the
mesh has T-junctions (a midpoint on a neighbour's edge, no crack), which a survey's mesh
would not; ray casting does not mind them. The shape stays the tile's; only the triangle
count grows, which is what costs a user's fine mesh (a photogrammetric survey) its set-up
time and memory: loading and checking the mesh, Open3D's BVH, the lighting tables (rays
from every patch of triangles), the start check.

Then runs `cavenav run FILE --pilot geometric --no-frames --steps N` as a fresh process
(``--runs`` times, with an empty cave cache each, so nothing is read from an earlier run)
and prints:

- ready to fly: from the process's start until the first step is in `steps.jsonl`
- whole run: the process's wall time (the first steps and the plots included)
- peak memory: the process's peak resident set (`getrusage`'s ``ru_maxrss``, Linux's
  kibibytes), in GB of 10^9 bytes

Target (issue 27): ready to fly in under 30 s, peak under 2 GB, with progress shown (the
bar reads "preparing" until the first step).

Run: python benchmarks/big_mesh.py [--triangles N] [--steps N] [--runs N]   (about 20 s a
     run on 2 cores)
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
import tomllib
from pathlib import Path

import numpy as np
import trimesh

TILE = Path(__file__).resolve().parent.parent / "examples" / "osrf_cave_straight.toml"


def fine_mesh(triangles: int) -> trimesh.Trimesh:
    """The tile's mesh subdivided to ``triangles`` triangles, to within two."""
    scenario = tomllib.loads(TILE.read_text())
    mesh = trimesh.load(TILE.parent / scenario["mesh"], force="mesh")
    while len(mesh.faces) * 4 <= triangles:
        mesh = mesh.subdivide()
    more = (triangles - len(mesh.faces)) // 3  # each face split in four adds three
    if more:
        mesh = mesh.subdivide(face_index=np.arange(more))
    return mesh


def write_scenario(mesh: trimesh.Trimesh, folder: Path) -> Path:
    """The mesh as binary PLY and the tile's scenario file pointing at it."""
    mesh.export(folder / "fine.ply")
    text = TILE.read_text()
    scenario = tomllib.loads(text)
    text = text.replace(f'"{scenario["mesh"]}"', '"fine.ply"')
    text = text.replace(f'name = "{scenario["name"]}"', 'name = "fine-mesh"')
    path = folder / "fine.toml"
    path.write_text(text)
    return path


def fly_once(scenario: Path, steps: int, folder: Path) -> tuple[float, float, float]:
    """(seconds to the first step, seconds in all, peak GB) of one `cavenav run`, alone in
    a process whose only child is it, so that ``ru_maxrss`` of the children is its own."""
    out = folder / "runs"
    env = dict(os.environ, CAVENAV_CACHE=str(folder / "cache"))
    command = [
        sys.executable, "-c", "from cavenav.cli import main; main()", "run", str(scenario),
        "--pilot", "geometric", "--no-frames", "--steps", str(steps), "--out", str(out),
    ]  # fmt: skip
    probe = (
        "import resource, subprocess, sys, time\n"
        "start = time.perf_counter()\n"
        "child = subprocess.Popen(sys.argv[1:], stdout=subprocess.DEVNULL)\n"
        "code = child.wait()\n"
        "peak = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss\n"
        "print(code, time.perf_counter() - start, peak)\n"
    )
    start = time.perf_counter()
    probe_process = subprocess.Popen(
        [sys.executable, "-c", probe, *command], env=env, stdout=subprocess.PIPE, text=True
    )
    first = None
    while probe_process.poll() is None:
        if first is None and any(
            p.stat().st_size > 0 for p in out.glob("*/steps.jsonl") if p.is_file()
        ):
            first = time.perf_counter() - start
        time.sleep(0.05)
    code, wall, peak_kb = probe_process.stdout.read().split()
    if int(code) != 0:
        raise SystemExit(f"cavenav run exited with {code}")
    return first if first is not None else float("nan"), float(wall), int(peak_kb) * 1024 / 1e9


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--triangles", type=int, default=3_000_000, help="at least 20,016")
    parser.add_argument("--steps", type=int, default=5, help="steps flown after the start")
    parser.add_argument("--runs", type=int, default=2, help="fresh processes, each timed")
    args = parser.parse_args()
    start = time.perf_counter()
    mesh = fine_mesh(args.triangles)
    if len(mesh.faces) < args.triangles - 2:
        parser.error(f"--triangles: the tile alone has {len(mesh.faces):,}")
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        scenario = write_scenario(mesh, folder)
        size = (folder / "fine.ply").stat().st_size / 2**20
        print(
            f"{len(mesh.faces):,} triangles, {len(mesh.vertices):,} vertices "
            f"({size:.0f} MB of PLY, built in {time.perf_counter() - start:.0f} s)"
        )
        del mesh
        print(f"{'run':>3} {'ready to fly s':>15} {'whole run s':>12} {'peak GB':>8}")
        for run in range(args.runs):
            ready, wall, peak = fly_once(scenario, args.steps, folder / str(run))
            print(f"{run + 1:>3} {ready:>15.1f} {wall:>12.1f} {peak:>8.2f}")
    print("target: ready to fly in under 30 s, peak under 2 GB")


if __name__ == "__main__":
    main()
