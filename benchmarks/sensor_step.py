"""Cost of one sensor step against the bare ray cast it is built on.

For each of S1-S5 (seed 0), at poses along the geometric pilot's own trajectory, prints
the median time of:

- bare cast:  Open3D's `cast_rays` of the 640x480 forward frame (rays prepared in advance)
- full step:  everything the loop pays per step: forward RGB with the underwater optics
              (lamps, backscatter, daylight, rock, marine snow, camera) + raw depth + depth
              PNG, both echo sounders, the clearance query and the swept collision check
- ratio:      full step / bare cast (target: at most 1.5), the median over pairs timed back
              to back, so that a machine that slows down between pairs cancels out
- fastest:    the fastest full step / the fastest bare cast: a shared machine only ever
              adds time, so this is the code's own ratio with the least of the noise
              (the target is judged on the median ratio)
- fresh step: the full step the first time at each pose, right after the geometric pilot
              decided there, as an episode meets it. It once cost a third more than
              the repeats: not cold caches but the pilot's BLAS threads, still spinning
              on both cores when the cast began (its product is now a numba kernel)
- set-up:     building the rig once per cave: the per-triangle light table (rays from
              every triangle) and the backscatter table, cold (an empty cache; a
              later process reads the light table from the cache instead)

The two timings alternate at each pose, so that a busy machine slows both alike.

Run: make bench   (or: python benchmarks/sensor_step.py [--poses N] [--repeats N])
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time

from cavenav.motion.kinematics import apply
from cavenav.pilots.geometric import GeometricPilot
from cavenav.sensors.rig import SensorConfig, SensorRig
from cavenav.world.collision import VehicleBody, clearance, swept_collision
from cavenav.world.raycast import RayCaster
from cavenav.world.scenarios import SCENARIOS, load_scenario


def _ms(fn) -> float:  # noqa: ANN001
    start = time.perf_counter()
    fn()
    return 1e3 * (time.perf_counter() - start)


def bench(name: str, poses: int, repeats: int) -> tuple[float, float, float, float, float, float]:
    scenario = load_scenario(name, seed=0)
    caster = RayCaster(scenario.mesh)
    with tempfile.TemporaryDirectory() as empty:
        os.environ["CAVENAV_CACHE"], cache = empty, os.environ.get("CAVENAV_CACHE")
        start = time.perf_counter()
        rig = SensorRig(caster, SensorConfig(seed=poses))  # a seed no earlier rig used: cold
        setup = time.perf_counter() - start
        if cache is None:
            del os.environ["CAVENAV_CACHE"]
        else:
            os.environ["CAVENAV_CACHE"] = cache
    body = VehicleBody()
    pilot = GeometricPilot()
    pose = scenario.start
    frame_rays = rig.config.camera.width * rig.config.camera.height
    rig.observe(pose)  # compile the kernels, warm the caches
    bare, full, fresh = [], [], []
    for _ in range(poses):
        obs = rig.observe(pose)
        nxt = apply(pose, pilot.decide(obs).action)

        def step(pose=pose, nxt=nxt) -> None:
            rig.observe(pose)
            gap = clearance(caster, pose)
            swept_collision(caster, body, pose, nxt, gap)

        fresh.append(_ms(step))  # right after the pilot, as in an episode
        # The forward frame's rays at this pose, as the step just cast them (computing
        # them here with a numpy product would leave BLAS threads spinning on the cores).
        rays = caster._o3d.core.Tensor.from_numpy(rig._rays[:frame_rays].copy())
        for _ in range(repeats):
            bare.append(_ms(lambda rays=rays: caster._scene.cast_rays(rays)))
            full.append(_ms(step))
        pose = nxt
    ratio = statistics.median(f / b for b, f in zip(bare, full, strict=True))
    fastest = min(full) / min(bare)
    return (
        statistics.median(bare), statistics.median(full), ratio, fastest, setup,
        statistics.median(fresh),
    )  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--poses", type=int, default=8, help="poses per scenario")
    parser.add_argument("--repeats", type=int, default=5, help="timings per pose")
    args = parser.parse_args()
    print(
        f"{'scenario':<9} {'triangles':>9} {'bare cast ms':>13} {'full step ms':>13} "
        f"{'ratio':>6} {'fastest':>8} {'set-up s':>9} {'fresh step ms':>14}"
    )
    ratios, fastest_ratios = [], []
    for name in SCENARIOS:
        bare, full, ratio, fastest, setup, fresh = bench(name, args.poses, args.repeats)
        triangles = load_scenario(name, seed=0).mesh.triangle_count
        ratios.append(ratio)
        fastest_ratios.append(fastest)
        print(
            f"{name:<9} {triangles:>9,} {bare:>13.1f} {full:>13.1f} {ratio:>6.2f} {fastest:>8.2f} "
            f"{setup:>9.2f} {fresh:>14.1f}"
        )
    print(
        f"median ratio {statistics.median(ratios):.2f} (target <= 1.5); "
        f"median of the fastest ratios {statistics.median(fastest_ratios):.2f}"
    )


if __name__ == "__main__":
    main()
