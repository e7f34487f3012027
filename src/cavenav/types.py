"""The plain values that flow around the loop: pose, action, observation, decision.

This module is a leaf: it imports nothing from cavenav, so every layer can use it.

Conventions (SPEC section 5): metres and radians in world frame, z up; yaw ``psi = 0``
heads along the world's -y axis and a positive yaw turn is counter-clockwise seen from
above, i.e. to the left.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

__all__ = ["Action", "Decision", "Observation", "Pose"]


@dataclass(frozen=True)
class Pose:
    """Vehicle pose: position in metres and yaw ``psi`` in radians (0 = heading -y)."""

    x: float
    y: float
    z: float
    psi: float = 0.0

    @property
    def position(self) -> np.ndarray:
        """(3,) float64 position."""
        return np.array([self.x, self.y, self.z], dtype=np.float64)

    @property
    def forward(self) -> np.ndarray:
        """(3,) unit heading vector; the kinematics move along it for a forward command."""
        return np.array([math.sin(self.psi), -math.cos(self.psi), 0.0])

    @property
    def right(self) -> np.ndarray:
        """(3,) unit vector to the vehicle's right, as a positive ``dr`` moves it."""
        return np.array([-math.cos(self.psi), -math.sin(self.psi), 0.0])

    @property
    def yaw_deg(self) -> float:
        return math.degrees(self.psi)

    @classmethod
    def facing(cls, position: np.ndarray, direction: np.ndarray) -> Pose:
        """A pose at ``position`` heading along the horizontal part of ``direction``."""
        dx, dy = float(direction[0]), float(direction[1])
        x, y, z = (float(v) for v in position)
        return cls(x, y, z, psi=math.atan2(dx, -dy))

    def to_dict(self) -> dict[str, float]:
        return {
            "x": round(self.x, 4),
            "y": round(self.y, 4),
            "z": round(self.z, 4),
            "yaw_deg": round(self.yaw_deg, 3),
        }


@dataclass(frozen=True)
class Action:
    """One increment ``a = (df, dr, dz, dpsi)`` in the body frame.

    Attributes:
        forward: df in metres, positive ahead.
        right: dr in metres, positive to the vehicle's right.
        up: dz in metres, positive up.
        yaw_deg: dpsi in degrees, positive to the left (counter-clockwise from above).
    """

    forward: float = 0.0
    right: float = 0.0
    up: float = 0.0
    yaw_deg: float = 0.0

    @property
    def is_hold(self) -> bool:
        return self.forward == 0 and self.right == 0 and self.up == 0 and self.yaw_deg == 0


@dataclass(frozen=True)
class Observation:
    """What a pilot may see at one step; never the mesh, never the pose.

    Attributes:
        rgb: (H, W, 3) uint8 forward colour image.
        depth_m: (H, W) float32 planar depth in metres; ``inf`` where no surface is hit.
        depth_png: (H, W) uint8 normalised depth (dark near, bright far) as sent to a VLM.
        d_top: range to the ceiling from the upward echo sounder, metres.
        d_bottom: range to the floor from the downward echo sounder, metres.
        depth_range: (D_min, D_max) in metres used for ``depth_png``.
        step: index of the step at which this was observed.
    """

    rgb: np.ndarray
    depth_m: np.ndarray
    depth_png: np.ndarray
    d_top: float
    d_bottom: float
    depth_range: tuple[float, float] = (0.0, 20.0)
    step: int = 0


@dataclass(frozen=True)
class Decision:
    """A pilot's answer: the action, its string form, the justification and the raw text.

    ``raw`` keeps the complete reply (reasoning included) so a run can be audited;
    ``extra`` holds per-step accounting (tokens, latency) that goes into steps.jsonl.
    """

    action: Action
    action_text: str
    justification: str
    raw: str = ""
    extra: dict[str, object] = field(default_factory=dict)
    exchanges: tuple = ()  # model requests and replies behind this decision, if any
