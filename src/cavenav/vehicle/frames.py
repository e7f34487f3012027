"""Between an autopilot's NED frame and cavenav's world frame, documented both ways.

ArduSub reports ``LOCAL_POSITION_NED`` (north, east, down from its EKF origin, metres)
and ``ATTITUDE.yaw`` (radians, clockwise from north). cavenav's world frame has z up
and a yaw ``psi`` that is counter-clockwise from above, 0 heading along -y (SPEC
section 5). The two are tied by one pairing, made when an episode starts: the pose the
autopilot reports then *is* the scenario's start pose. Without rotation the axes map as

    north = -y,   east = -x,   down = -z,   yaw = -psi

(a proper rotation: psi = 0 heads north; a right turn, psi < 0, heads east), and the
pairing adds a turn about the vertical and a shift so that the start matches, whatever
origin and compass heading the autopilot has. Body-frame commands need no pairing: a
`cavenav.core.types.Action` (forward, right, up, left turn) is (x, y, -z, -yaw) in ArduSub's
``MAV_FRAME_BODY_OFFSET_NED`` and in MANUAL_CONTROL's stick axes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from cavenav.core.types import Action, Pose
from cavenav.motion.kinematics import wrap_angle

__all__ = ["NedFrame", "NedPose", "body_offset", "body_to_ned"]


@dataclass(frozen=True)
class NedPose:
    """A pose as an ArduSub autopilot reports it.

    Attributes:
        north, east, down: metres from the autopilot's origin (down is depth there).
        yaw: radians, clockwise from north seen from above.
    """

    north: float
    east: float
    down: float
    yaw: float

    def to_dict(self) -> dict[str, float]:
        return {
            "north": round(self.north, 4),
            "east": round(self.east, 4),
            "down": round(self.down, 4),
            "yaw_deg": round(math.degrees(self.yaw), 3),
        }


def _unrotated(ned: NedPose) -> tuple[float, float, float, float]:
    """(x, y, z, psi) of ``ned`` with the axes mapped and no pairing."""
    return -ned.east, -ned.north, -ned.down, -ned.yaw


@dataclass(frozen=True)
class NedFrame:
    """The pairing of an autopilot's pose ``ned`` with the world pose ``world``."""

    ned: NedPose
    world: Pose

    @property
    def _turn(self) -> float:
        """How far the world frame is turned from the plainly mapped NED axes."""
        return self.world.psi - _unrotated(self.ned)[3]

    def to_world(self, ned: NedPose) -> Pose:
        """The world pose of the autopilot's ``ned``."""
        x0, y0, z0, _ = _unrotated(self.ned)
        x, y, z, psi = _unrotated(ned)
        c, s = math.cos(self._turn), math.sin(self._turn)
        dx, dy = x - x0, y - y0
        return Pose(
            x=self.world.x + c * dx - s * dy,
            y=self.world.y + s * dx + c * dy,
            z=self.world.z + z - z0,
            psi=wrap_angle(psi + self._turn),
        )

    def to_ned(self, pose: Pose) -> NedPose:
        """The autopilot's pose for the world ``pose`` (the inverse of `to_world`)."""
        x0, y0, z0, _ = _unrotated(self.ned)
        c, s = math.cos(self._turn), math.sin(self._turn)
        dx, dy = pose.x - self.world.x, pose.y - self.world.y
        x, y = x0 + c * dx + s * dy, y0 - s * dx + c * dy
        z = z0 + pose.z - self.world.z
        return NedPose(north=-y, east=-x, down=-z, yaw=wrap_angle(-(pose.psi - self._turn)))


def body_offset(action: Action) -> tuple[float, float, float, float]:
    """``action`` in ArduSub's body-offset NED frame: (forward, right, down) metres and
    the yaw change in radians, clockwise."""
    return action.forward, action.right, -action.up, -math.radians(action.yaw_deg)


def body_to_ned(forward: float, right: float, yaw: float) -> tuple[float, float]:
    """(north, east) of a horizontal body vector at heading ``yaw`` (rad, clockwise from north)."""
    cos_yaw, sin_yaw = math.cos(yaw), math.sin(yaw)
    return forward * cos_yaw - right * sin_yaw, forward * sin_yaw + right * cos_yaw
