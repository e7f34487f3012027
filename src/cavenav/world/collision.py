"""Clearance and swept collision of the vehicle body.

One command can move the vehicle more than 2 m, so checking only the end pose would let
it tunnel through a thin wall. The kinematics turn in place and then translate in a
straight line (SPEC section 5); the check sweeps the body's hull through both phases
with rays: chords between successive yaw samples for the turn, and one ray per hull
point along the translation.
"""

from __future__ import annotations

import math

import numpy as np

from cavenav.core.types import Pose, VehicleBody  # the body is a plain value shared by every layer
from cavenav.world.raycast import RayCaster

__all__ = ["VehicleBody", "clearance", "swept_collision"]


def clearance(caster: RayCaster, pose: Pose) -> float:
    """Distance in metres from the vehicle's centre to the nearest surface."""
    return float(caster.distance(pose.position[None])[0])


def swept_collision(
    caster: RayCaster,
    body: VehicleBody,
    start: Pose,
    end: Pose,
    start_clearance: float | None = None,
) -> bool:
    """Whether the body touches a surface while moving from ``start`` to ``end``.

    Args:
        start_clearance: clearance at ``start`` if already known; when it exceeds the
            whole move plus the body radius, nothing can be hit and no ray is cast.
    """
    move = end.position - start.position
    if start_clearance is None:
        start_clearance = clearance(caster, start)
    if start_clearance > float(np.linalg.norm(move)) + body.bounding_radius + 1e-3:
        return False

    origins, segments = [], []
    # Turn in place: chords between hull positions at yaw steps of at most 10 degrees.
    dpsi = math.remainder(end.psi - start.psi, 2 * math.pi)
    n_turn = max(1, math.ceil(abs(math.degrees(dpsi)) / 10.0))
    previous = body.world_points(start)
    for k in range(1, n_turn + 1):
        current = body.world_points(Pose(start.x, start.y, start.z, start.psi + dpsi * k / n_turn))
        origins.append(previous)
        segments.append(current - previous)
        previous = current
    # Translate: every hull point along the straight move.
    origins.append(previous)
    segments.append(np.broadcast_to(move, previous.shape))
    # The body at rest at the end: hull edges and diagonals through the centre.
    final = body.world_points(end)
    centre = end.position
    origins.append(np.broadcast_to(centre, final.shape))
    segments.append(final - centre)

    o = np.concatenate(origins)
    d = np.concatenate(segments)
    moving = np.linalg.norm(d, axis=1) > 1e-9
    if not moving.any():
        return False
    t = caster.first_hit(o[moving], d[moving])
    return bool((t <= 1.0).any())
