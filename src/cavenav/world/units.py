"""Units of a cave mesh: whether the passage is a plausible size for the vehicle.

Most mesh formats carry no unit at all, so `check_units` looks at the passage itself and
warns when it is implausibly large or small for the vehicle, naming the likely unit and
the ``scale`` that fixes it. Measuring the passage casts rays, so this sits above both
`cavenav.world.mesh` and `cavenav.world.raycast`, which the cast is built on.
"""

from __future__ import annotations

import math
import warnings

import numpy as np

from cavenav.core.errors import CavenavWarning
from cavenav.core.types import VehicleBody
from cavenav.world.mesh import CaveMesh, sphere_directions
from cavenav.world.raycast import RayCaster

__all__ = [
    "PLAUSIBLE_PASSAGE_M",
    "TYPICAL_PASSAGE_M",
    "check_units",
    "likely_scale",
    "passage_size",
]

PLAUSIBLE_PASSAGE_M = (0.3, 30.0)
"""Passage sizes (about the width, metres) that a cave for this vehicle can have.

Below 0.3 m not even the 0.34 m wide vehicle fits through; above 30 m the passage is
wider than the largest flooded galleries a small ROV explores, and more than 60 times
the vehicle's length. A mesh drawn in centimetres, millimetres or inches and read as
metres lands far outside (a 5 m passage reads 500 m, 5,000 m or 197 m), and one read
with a scale that was meant for another file can land below. Feet (3.3 times) stay
inside for most passages: no rule on size alone can tell them apart.
"""

# What the caves shipped with cavenav measure by `passage_size` (5-8.5 m: the OSRF tiles,
# S1-S5): a suggested scale aims here, so that among units that all land inside the
# plausible range the one making an ordinary cave wins.
TYPICAL_PASSAGE_M = 6.0

# The units meshes are drawn in, metres per unit.
_UNITS = {0.001: "millimetres", 0.01: "centimetres", 0.0254: "inches", 0.3048: "feet",
          1.0: "metres", 1000.0: "kilometres"}  # fmt: skip


def passage_size(mesh: CaveMesh, point: np.ndarray | None = None) -> float:
    """About how wide the passage is, in metres: twice the median distance to the walls
    along 64 rays from ``point`` in all directions.

    In a long tube of radius r the median ray (at 60 degrees from the axis) meets the wall
    at 1.15 r, so this reads 1.15 times the diameter; in a chamber, its size. When there
    is no point, or most rays from it escape (it lies outside the mesh), the smallest
    extent of the bounding box stands in: the width of a single passage, more for a
    whole cave system.

    Args:
        point: (3,) a point inside the passage, e.g. the start position.
    """
    if point is not None:
        directions = sphere_directions(64)
        origins = np.broadcast_to(np.asarray(point, np.float64), directions.shape)
        t = RayCaster(mesh).first_hit(origins, directions)
        hits = t[np.isfinite(t)]
        if len(hits) >= len(directions) // 2:
            return 2.0 * float(np.median(hits))
    return float(np.ptp(mesh.vertices, axis=0).min())


def likely_scale(size_m: float, scale: float = 1.0) -> tuple[float, str] | None:
    """The ``scale`` that brings a passage measured ``size_m`` metres into
    `PLAUSIBLE_PASSAGE_M`, and the unit it means; None when it is plausible already.

    Of the common units (millimetres, centimetres, inches, feet, metres, kilometres)
    that bring it into range, the one that brings it nearest `TYPICAL_PASSAGE_M` on a
    log scale wins: a 5 m passage drawn in centimetres measures about 570 m, and 0.01
    makes it 5.7 m where inches would make 14.5 m. Only when none fits does another
    power of ten stand in. Size alone cannot tell centimetres from inches in every
    cave (the factor is 2.54); the warning says "likely".

    Args:
        size_m: the passage size read with ``scale`` (see `passage_size`).
        scale: the metres per file unit it was read with.
    """
    low, high = PLAUSIBLE_PASSAGE_M
    if low <= size_m <= high or not (math.isfinite(size_m) and size_m > 0):
        return None
    units = size_m / scale  # the size in the file's own units
    for candidates in (_UNITS, [10.0**k for k in range(-6, 7)]):
        fits = [c for c in candidates if low <= units * c <= high]
        if fits:
            best = min(fits, key=lambda c: abs(math.log(units * c / TYPICAL_PASSAGE_M)))
            return best, _UNITS.get(best, f"units of {best:g} m")
    return None


def check_units(mesh: CaveMesh, point: np.ndarray | None = None) -> None:
    """Warn (`CavenavWarning`) when the passage at ``point`` is implausibly large or small
    for the vehicle, naming the likely unit and the ``scale`` to give.

    Most mesh formats carry no unit, and a cave drawn in centimetres and read as metres
    is flown 100 times too large without any error: every wall is far, every step safe.

    Args:
        point: (3,) where the vehicle starts, in metres; None measures the bounding box.
    """
    size = passage_size(mesh, point)
    found = likely_scale(size, mesh.scale)
    if found is None:
        return
    new, unit = found
    low, high = PLAUSIBLE_PASSAGE_M
    where = "around the start" if point is not None else "across its bounding box"
    warnings.warn(
        f"{mesh.name}: the passage {where} measures about {size:,.3g} m across (read with "
        f"scale = {mesh.scale:g}), implausible for a {VehicleBody().length:g} m vehicle "
        f"({low:g}-{high:g} m expected); the mesh is likely in {unit}: set `scale = {new:g}` "
        "in the scenario file (metres per mesh unit), with the start and exits in metres",
        CavenavWarning,
        stacklevel=2,
    )
