"""Dead reckoning and back-projection: where what the vehicle saw lies, from the
observations and the actions it executed alone.

The safety shield's memory of recent depth images, the cave map and the geometric pilot
all place what they saw this way (never by the mesh, never by the true pose), so the
same code runs on a real vehicle, where dead reckoning drifts. One module holds what
they share:

- back-projection: a depth image read at every n-th pixel (`sampling_stride`) becomes
  points in the camera or the body frame (`DepthSamples`);
- dead reckoning: the action executed since the last observation (`executed_since`; its
  translation as the DVL measured it, while the DVL has bottom lock) turns the vehicle by
  dpsi, then translates it by (df, -dr, dz) in its new frame (SPEC section 5,
  `body_step`): points seen before move the other way (`move_points`), and the
  vehicle's pose in the map frame moves forward (`reckon`, `ReckonedPose` with its
  uncertainty).

Body frame: (forward, left, up) in metres from the vehicle's centre; the camera frame is
the same axes from the camera. Map frame: the vehicle's centre at the first observation
is the origin, x its heading then, y to its left, z up; metres.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from cavenav.core.errors import ConfigError
from cavenav.core.types import Action, Observation
from cavenav.sensors.depth import denormalise_depth, pixel_slopes
from cavenav.sensors.dvl import A50
from cavenav.sensors.fusion import readable_depth

__all__ = [
    "COMMANDED_DRIFT",
    "DepthSamples",
    "body_step",
    "executed_since",
    "ReckonedPose",
    "move_points",
    "reckon",
    "sampling_stride",
    "to_body",
    "to_map",
    "translation",
    "yaw_matrix",
]


def sampling_stride(width: int, stride: int | None, columns: int, height: int | None = None) -> int:
    """Every how many pixels a depth image ``width`` wide is read: ``stride``, or, when
    None, as many as keep about ``columns`` of its columns (so that readers tuned at
    640x480 read an 84x84 image whole rather than a handful of its pixels); never more
    than its ``height``, so that a wide, flat image (8192x10) keeps a row.

    Raises:
        ConfigError: a stride or a column count below 1.
    """
    if (stride is not None and stride < 1) or columns < 1:
        raise ConfigError(
            f"stride {stride} and columns {columns}: give a stride of at least 1 (or None) "
            "and at least 1 column"
        )
    chosen = stride if stride is not None else max(1, width // columns)
    return chosen if height is None else max(1, min(chosen, height))


@dataclass(frozen=True)
class DepthSamples:
    """A depth image read at every ``stride``-th pixel, ready to back-project.

    Attributes:
        depth: (h, w) float32 planar depth in metres at the pixels read.
        leftward, upward: (h, w) metres left and up per metre of planar depth at each of
            them (`cavenav.sensors.depth.pixel_slopes`).
        surface: (h, w) bool, where a surface was hit: no-hit pixels read D_max, and
            8-bit quantisation puts them within 0.5% of it.
        ranged: (h, w) bool, where the depth was measured (by the camera or the sonar)
            rather than guessed for a pixel the depth camera found nothing at
            (`cavenav.sensors.fusion`): a guess may stop a move, but is never
            remembered as rock nor carved as free water.
    """

    depth: np.ndarray
    leftward: np.ndarray
    upward: np.ndarray
    surface: np.ndarray
    ranged: np.ndarray

    @classmethod
    def of(
        cls,
        observation: Observation,
        stride: int,
        first: int = 0,
        dtype: type[np.floating] = np.float32,
    ) -> DepthSamples:
        """Read ``observation``'s depth image at every ``stride``-th pixel from ``first``,
        with slopes of ``dtype`` (the map carves in float64, the memory keeps float32)."""
        png, guessed = readable_depth(observation)
        h, w = png.shape
        depth = denormalise_depth(png[first::stride, first::stride], *observation.depth_range)
        leftward, upward = pixel_slopes((h, w), observation.hfov_deg, stride, first, dtype)
        surface = depth < 0.995 * observation.depth_range[1]
        ranged = (
            np.ones(depth.shape, bool)
            if guessed is None
            else ~guessed[first::stride, first::stride]
        )
        return cls(depth=depth, leftward=leftward, upward=upward, surface=surface, ranged=ranged)

    def points(self, depth: np.ndarray | None = None, ahead_m: float = 0.0) -> np.ndarray:
        """(h, w, 3) the point of every pixel read, at ``depth`` (its own by default),
        ``ahead_m`` added forward: 0 gives the camera frame, the camera's offset from the
        centre the body frame."""
        depth = self.depth if depth is None else depth
        return np.stack([depth + ahead_m, self.leftward * depth, self.upward * depth], axis=-1)


def executed_since(observation: Observation, last: Action | None) -> Action | None:
    """The move the vehicle made since the previous observation: the translation its DVL
    measured while it has bottom lock, else the action the observation reports or, where
    it reports none, ``last``, the one chosen last; the turn is always the commanded one
    (a vehicle's compass)."""
    executed = observation.previous_action
    executed = executed if executed is not None else last
    dvl = observation.dvl
    if dvl is None or not dvl.locked:
        return executed
    forward, left, up = (float(v) for v in dvl.velocity_m_s * dvl.seconds)
    yaw = executed.yaw_deg if executed is not None else 0.0
    return Action(forward=forward, right=-left, up=up, yaw_deg=yaw)


# How far off a move reckoned from its command alone may land, as a share of its length:
# an assumption, not a measurement (the vehicle bridge's default speed calibration,
# `cavenav.vehicle.dead_reckoning`): thrusters, tether drag and any current (which a
# command knows nothing of) carry a vehicle off, and with no velocity sensor nothing
# corrects it.
COMMANDED_DRIFT = 0.10


def body_step(action: Action, dtype: type[np.floating] = np.float32) -> np.ndarray:
    """(3,) the translation of ``action`` in the body frame after its turn: (df, -dr, dz)."""
    return np.array([action.forward, -action.right, action.up], dtype)


def yaw_matrix(yaw_deg: float) -> np.ndarray:
    """(3, 3) float32 rotation about the up axis by ``yaw_deg``, left positive."""
    a = math.radians(yaw_deg)
    return np.array(
        [[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]],
        np.float32,
    )


def move_points(points: np.ndarray, action: Action) -> np.ndarray:
    """(n, 3) body-frame points as seen after the vehicle executes ``action``.

    The vehicle turns by dpsi (left positive), then translates by (df, -dr, dz) in its new
    frame (SPEC section 5); fixed points therefore turn by -dpsi and shift back.
    """
    return points @ yaw_matrix(-action.yaw_deg).T - body_step(action)


def translation(action: Action) -> np.ndarray:
    """(3,) the straight move of ``action`` in the body frame before it (after its turn)."""
    return yaw_matrix(action.yaw_deg) @ body_step(action)


def to_map(body_points: np.ndarray, position: np.ndarray, heading: float) -> np.ndarray:
    """(n, 3) body-frame points of a vehicle at ``position`` (3,) heading ``heading``
    (radians from the map's x axis, left positive) in the map frame."""
    c, s = math.cos(heading), math.sin(heading)
    p = np.asarray(body_points, np.float64)
    return position + np.stack(
        [c * p[:, 0] - s * p[:, 1], s * p[:, 0] + c * p[:, 1], p[:, 2]], axis=1
    )


def to_body(map_points: np.ndarray, position: np.ndarray, heading: float) -> np.ndarray:
    """(n, 3) map-frame points in the body frame of a vehicle at ``position``, ``heading``."""
    c, s = math.cos(heading), math.sin(heading)
    p = np.asarray(map_points, np.float64) - position
    return np.stack([c * p[:, 0] + s * p[:, 1], -s * p[:, 0] + c * p[:, 1], p[:, 2]], axis=1)


def reckon(position: np.ndarray, heading: float, action: Action) -> tuple[np.ndarray, float]:
    """The map-frame position (3,) and heading after ``action``: turn, then translate."""
    heading = heading + math.radians(action.yaw_deg)
    return to_map(body_step(action, np.float64)[None], position, heading)[0], heading


@dataclass(frozen=True)
class ReckonedPose:
    """Where the vehicle believes it is, from its launch point and its moves alone, and
    how far off that may be: the DVL's measured translation while it has bottom lock, the
    commanded one otherwise (`executed_since`), the turn always commanded.

    The uncertainty (one standard deviation, metres) adds a systematic part, which grows
    with the distance flown as a calibration error does (`COMMANDED_DRIFT` of the metres
    reckoned from commands, the DVL's long-term scale error, 1.01%, of those it
    measured), and in quadrature the DVL's random velocity noise over each move's time.

    Attributes:
        position: (3,) metres in the world frame of the launch pose (a real vehicle knows
            where it went in).
        psi: its heading as `cavenav.core.types.Pose` counts it (0 along -y).
        commanded_m, measured_m: metres reckoned from commands, and from the DVL.
        noise_m2: the DVL's random part of the variance, summed.
        moves, dvl_moves: moves reckoned, and those the DVL measured.
    """

    position: np.ndarray
    psi: float
    commanded_m: float = 0.0
    measured_m: float = 0.0
    noise_m2: float = 0.0
    moves: int = 0
    dvl_moves: int = 0

    @classmethod
    def launched(cls, x: float, y: float, z: float, psi: float) -> ReckonedPose:
        return cls(np.array([x, y, z], np.float64), psi)

    @property
    def sigma_m(self) -> float:
        systematic = COMMANDED_DRIFT * self.commanded_m + A50.scale_error * self.measured_m
        return math.sqrt(systematic**2 + self.noise_m2)

    def after(self, observation: Observation, last: Action | None) -> ReckonedPose:
        """This estimate moved by what the vehicle executed before ``observation``."""
        moved = executed_since(observation, last)
        if moved is None:
            return self
        # The map frame's heading is x-based: a Pose heading psi faces (sin psi, -cos psi).
        position, heading = reckon(self.position, self.psi - math.pi / 2, moved)
        length = math.sqrt(moved.forward**2 + moved.right**2 + moved.up**2)
        dvl = observation.dvl
        if dvl is None or not dvl.locked:
            return replace(
                self, position=position, psi=heading + math.pi / 2,
                commanded_m=self.commanded_m + length, moves=self.moves + 1,
            )  # fmt: skip
        return replace(
            self, position=position, psi=heading + math.pi / 2,
            measured_m=self.measured_m + length,
            noise_m2=self.noise_m2 + (dvl.sigma_m_s * dvl.seconds) ** 2,
            moves=self.moves + 1, dvl_moves=self.dvl_moves + 1,
        )  # fmt: skip

    def to_dict(self) -> dict[str, float]:
        """steps.jsonl's ``reckoned``."""
        x, y, z = (round(float(v), 4) for v in self.position)
        return {
            "x": x,
            "y": y,
            "z": z,
            "sigma_m": round(self.sigma_m, 4),
            "dvl_moves": self.dvl_moves,
        }
