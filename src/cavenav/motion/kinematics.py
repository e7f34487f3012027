"""The pose update of SPEC section 5, exactly, with no dynamics.

    psi' = psi + dpsi
    x'   = x + df * sin(psi') - dr * cos(psi')
    y'   = y - df * cos(psi') - dr * sin(psi')
    z'   = z + dz

The vehicle first turns in place, then translates along a straight line in the new
heading; collision checks sweep the body through exactly these two phases.

Who carries an action out is a `Motion`: these kinematics (`Kinematic`, the simulator's
default) or a vehicle that reports where it got to (`cavenav.vehicle.mavlink`), and the
`Drift` between where it got to and where these equations would have put it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from cavenav.core.types import Action, Pose

__all__ = ["Drift", "Kinematic", "Motion", "apply", "carried", "turn_deg", "wrap_angle"]


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


def carried(pose: Pose, north_east_m: tuple[float, float]) -> Pose:
    """``pose`` moved ``north_east_m`` (x, y) by the water, at the depth and heading the
    vehicle holds (`cavenav.world.current.carry` works the distance out)."""
    return Pose(pose.x + north_east_m[0], pose.y + north_east_m[1], pose.z, pose.psi)


@dataclass(frozen=True)
class Drift:
    """How far a move ended from the pose `apply` commands: a vehicle's currents, noise
    and controller, which the kinematics do not have.

    Attributes:
        commanded: the pose `apply` gives for the move.
        metres: distance between the commanded and the reached positions.
        degrees: the turn between the commanded and the reached headings (0 to 180).
    """

    commanded: Pose
    metres: float
    degrees: float

    @classmethod
    def of(cls, pose: Pose, action: Action, reached: Pose) -> Drift:
        """The drift of a move of ``action`` from ``pose`` that ended at ``reached``."""
        commanded = apply(pose, action)
        return cls(
            commanded,
            float(np.linalg.norm(reached.position - commanded.position)),
            turn_deg(reached.psi, commanded.psi),
        )

    def to_info(self) -> dict[str, Any]:
        """The environment's ``info`` keys for it: ``commanded_pose``, ``drift_m``,
        ``drift_deg``."""
        return {
            "commanded_pose": self.commanded.to_dict(),
            "drift_m": self.metres,
            "drift_deg": self.degrees,
        }


class Motion(Protocol):
    """Carries out actions: the environment asks it where each action took the vehicle,
    and how far that is from where the action was commanded to take it."""

    def start(self, pose: Pose) -> Pose:
        """The vehicle begins at ``pose`` (the scenario's start); where it is."""
        ...

    def move(self, pose: Pose, action: Action) -> Pose:
        """Carry out ``action`` from ``pose``; the pose reached."""
        ...

    def drift(self, pose: Pose, action: Action, reached: Pose) -> Drift | None:
        """How far ``reached``, where `move` took the vehicle from ``pose``, is from the
        pose ``action`` commands; None where the two are one by construction."""
        ...


class Kinematic:
    """`apply`, exactly: the pose commanded is the pose reached, so there is no drift."""

    def start(self, pose: Pose) -> Pose:
        return pose

    def move(self, pose: Pose, action: Action) -> Pose:
        return apply(pose, action)

    def drift(self, pose: Pose, action: Action, reached: Pose) -> Drift | None:
        return None
