"""Load (the first time: compile) the kernels of a step before anyone waits for them.

numba compiles the sensor kernels and the geometric pilot's the first time they run on a
machine, about a minute on two cores, and keeps them in its on-disk cache. `make setup`
calls `cavenav warmup` so that a newcomer's first `make demo` does not spend that minute
inside its first step.
"""

from __future__ import annotations

import time

import numpy as np
import trimesh

from cavenav.core.types import Pose
from cavenav.pilots.geometric import GeometricPilot
from cavenav.sensors.lighting import surface_table
from cavenav.sensors.optics import Optics
from cavenav.sensors.rig import SensorConfig, SensorRig
from cavenav.world.guideline import Guideline
from cavenav.world.mesh import make_mesh
from cavenav.world.raycast import RayCaster
from cavenav.world.silt import Puff, SiltCloud

__all__ = ["warm_up"]


def warm_up() -> float:
    """Render one observation in a small box room with both sounder models and let the
    geometric pilot decide on it; the seconds it took.

    Every kernel a step runs (lighting tables, shading, particles, silt, a guideline and
    its arrow, both sounders, the pilot's corridors) runs here once with the types an
    episode gives it, so numba's cache then holds them all.
    """
    started = time.perf_counter()
    box = trimesh.creation.box(extents=(4.0, 20.0, 4.0))
    caster = RayCaster(make_mesh(np.asarray(box.vertices), np.asarray(box.faces), "warm-up"))
    surface_table(caster, Optics(), cached=False)  # the rigs may find it on disk
    silt = SiltCloud((Puff((0.0, 3.0, 0.0), 0.5, 10.0),))  # a puff in view, ahead
    across = np.array([[-1.99, 3.0, -0.5], [1.99, 3.0, -0.5]])  # a line across, in view
    arrow = np.array([[0.5, 3.0, -0.5]]), np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 1.0, 0.0]])
    line = Guideline(across, *arrow)
    for sounder in ("camera", "beam"):
        rig = SensorRig(caster, SensorConfig(sounder=sounder), line)
        GeometricPilot().decide(rig.observe(Pose(0.0, 5.0, 0.0, 0.0), silt=silt))
    return time.perf_counter() - started
