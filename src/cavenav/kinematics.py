"""The pose update of SPEC section 5, exactly, with no dynamics.

    psi' = psi + dpsi
    x'   = x + df * sin(psi') - dr * cos(psi')
    y'   = y - df * cos(psi') - dr * sin(psi')
    z'   = z + dz

The vehicle first turns in place, then translates along a straight line in the new
heading; collision checks sweep the body through exactly these two phases.
"""

from __future__ import annotations

import math

from cavenav.types import Action, Pose

__all__ = ["apply", "wrap_angle"]


def wrap_angle(psi: float) -> float:
    """Wrap an angle in radians to [-pi, pi)."""
    return (psi + math.pi) % (2.0 * math.pi) - math.pi


def apply(pose: Pose, action: Action) -> Pose:
    """Return the pose after ``action``; yaw is wrapped to [-pi, pi)."""
    psi = pose.psi + math.radians(action.yaw_deg)
    df, dr = action.forward, action.right
    return Pose(
        x=pose.x + df * math.sin(psi) - dr * math.cos(psi),
        y=pose.y - df * math.cos(psi) - dr * math.sin(psi),
        z=pose.z + action.up,
        psi=wrap_angle(psi),
    )
