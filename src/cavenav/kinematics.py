"""The pose update of SPEC section 5, exactly, with no dynamics.

    psi' = psi + dpsi
    x'   = x + df * sin(psi') - dr * cos(psi')
    y'   = y - df * cos(psi') - dr * sin(psi')
    z'   = z + dz

The vehicle first turns in place, then translates along a straight line in the new
heading; collision checks sweep the body through exactly these two phases.

Who carries an action out is a `Motion`: these kinematics (`Kinematic`, the simulator's
default) or a vehicle that reports where it got to (`cavenav.vehicle.mavlink`).
"""

from __future__ import annotations

import math
from typing import Protocol

from cavenav.types import Action, Pose

__all__ = ["Kinematic", "Motion", "apply", "turn_deg", "wrap_angle"]


def wrap_angle(psi: float) -> float:
    """Wrap an angle in radians to [-pi, pi)."""
    return (psi + math.pi) % (2.0 * math.pi) - math.pi


def turn_deg(psi: float, other: float) -> float:
    """The smallest turn between two headings in radians, in degrees (0 to 180)."""
    return abs(math.degrees(wrap_angle(psi - other)))


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


class Motion(Protocol):
    """Carries out actions: the environment asks it where each action took the vehicle."""

    def start(self, pose: Pose) -> Pose:
        """The vehicle begins at ``pose`` (the scenario's start); where it is."""
        ...

    def move(self, pose: Pose, action: Action) -> Pose:
        """Carry out ``action`` from ``pose``; the pose reached."""
        ...


class Kinematic:
    """`apply`, exactly: the pose commanded is the pose reached."""

    def start(self, pose: Pose) -> Pose:
        return pose

    def move(self, pose: Pose, action: Action) -> Pose:
        return apply(pose, action)
