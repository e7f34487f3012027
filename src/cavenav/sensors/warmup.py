"""Load (the first time: compile) the sensor kernels before anyone waits for them.

numba compiles the kernels the first time they run on a machine, about a minute on two
cores, and keeps them in its on-disk cache. `make setup` calls `cavenav warmup` so that
a newcomer's first `make demo` does not spend that minute inside its first step.
"""

from __future__ import annotations

import time

import numpy as np
import trimesh

from cavenav.sensors.kernels import free_lengths
from cavenav.sensors.lighting import surface_table
from cavenav.sensors.optics import Optics
from cavenav.sensors.rig import SensorConfig, SensorRig
from cavenav.types import Pose
from cavenav.world.mesh import make_mesh
from cavenav.world.raycast import RayCaster

__all__ = ["warm_up"]


def warm_up() -> float:
    """Render one observation in a small box room with both sounder models; the seconds it took.

    Every kernel a step runs (lighting tables, shading, particles, both sounders, the
    geometric pilot's corridors) runs here once with the types an episode gives it, so
    numba's cache then holds them all.
    """
    started = time.perf_counter()
    box = trimesh.creation.box(extents=(4.0, 20.0, 4.0))
    caster = RayCaster(make_mesh(np.asarray(box.vertices), np.asarray(box.faces), "warm-up"))
    surface_table(caster, Optics(), cached=False)  # the rigs may find it on disk
    for sounder in ("camera", "beam"):
        SensorRig(caster, SensorConfig(sounder=sounder)).observe(Pose(0.0, 5.0, 0.0, 0.0))
    free_lengths(np.zeros((1, 3), np.float32), np.ones((1, 3)), 0.6, 20.0)  # the pilot's
    return time.perf_counter() - started
