"""The documentation's gallery (docs/guides/camera-and-water.md, and the README's picture):
what a pilot sees in each water, one frame per cave family.

For each water preset, renders S1-S5 (seed 0, default optics but the water) from the
pose two fifths of the way along the geometric pilot's path (`passage_poses`, as
`cavenav render` picks its views), and writes one strip per water: five frames of
320x240 side by side, S1 to S5 from left to right. Run it on two versions of the code to
compare them:

    python benchmarks/gallery.py --out docs/gallery --label after

writes docs/gallery/after-clear.jpg, after-ocean.jpg, ... (about a minute; JPEG at
quality 88, so the documentation's pictures stay small).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import imageio.v3 as iio
import numpy as np

from cavenav.core.types import Pose
from cavenav.episode.gallery import passage_poses
from cavenav.sensors.image_stats import downscale
from cavenav.sensors.optics import CAVE_WATERS, Optics
from cavenav.sensors.rig import SensorConfig, SensorRig
from cavenav.world.raycast import RayCaster
from cavenav.world.scenarios import load_scenario

FAMILIES = ("S1", "S2", "S3", "S4", "S5")


def strip(water: str, views: list[tuple[RayCaster, Pose]]) -> np.ndarray:
    """(240, 5 * 320 + 4 * 4, 3) uint8: one frame per family, 4-pixel black gaps."""
    frames = []
    for caster, pose in views:
        rig = SensorRig(caster, SensorConfig(optics=Optics(water=water)))
        frames.append(np.round(downscale(rig.observe(pose).rgb)).astype(np.uint8))
    gap = np.zeros((frames[0].shape[0], 4, 3), np.uint8)
    parts = [part for frame in frames for part in (frame, gap)][:-1]
    return np.concatenate(parts, axis=1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("docs/gallery"))
    parser.add_argument("--label", default="after", help="file name prefix, e.g. before")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    views = []
    for name in FAMILIES:
        scenario = load_scenario(name, seed=0)
        along = passage_poses(scenario, count=6)
        views.append((RayCaster(scenario.mesh), along[min(2, len(along) - 1)][0]))
    for water in CAVE_WATERS:
        path = args.out / f"{args.label}-{water}.jpg"
        iio.imwrite(path, strip(water, views), quality=88)
        print(path)


if __name__ == "__main__":
    main()
