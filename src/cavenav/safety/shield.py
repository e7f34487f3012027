"""The safety shield: judge a proposed action from what a real vehicle has, nothing more.

The shield sees the current depth image, the echo sounders and its own memory of the
last few depth images, each placed by dead reckoning on the actions the vehicle executed
(never the mesh, never the true pose; `cavenav.safety.reckoning`, as the cave map is), so the
same code can stand between a pilot and a real BlueROV2. It enforces, with the numbers
of `Rules` (SPEC section 3):

1. No forward motion when an obstacle ahead of the new heading is closer than
   ``no_forward_within_m`` (measured from the camera, as the depth image is, in a
   corridor of the body's section plus a margin).
2. Inside the standoff, forward motion of at most ``slow_forward_m[1]`` and only together
   with a turn or a lateral or vertical shift.
3. No move passes within the body's radius plus a margin of a surface it has seen, or,
   already nearer than that to one, more than ``Margins.closer_m`` (5 cm) nearer than the
   nearest is now, nor within the crawlway's distance (already within it, no nearer at
   all); the ceiling and floor the sounders read count as level planes near the vehicle.
4. No move enters space that was never seen free: every point along the straight move,
   and the body's leading edge beyond its end, must lie in the view of a remembered depth
   image in front of the surface there, in the sounders' column, or inside the body.
5. Without a depth image (`Observation.has_depth`: a vehicle with no depth source) only
   vertical moves fly, judged by the sounders: every turn and horizontal move goes where
   nothing was seen.

Crawlway mode: where the open margin cannot be kept for the way on, that is in a passage
pinched on both sides (surfaces nearer than the open margin on opposite sides of the
body) or for a forward move into a pinch ahead that only the body's section plus a thin
margin passes, rules 1, 3 and 4 use the thin margins the geometric pilot flies crawlways
with. A surface merely near (on one side, behind, the floor) is no crawlway: rule 3's
5 cm applies; rule 1 alone reads the thin corridor wherever only the open one is blocked
(a wall alongside, which the body passes). `Margins` is the one definition both read,
`crawlway_move` the one choice of margins, and `move_hazard` (rules 3 and 4) the one
judgement both make of a move.

A move that breaks a rule is replaced by the nearest action that keeps them all: its
translations shrunk toward zero (inside the standoff also a 0.1 m shift away from the
nearest surface), its turn kept or shrunk; "hold" when nothing else is safe.

Body frame throughout: (forward, left, up) in metres from the vehicle's centre.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field, replace
from typing import Literal, NamedTuple

import numpy as np

from cavenav.core.errors import ConfigError
from cavenav.core.types import DEFAULT_RULES, Action, Observation, Rules, VehicleBody
from cavenav.motion.actions import DEFAULT_SPACE, ActionSpace, format_action
from cavenav.safety.reckoning import (
    DepthSamples,
    body_step,
    executed_since,
    move_points,
    sampling_stride,
    translation,
    yaw_matrix,
)
from cavenav.sensors.depth import denormalise_depth
from cavenav.sensors.fusion import readable_depth

__all__ = [
    "DepthMemory",
    "Hazard",
    "Margins",
    "MoveMargins",
    "SeenFrame",
    "Shield",
    "ShieldConfig",
    "Surroundings",
    "Verdict",
    "crawlway_move",
    "move_hazard",
    "move_points",
    "sampling_stride",
]


def clearance_of_move(cloud: np.ndarray, action: Action) -> float:
    """Smallest distance from the points ``cloud`` (n, 3) to the straight move of the centre."""
    if not len(cloud):
        return math.inf
    pts = cloud @ yaw_matrix(-action.yaw_deg).T  # in the frame after the turn
    move = body_step(action)
    length2 = float(move @ move)
    t = np.clip(pts @ move / length2, 0.0, 1.0) if length2 > 0 else np.zeros(len(pts), np.float32)
    return float(np.linalg.norm(pts - t[:, None] * move, axis=1).min())


@dataclass(frozen=True)
class SeenFrame:
    """One remembered depth image and where its camera was, in the current body frame.

    Attributes:
        points: (n, 3) float32 surface points it saw (closer than the memory's range),
            the ceiling and floor straight above and below where the sounders read them
            included.
        depth: (h, w) float32 planar depth in blocks of ``stride`` pixels, each block's
            nearest value, then the nearest of its 3x3 neighbours: a conservative map of
            the free space in view; D_max where nothing is in range.
        origin: (3,) float32 camera position.
        yaw_deg: the camera's heading relative to the current heading, left positive.
        focal_px: focal length in pixels of the full image.
        stride: pixels per block of ``depth``.
        width, height: size of the full image in pixels.
    """

    points: np.ndarray
    depth: np.ndarray
    origin: np.ndarray
    yaw_deg: float
    focal_px: float
    stride: int
    width: int
    height: int

    def moved(self, action: Action) -> SeenFrame:
        return replace(
            self,
            points=move_points(self.points, action),
            origin=move_points(self.origin[None], action)[0],
            yaw_deg=self.yaw_deg - action.yaw_deg,
        )

    def sees_free(self, points: np.ndarray, margin_m: float, edge_m: float = 0.15) -> np.ndarray:
        """(n,) whether each body-frame point lies in view, ``margin_m`` before the surface.

        Args:
            edge_m: points up to this far outside the view's edges count as in view,
                at the depth of the nearest edge block: close to the camera the view is
                narrow, and a wall just outside it shows in the edge pixels too.
        """
        rel = points - self.origin
        a = math.radians(self.yaw_deg)
        ahead = rel[:, 0] * math.cos(a) + rel[:, 1] * math.sin(a)
        left = -rel[:, 0] * math.sin(a) + rel[:, 1] * math.cos(a)
        up = rel[:, 2]
        half_w, half_h = 0.5 * self.width / self.focal_px, 0.5 * self.height / self.focal_px
        inside = (
            (ahead > 0.05)
            & (np.abs(left) <= ahead * half_w + edge_m)
            & (np.abs(up) <= ahead * half_h + edge_m)
        )
        safe_ahead = np.maximum(ahead, 1e-3)
        h, w = self.depth.shape
        col = np.floor((0.5 * self.width - self.focal_px * left / safe_ahead) / self.stride)
        row = np.floor((0.5 * self.height - self.focal_px * up / safe_ahead) / self.stride)
        r = np.clip(row[inside], 0, h - 1).astype(np.intp)
        c = np.clip(col[inside], 0, w - 1).astype(np.intp)
        free = np.zeros(len(points), bool)
        free[inside] = ahead[inside] + margin_m <= self.depth[r, c]
        return free


class DepthMemory:
    """The last few depth images, placed by the actions the vehicle executed.

    A plain structure that any pilot, the shield or a prompt can read: `cloud` holds the
    surfaces seen (for clearance), `seen_free` tells known free space from the unknown.
    """

    def __init__(
        self,
        frames: int = 8,
        stride: int | None = None,
        max_range_m: float = 10.0,
        columns: int = 64,
    ):
        """
        Args:
            frames: depth images kept, the current one included.
            stride: every n-th pixel becomes a remembered surface point; free space is
                kept in blocks of n x n pixels. None follows each image's width to keep
                about ``columns`` of them: 10 at 640x480, 2 at 160x120, 1 at 84x84
                (a coarser block would see a 53-degree view as a few pixels).
            max_range_m: surfaces farther than this are not remembered as points.
            columns: see ``stride``.
        """
        sampling_stride(640, stride, columns)  # refuse a bad setting here, not mid-episode
        self.frames_kept = frames
        self.stride = stride
        self.columns = columns
        self.max_range_m = max_range_m
        self.frames: list[SeenFrame] = []

    def reset(self) -> None:
        self.frames = []

    def update(self, observation: Observation, moved_by: Action | None) -> None:
        """Move the remembered frames by ``moved_by`` and add ``observation``'s depth."""
        if moved_by is not None:
            self.frames = [frame.moved(moved_by) for frame in self.frames]
        self.frames.append(self._frame(observation))
        self.frames = self.frames[-self.frames_kept :]

    def _frame(self, obs: Observation) -> SeenFrame:
        h, w = obs.depth_png.shape
        s = sampling_stride(w, self.stride, self.columns, h)
        focal = 0.5 * w / math.tan(math.radians(obs.hfov_deg) / 2)
        # Surface points at every s-th pixel, as the geometric pilot has always kept them.
        points = np.empty((0, 3), np.float32)
        if obs.has_depth:  # without one, no surface is known and no space free (depth 0)
            seen = DepthSamples.of(obs, s)
            keep = seen.surface & seen.ranged & (seen.depth < self.max_range_m)
            points = seen.points(ahead_m=obs.camera_offset_m)[keep].astype(np.float32)
        sounded = [(0.0, 0.0, z) for z in (obs.d_top, -obs.d_bottom) if abs(z) < self.max_range_m]
        points = np.concatenate([points, np.array(sounded, np.float32).reshape(-1, 3)])
        # Free space: the nearest depth in each block and its neighbours.
        png, _ = readable_depth(obs)  # the sonar's ranges where stereo found nothing
        blocks = png[: h // s * s, : w // s * s].reshape(h // s, s, w // s, s)
        nearest = blocks.min(axis=(1, 3))
        padded = np.pad(nearest, 1, mode="edge")
        nearest = np.min(
            [padded[i : i + h // s, j : j + w // s] for i in range(3) for j in range(3)], axis=0
        )
        return SeenFrame(
            points=points,
            depth=denormalise_depth(nearest, *obs.depth_range),
            origin=np.array([obs.camera_offset_m, 0.0, 0.0], np.float32),
            yaw_deg=0.0,
            focal_px=focal,
            stride=s,
            width=w,
            height=h,
        )

    @property
    def cloud(self) -> np.ndarray:
        """(n, 3) float32 every remembered surface point, current body frame."""
        if not self.frames:
            return np.empty((0, 3), np.float32)
        return np.concatenate([frame.points for frame in self.frames])

    def seen_free(self, points: np.ndarray, margin_m: float) -> np.ndarray:
        """(n,) whether some remembered depth image saw each point free, with a margin."""
        free = np.zeros(len(points), bool)
        for frame in reversed(self.frames):
            todo = ~free
            if not todo.any():
                break
            free[todo] = frame.sees_free(points[todo], margin_m)
        return free


@dataclass(frozen=True)
class Margins:
    """Distances kept from surfaces seen: one definition that the safety shield and the
    geometric pilot both judge moves by, so that the shield never stops the pilot for
    doing what the pilot was built to do.

    Attributes:
        open_m: kept beyond the body's half-diagonal from every surface seen (0.61 m from
            the centre), and added to the body's section for the corridor in which an
            obstacle counts as "ahead"; also how far in front of a surface space must lie
            to count as seen free.
        crawlway_m: the same in a crawlway, where ``open_m`` cannot be kept for the way
            on: beyond the reach of the body's corners when it turns (0.39 m from the
            centre), beyond its section for a corridor, and in front of a surface for
            space seen free.
        closer_m: a move may pass this much nearer to a surface than the nearest one is
            now, once the body is already nearer than the margin (a rough wall beside it),
            but never nearer than a crawlway's distance.

    Raises:
        ConfigError: a negative or non-finite distance, or ``crawlway_m`` above
            ``open_m``.
    """

    open_m: float = 0.3
    crawlway_m: float = 0.1
    closer_m: float = 0.05

    def __post_init__(self) -> None:
        for name in ("open_m", "crawlway_m", "closer_m"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0.0):
                raise ConfigError(f"margins {name} = {value}: give a distance of 0 m or more")
        if self.crawlway_m > self.open_m:
            raise ConfigError(
                f"margins crawlway_m = {self.crawlway_m} exceeds open_m = {self.open_m}: "
                "the crawlway's margin is the thinner one"
            )

    def open_keep_m(self, body: VehicleBody) -> float:
        """Distance from the centre kept from every surface in the open (0.61 m)."""
        return body.bounding_radius + self.open_m

    def corridor_m(self, body: VehicleBody, crawlway: bool) -> float:
        """Radius of the corridor a forward move needs: the body's section plus a margin."""
        return body.section_radius + (self.crawlway_m if crawlway else self.open_m)

    def keep_clear_m(self, body: VehicleBody, here_m: float, crawlway: bool) -> float:
        """How near a move may pass to a surface seen, the nearest being ``here_m`` away.

        In the open the body's bounding radius plus ``open_m``; in a crawlway the reach of
        its corners when it turns plus ``crawlway_m``. Already nearer than that, any move
        that comes at most ``closer_m`` nearer, down to the crawlway's distance; nearer
        still (a wall it drifted to), only one that comes no nearer at all.
        """
        reach = body.turn_radius + self.crawlway_m
        keep = reach if crawlway else self.open_keep_m(body)
        if here_m < keep:
            keep = max(reach, here_m - self.closer_m) if here_m >= reach else here_m - 1e-6
        return keep


@dataclass(frozen=True)
class Surroundings:
    """What judging any move reads from one observation, measured once (body frame).

    Attributes:
        cloud: (n, 3) float32 remembered surface points within reach of any move, the
            ceiling and floor the sounders read included.
        memory: the remembered depth images, for space seen free.
        d_top, d_bottom: what the sounders read, metres.
        camera_offset_m: how far ahead of the centre the camera sits.
        nearest_m: distance from the centre to the nearest point of ``cloud``.
        pinched: surfaces nearer than the open margin on opposite sides of the body (more
            than 120 degrees apart seen from its centre: left and right, above and
            below): a passage where the open margin cannot be kept anywhere across it.
    """

    cloud: np.ndarray
    memory: DepthMemory
    d_top: float
    d_bottom: float
    camera_offset_m: float
    nearest_m: float
    pinched: bool

    @classmethod
    def of(
        cls,
        observation: Observation,
        memory: DepthMemory,
        body: VehicleBody,
        margins: Margins,
        no_forward_m: float,
    ) -> Surroundings:
        """Measure ``memory`` (already updated with ``observation``) once."""
        cloud = memory.cloud
        distance = np.linalg.norm(cloud, axis=1)
        # Moves reach at most ~2.3 m (1 m forward, 1 m sideways, 2 m up): farther points
        # cannot come within the margin, and the forward check looks no_forward_m beyond.
        reach = 2.3 + no_forward_m + margins.open_keep_m(body)
        near = distance < margins.open_keep_m(body)
        return cls(
            cloud=cloud[distance < reach],
            memory=memory,
            d_top=observation.d_top,
            d_bottom=observation.d_bottom,
            camera_offset_m=observation.camera_offset_m,
            nearest_m=float(distance.min()) if len(cloud) else math.inf,
            pinched=_opposite(cloud[near] / distance[near, None]),
        )


def _opposite(directions: np.ndarray) -> bool:
    """Whether two of the (n, 3) unit ``directions`` lie more than 120 degrees apart."""
    if len(directions) < 2:
        return False
    # Directions within ~10 degrees of each other read as one: a few dozen stay.
    cells = np.unique(np.round(directions * 4.0), axis=0)
    cells /= np.linalg.norm(cells, axis=1, keepdims=True)
    return bool((cells @ cells.T).min() < -0.5)


class MoveMargins(NamedTuple):
    """The margins a move is judged with (`crawlway_move`)."""

    crawlway: bool  # rules 3 and 4 with the crawlway's thin margins, not the open ones
    ahead_m: float  # rule 1: free ahead of the camera in its corridor (inf: no forward move)


def crawlway_move(
    action: Action,
    around: Surroundings,
    *,
    body: VehicleBody,
    margins: Margins,
    no_forward_m: float,
) -> MoveMargins:
    """The margins ``action`` is judged with: the crawlway's where the open margin cannot
    be kept for the way on, the open ones everywhere else.

    A crawlway is a passage pinched on both sides (`Surroundings.pinched`), or, for a
    forward move, a pinch ahead: the open corridor blocked within ``no_forward_m`` from
    opposite sides of the axis while the crawlway's corridor is not. A surface merely near
    (on one side, behind, the floor) is no crawlway: `Margins.keep_clear_m` lets a move
    come at most ``closer_m`` nearer to it. Rule 1 reads the crawlway's corridor wherever
    the open one is blocked and the crawlway's is not, a wall alongside included: the
    body passes it, and rule 3 keeps it from closing in.
    """
    if action.forward <= 0:
        return MoveMargins(around.pinched, math.inf)
    # The cloud in the frame of the new heading: along it from the camera, and across it.
    pts = around.cloud @ yaw_matrix(-action.yaw_deg).T
    along = pts[:, 0] - around.camera_offset_m
    across = np.hypot(pts[:, 1], pts[:, 2])
    thin, wide = margins.corridor_m(body, True), margins.corridor_m(body, False)

    def ahead(radius: float) -> float:
        blocking = (along > 0) & (across < radius)
        return float(along[blocking].min()) if blocking.any() else math.inf

    if around.pinched:
        return MoveMargins(True, ahead(thin))
    open_ahead = ahead(wide)
    if open_ahead >= no_forward_m:
        return MoveMargins(False, open_ahead)
    tight_ahead = ahead(thin)
    if tight_ahead < no_forward_m:
        return MoveMargins(False, open_ahead)  # blocked either way
    # What blocks only the open corridor: from opposite sides, a pinch to squeeze
    # through; from one side, a wall to keep clear of.
    rim = (along > 0) & (along < no_forward_m) & (across >= thin) & (across < wide)
    sides = np.column_stack([np.zeros(int(rim.sum())), pts[rim, 1:] / across[rim, None]])
    return MoveMargins(_opposite(sides), tight_ahead)


@dataclass(frozen=True)
class Hazard:
    """Why a move is unsafe by what was seen; falsy (``kind`` "") when it is not.

    Attributes:
        kind: "surface" (it passes too near a surface seen), "sounded" (it ends too near
            the ceiling or floor the sounders read), "unseen" (it enters space never
            seen free), or "".
        text: the reason in words, as the shield records it.
    """

    kind: Literal["", "surface", "sounded", "unseen"] = ""
    text: str = ""

    def __bool__(self) -> bool:
        return bool(self.kind)


def move_hazard(
    action: Action,
    around: Surroundings,
    *,
    body: VehicleBody,
    margins: Margins,
    crawlway: bool,
    sample_m: float = 0.1,
) -> Hazard:
    """Why the straight move of ``action`` is unsafe by what was seen (rules 3 and 4).

    The move must keep `Margins.keep_clear_m` from the surfaces ``around.cloud`` and from
    the ceiling and floor the sounders read, taken as level planes; and the centre's path
    every ``sample_m`` and the body's leading edge beyond its end must lie in space
    ``around.memory`` saw free, or in the sounders' column short of what they read. A
    side or a depth never seen is no free space, however far the walls seen elsewhere are.
    """
    move = translation(action)
    length = float(np.linalg.norm(move))
    if length == 0.0:
        return Hazard()
    keep = margins.keep_clear_m(body, around.nearest_m, crawlway)
    if clearance_of_move(around.cloud, action) < keep - 1e-6:
        return Hazard("surface", f"the move would pass within {keep:.2f} m of a surface seen")
    for gap, rise, what in (
        (around.d_top, move[2], "ceiling"),
        (around.d_bottom, -move[2], "floor"),
    ):
        keep = margins.keep_clear_m(body, gap, crawlway)
        if rise > 0 and gap - rise < keep - 1e-6:
            return Hazard(
                "sounded",
                f"the move would end within {keep:.2f} m of the {what} ({gap:.2f} m away)",
            )
    # The centre's path and the body's leading edge beyond its end, past the body.
    radius = body.bounding_radius
    along = np.arange(sample_m, length + radius + 1e-6, sample_m)
    points = ((along[:, None] / length) * move)[along > radius]
    margin = margins.crawlway_m if crawlway else margins.open_m
    beside = np.hypot(points[:, 0], points[:, 1]) <= 0.1  # the sounders' column
    up = (points[:, 2] > 0) & (points[:, 2] + margin <= around.d_top)
    down = (points[:, 2] < 0) & (-points[:, 2] + margin <= around.d_bottom)
    known = around.memory.seen_free(points, margin) | (beside & (up | down))
    if known.all():
        return Hazard()
    where = _describe(points[int(np.argmin(known))])
    return Hazard("unseen", f"the move would enter space never seen free ({where})")


@dataclass(frozen=True)
class ShieldConfig:
    """Numbers of the shield.

    Attributes:
        rules: the strategy's distances (standoff, no forward within).
        body: the vehicle; its bounding radius is the body's extent in every direction.
        margins: distances kept from surfaces seen, in the open and in a crawlway (the
            geometric pilot's own), and in front of a surface for space seen free.
        memory_frames: depth images remembered, the current one included.
        sample_m: spacing of the points checked along a move.
    """

    rules: Rules = DEFAULT_RULES
    body: VehicleBody = field(default_factory=VehicleBody)
    margins: Margins = field(default_factory=Margins)
    memory_frames: int = 8
    sample_m: float = 0.1


@dataclass(frozen=True)
class Verdict:
    """The shield's answer: the action to execute and, if it differs, why."""

    proposed: Action
    action: Action
    reason: str = ""

    @property
    def intervened(self) -> bool:
        return self.action != self.proposed

    def to_dict(self) -> dict[str, str]:
        """The record written to steps.jsonl under ``shield``."""
        return {
            "proposed": format_action(self.proposed),
            "replacement": format_action(self.action),
            "reason": self.reason,
        }


class Shield:
    """Judges proposed actions; see the module docstring for the rules."""

    def __init__(self, config: ShieldConfig | None = None, space: ActionSpace = DEFAULT_SPACE):
        self.config = config or ShieldConfig()
        self.space = space
        self.memory = DepthMemory(frames=self.config.memory_frames)
        self._observation: Observation | None = None
        self._last: Action | None = None

    def reset(self) -> None:
        self.memory.reset()
        self._observation = None
        self._last = None

    def observe(self, observation: Observation) -> None:
        """Take in a new observation; the memory moves by the action executed before it,
        or, when the observation does not say, by the last action this shield judged."""
        self.memory.update(observation, executed_since(observation, self._last))
        self._observation = observation

    def judge(self, proposed: Action) -> Verdict:
        """The nearest action to ``proposed`` that keeps every rule (hold if none does)."""
        if self._observation is None:
            raise RuntimeError("Shield.judge needs an observation first: call observe()")
        situation = _Situation.of(self._observation, self.memory, self.config)
        reason = self._violation(proposed, situation)
        if not reason:
            verdict = Verdict(proposed, proposed)
        else:
            for candidate in self._candidates(proposed, situation):
                if not self._violation(candidate, situation):
                    verdict = Verdict(proposed, candidate, reason)
                    break
            else:
                verdict = Verdict(proposed, Action(), reason + "; nothing else is safe: hold")
        self._last = verdict.action
        return verdict

    # ------------------------------------------------------------------ rules
    def _violation(self, action: Action, s: _Situation) -> str:
        """Why ``action`` breaks a rule in situation ``s``; "" when it keeps them all."""
        cfg, rules = self.config, self.config.rules
        if action.is_hold:
            return ""
        if not s.sighted and (action.forward or action.right or action.yaw_deg):
            return "no depth image: only a vertical move, which the sounders judge, flies blind"
        if action.yaw_deg and s.turn_room_m < cfg.body.turn_radius + 0.05:
            return f"a surface {s.turn_room_m:.2f} m beside the centre leaves no room to turn"
        judged = crawlway_move(
            action,
            s.around,
            body=cfg.body,
            margins=cfg.margins,
            no_forward_m=rules.no_forward_within_m,
        )
        if action.forward > 0:
            if judged.ahead_m < rules.no_forward_within_m:
                return (
                    f"obstacle {judged.ahead_m:.1f} m ahead, within "
                    f"{rules.no_forward_within_m:g} m: no forward motion"
                )
            if s.nearest_m < rules.standoff_m:
                slow = rules.slow_forward_m[1]
                if action.forward > slow + 1e-9:
                    return (
                        f"nearest surface {s.nearest_m:.1f} m is inside the "
                        f"{rules.standoff_m:g} m standoff: forward at most {slow:g} m"
                    )
                if not (action.yaw_deg or action.right or action.up):
                    return "inside the standoff, forward motion must come with a turn or a shift"
        hazard = move_hazard(
            action,
            s.around,
            body=cfg.body,
            margins=cfg.margins,
            crawlway=judged.crawlway,
            sample_m=cfg.sample_m,
        )
        return hazard.text

    def _candidates(self, proposed: Action, s: _Situation) -> list[Action]:
        """Admissible actions near ``proposed``, nearest first (hold excluded)."""
        space = self.space

        def toward_zero(value: float, allowed: tuple[float, ...]) -> list[float]:
            return [math.copysign(a, value) for a in allowed if a <= abs(value) + 1e-9]

        forwards = toward_zero(proposed.forward, space.forward_m)
        rights = toward_zero(proposed.right, space.lateral_m)
        yaws = toward_zero(proposed.yaw_deg, space.yaw_deg)
        lo = space.vertical_range_m[0]
        ups = {proposed.up, 0.0}
        if abs(proposed.up) >= 2 * lo:
            ups |= {round(proposed.up / 2, 2), math.copysign(lo, proposed.up)}
        if s.nearest_m < self.config.rules.standoff_m:  # the shift the standoff asks for
            rights.append(s.away.right)
            ups.add(s.away.up)
        options = {
            Action(f, r, u, y)
            for f, r, u, y in itertools.product(forwards, rights, ups, yaws)
            if space.is_valid(Action(f, r, u, y))
        }
        options.discard(proposed)
        options.discard(Action())

        def distance(a: Action) -> float:
            return (
                abs(a.forward - proposed.forward)
                + abs(a.right - proposed.right)
                + abs(a.up - proposed.up)
                + abs(a.yaw_deg - proposed.yaw_deg) / 45.0
            )

        return sorted(options, key=lambda a: (distance(a), format_action(a)))


@dataclass(frozen=True)
class _Situation:
    """What the shield measured for one observation (body frame, metres)."""

    around: Surroundings  # what every judgement of a move reads
    turn_room_m: float  # horizontal distance to the nearest surface at the body's height
    nearest_m: float  # the nearest surface, or the ceiling or floor if nearer
    away: Action  # a 0.1 m lateral or vertical shift away from the nearest surface
    sighted: bool  # a depth image came with the observation

    @classmethod
    def of(cls, obs: Observation, memory: DepthMemory, cfg: ShieldConfig) -> _Situation:
        body = cfg.body
        around = Surroundings.of(obs, memory, body, cfg.margins, cfg.rules.no_forward_within_m)
        cloud = around.cloud  # the nearest point is within reach: it is kept
        shift = 0.1
        # The sounders' readings are points of the cloud too: a tie means they are nearest.
        if min(obs.d_top, obs.d_bottom) <= around.nearest_m + 1e-6:
            away = Action(up=-shift if obs.d_top < obs.d_bottom else shift)
        elif len(cloud):  # away from a wall on the left is to the right
            nearest = int(np.argmin(np.linalg.norm(cloud, axis=1)))
            away = Action(right=shift if cloud[nearest, 1] > 0 else -shift)
        else:
            away = Action()
        level = np.abs(cloud[:, 2]) <= body.height / 2 + 0.05
        beside = np.hypot(cloud[level, 0], cloud[level, 1])
        return cls(
            around=around,
            turn_room_m=float(beside.min()) if beside.size else math.inf,
            nearest_m=min(around.nearest_m, obs.d_top, obs.d_bottom),
            away=away,
            sighted=obs.has_depth,
        )


def _describe(point: np.ndarray) -> str:
    """Where a body-frame point lies, as a pilot reads it: "0.3 m behind, 0.2 m above the
    vehicle", "0.4 m right of the vehicle" (offsets under 5 cm are not named)."""
    f, left, u = (float(v) for v in point)
    parts = []
    if abs(f) >= 0.05:
        parts.append(f"{abs(f):.1f} m {'ahead of' if f > 0 else 'behind'}")
    if abs(left) >= 0.05:
        parts.append(f"{abs(left):.1f} m {'left of' if left > 0 else 'right of'}")
    if abs(u) >= 0.05:
        parts.append(f"{abs(u):.1f} m {'above' if u > 0 else 'below'}")
    if not parts:
        return "at the vehicle's centre"
    # Only the last offset takes the preposition: "0.1 m ahead, 0.4 m left of the vehicle".
    *first, last = parts
    return ", ".join([p.removesuffix(" of") for p in first] + [f"{last} the vehicle"])
