"""Episode metrics of SPEC section 7, computed from the per-step records."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from cavenav.core.types import Pose

__all__ = ["path_length", "summarise_clearance"]


def path_length(poses: Sequence[Pose]) -> float:
    """Sum of straight-line moves between consecutive poses, metres."""
    if len(poses) < 2:
        return 0.0
    p = np.array([pose.position for pose in poses])
    return float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum())


def summarise_clearance(
    clearances: Sequence[float], standoff_m: float
) -> dict[str, float | int | None]:
    """Minimum, mean and the number of poses closer than the standoff."""
    c = np.asarray(clearances, np.float64)
    if c.size == 0:
        return {"min_clearance_m": None, "mean_clearance_m": None, "steps_below_standoff": 0}
    return {
        "min_clearance_m": round(float(c.min()), 4),
        "mean_clearance_m": round(float(c.mean()), 4),
        "steps_below_standoff": int((c < standoff_m).sum()),
    }
