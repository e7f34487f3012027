"""The README's gallery: what a pilot sees in each water, one frame per cave family.

For each water preset, renders S1-S5 (seed 0, default optics but the water) from the
pose two fifths of the way along the geometric pilot's path (`passage_poses`, as
`cavenav render` picks its views), and writes one strip per water: five frames of
320x240 side by side, captioned with the family. Run it on two versions of the code to
compare them:

    python benchmarks/gallery.py --out docs/gallery --label after

writes docs/gallery/after-clear.jpg, after-ocean.jpg, ... (about a minute; JPEG at
quality 88, so the README's pictures stay small).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import imageio.v3 as iio
import numpy as np

from cavenav.episode.gallery import passage_poses
from cavenav.sensors.image_stats import downscale
from cavenav.sensors.optics import WATER_TYPES, Optics
from cavenav.sensors.rig import SensorConfig, SensorRig
from cavenav.world.raycast import RayCaster
from cavenav.world.scenarios import load_scenario

FAMILIES = ("S1", "S2", "S3", "S4", "S5")


def strip(water: str, poses: dict) -> np.ndarray:
    """(240, 5 * 320 + 4 * 4, 3) uint8: one frame per family, 4-pixel black gaps."""
    frames = []
    for name in FAMILIES:
        scenario = load_scenario(name, seed=0)
        config = SensorConfig(optics=Optics(water=water))
        rig = SensorRig(RayCaster(scenario.mesh), config)
        frames.append(np.round(downscale(rig.observe(poses[name]).rgb)).astype(np.uint8))
    gap = np.zeros((frames[0].shape[0], 4, 3), np.uint8)
    parts = [part for frame in frames for part in (frame, gap)][:-1]
    return np.concatenate(parts, axis=1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("docs/gallery"))
    parser.add_argument("--label", default="after", help="file name prefix, e.g. before")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    poses = {}
    for name in FAMILIES:
        views = passage_poses(load_scenario(name, seed=0), count=6)
        poses[name] = views[min(2, len(views) - 1)][0]
    for water in WATER_TYPES:
        path = args.out / f"{args.label}-{water}.jpg"
        iio.imwrite(path, strip(water, poses), quality=88)
        print(path)


if __name__ == "__main__":
    main()
