"""How a VLM pilot's answer becomes a move: the pilot designs researchers compare.

- ``direct``, the paper's: the model writes the action string itself (`cavenav.pilots.reply`).
- ``arrows``, visual prompting as VLMnav does it: the directions where the body fits for
  at least `REACH_M` are found in the depth image, drawn on the colour image as numbered
  arrows, and the model answers with a number (and, if it likes, ``ascend``/``descend``).
  The number becomes an admissible move by the geometric pilot's standoff rules and its
  judgement of a move (`cavenav.pilots.geometric.GeometricPilot.steer`).
- ``waypoint``, a split design (CORAL, UnderwaterVLA): the model marks a point on the
  image, by normalised coordinates or by a numbered candidate; the depth under it gives a
  3D goal short of the rock by the standoff, and a local planner (the same helmsman) flies
  there in admissible steps without calling the model, until it arrives, the goal is no
  longer free, or ``replan_every`` steps have passed.

In both designs two more numbers turn in place by `TURN_DEG`, left and right, for the way
on out of view. Numbers run left to right across the image. What is drawn, and the
choice read from a reply, are plain data (`Candidate`, `Choice`) the run folder records.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, replace
from functools import lru_cache
from typing import Any, Literal

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from cavenav.core.errors import ActionError
from cavenav.core.types import Action, Decision, Observation, Rules
from cavenav.motion.actions import ActionSpace, parse_action
from cavenav.pilots.geometric import FreeView, GeometricPilot, GeometricPilotConfig
from cavenav.safety.reckoning import executed_since, move_points
from cavenav.sensors.depth import denormalise_depth
from cavenav.sensors.fusion import readable_depth

__all__ = [
    "DESIGNS",
    "Candidate",
    "Choice",
    "Design",
    "Helm",
    "draw_candidates",
    "offer_candidates",
    "read_choice",
    "waypoint_goal",
]

Design = Literal["direct", "arrows", "waypoint"]
DESIGNS: tuple[Design, ...] = ("direct", "arrows", "waypoint")
TURN_DEG = 45.0  # the turn in place the two side numbers offer
REPLAN_EVERY = 8  # the most steps the waypoint planner flies before asking again
SPACING_DEG = 7.5  # arrows at most this close in bearing: up to seven across the view
MOST_ARROWS = 7
GOAL_MIN_M = 0.5  # a waypoint nearer than this past the standoff is no goal to fly to
ARRIVED_M = 0.5  # the planner has arrived this near its goal, across
DRAWN_REACH_M = 8.0  # an arrow free this far or more is drawn at full length
EDGE = 0.12  # the arrows' numbers keep this share of the image from its sides
TURN_Y = 0.72  # the turns' arrows lie this far down the sides, below most arrows' ends


def design_suffix(design: str) -> str:
    """What a pilot's name gains for a design: nothing for the paper's, `` (arrows)`` or
    `` (waypoint)`` for the others, so that tables and comparisons tell them apart."""
    return "" if design == "direct" else f" ({design})"


def navigable_reach_m(rules: Rules) -> float:
    """How far the body must fit along a direction for it to be offered: a metre past
    the distance within which the standoff rules allow no forward move."""
    return rules.no_forward_within_m + 1.0


@dataclass(frozen=True)
class Candidate:
    """One numbered choice drawn on the image.

    Attributes:
        number: what the model answers with.
        bearing_deg, elevation_deg: its direction from the camera (left and up positive);
            for a turn in place, the turn.
        free_m: how far a corridor the body fits stays free along it (0 for a turn).
        x, y: where its number is drawn, normalised image coordinates from the top left.
    """

    number: int
    bearing_deg: float
    elevation_deg: float
    free_m: float
    x: float
    y: float

    @property
    def turn(self) -> bool:
        return self.free_m == 0.0

    def words(self) -> str:
        """The candidate as the request lists it."""
        side = "left" if self.bearing_deg > 0 else "right"
        if self.turn:
            return f"{self.number} = turn {side} {abs(self.bearing_deg):g} degrees in place"
        where = (
            [f"{abs(self.bearing_deg):.0f} degrees {side}"] if abs(self.bearing_deg) >= 1 else []
        )
        if abs(self.elevation_deg) >= 1:
            up = "up" if self.elevation_deg > 0 else "down"
            where.append(f"{abs(self.elevation_deg):.0f} degrees {up}")
        return f"{self.number} = {', '.join(where) or 'straight ahead'}, {self.free_m:.1f} m free"

    def to_dict(self) -> dict[str, Any]:
        return {
            "number": self.number,
            "bearing_deg": round(self.bearing_deg, 2),
            "elevation_deg": round(self.elevation_deg, 2),
            "free_m": round(self.free_m, 2),
            "x": round(self.x, 4),
            "y": round(self.y, 4),
        }


@dataclass(frozen=True)
class Choice:
    """What a reply chose: a candidate, or a point marked on the image.

    Attributes:
        text: the answer as the model wrote it (the dictionary's key).
        justification: the dictionary's value.
        candidate: the numbered candidate chosen, if it was one.
        point: (x, y) normalised image coordinates marked, if a point was.
        up_m: the ascend (positive) or descend the model asked for with an arrow.
    """

    text: str
    justification: str
    candidate: Candidate | None = None
    point: tuple[float, float] | None = None
    up_m: float | None = None

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"text": self.text}
        if self.candidate is not None:
            out["number"] = self.candidate.number
        if self.point is not None:
            out["point"] = [round(v, 4) for v in self.point]
        if self.up_m is not None:
            out["up_m"] = self.up_m
        return out


def _pixel(
    bearing_deg: float, elevation_deg: float, hfov_deg: float, shape: tuple[int, int]
) -> tuple[float, float]:
    """Where a direction from the camera meets the image, normalised (x, y)."""
    h, w = shape
    focal = 0.5 * w / math.tan(math.radians(hfov_deg) / 2)
    b, e = math.radians(bearing_deg), math.radians(elevation_deg)
    x = 0.5 * w - focal * math.tan(b)
    y = 0.5 * h - focal * math.tan(e) / math.cos(b)
    return x / w, y / h


def offer_candidates(
    view: FreeView, hfov_deg: float, shape: tuple[int, int], reach_m: float
) -> tuple[Candidate, ...]:
    """The numbered choices for one view: a turn left, the navigable directions left to
    right, a turn right.

    A bearing is navigable where the body's corridor, at the elevation that reaches
    farthest, stays free for ``reach_m``. Of neighbouring navigable bearings within
    `SPACING_DEG` the farther-reaching one stays, at most `MOST_ARROWS`.
    """
    bearings, elevations, free = view.bearings_deg, view.elevations_deg, view.free
    half_view = 0.5 * hfov_deg
    best = np.argmax(free - 1e-3 * np.abs(elevations)[None, :], axis=1)  # level on ties
    reach = free[np.arange(len(bearings)), best]
    order = sorted(
        (i for i in range(len(bearings)) if reach[i] >= reach_m and abs(bearings[i]) < half_view),
        key=lambda i: (-reach[i], abs(bearings[i])),
    )
    kept: list[int] = []
    for i in order:
        if all(abs(bearings[i] - bearings[k]) >= SPACING_DEG for k in kept):
            kept.append(i)
    kept = sorted(kept[:MOST_ARROWS], key=lambda i: -bearings[i])  # left to right
    directions = [(TURN_DEG, 0.0, 0.0, 0.03, TURN_Y)]
    for i in kept:
        b, e, f = float(bearings[i]), float(elevations[best[i]]), float(reach[i])
        x, y = _pixel(b, e, hfov_deg, shape)
        # The number sits part way from the vehicle (bottom centre) toward the direction,
        # farther the more water is free along it, clear of the edges the turns hold.
        share = min(max(f / DRAWN_REACH_M, 0.35), 1.0)
        x = min(max(0.5 + share * (x - 0.5), EDGE), 1.0 - EDGE)
        directions.append((b, e, f, x, min(max(1.0 + share * (y - 1.0), EDGE), 1.0 - EDGE)))
    directions.append((-TURN_DEG, 0.0, 0.0, 0.97, TURN_Y))
    return tuple(Candidate(n, *d) for n, d in enumerate(directions, start=1))


@lru_cache(maxsize=8)
def _font(size: int) -> ImageFont.FreeTypeFont | ImageFont.ImageFont:
    return ImageFont.load_default(size=size)


def draw_candidates(rgb: np.ndarray, candidates: tuple[Candidate, ...]) -> np.ndarray:
    """A copy of ``rgb`` with each candidate drawn: an arrow from the bottom centre (the
    vehicle) to its number, or along the edge for a turn, and the number in a disc.

    Thick white strokes on a black outline, and numbers a twentieth of the image high:
    they stay legible after JPEG coding and after downscaling to a quarter of the area.
    """
    picture = Image.fromarray(rgb)
    draw = ImageDraw.Draw(picture)
    h, w = rgb.shape[:2]
    line = max(2, round(w / 160))
    radius = max(7, round(h / 28))
    font = _font(max(9, round(radius * 1.3)))
    origin = (0.5 * w, h - 1.0)
    for c in candidates:
        tip = (c.x * w, c.y * h)
        if c.turn:
            inward = 1 if c.x < 0.5 else -1
            start = (tip[0] + inward * 4 * radius, tip[1])
            _arrow(draw, start, tip, line, radius)
            centre = (tip[0] + inward * 2 * radius, tip[1] - 2 * radius)
        else:
            _arrow(draw, origin, tip, line, radius)
            centre = tip
        box = (centre[0] - radius, centre[1] - radius, centre[0] + radius, centre[1] + radius)
        draw.ellipse(box, fill=(255, 255, 255), outline=(0, 0, 0), width=max(2, line // 2))
        draw.text(centre, str(c.number), fill=(0, 0, 0), font=font, anchor="mm")
    return np.asarray(picture)


Pixel = tuple[float, float]


def _arrow(draw: ImageDraw.ImageDraw, start: Pixel, end: Pixel, line: int, radius: int) -> None:
    """A white arrow with a black outline from ``start`` to ``end``, its head at ``end``."""
    dx, dy = end[0] - start[0], end[1] - start[1]
    length = math.hypot(dx, dy) or 1.0
    ux, uy = dx / length, dy / length
    back = (end[0] - ux * 1.6 * radius, end[1] - uy * 1.6 * radius)
    head = [
        (end[0] - ux * radius, end[1] - uy * radius),
        (back[0] - uy * 0.9 * radius, back[1] + ux * 0.9 * radius),
        (back[0] + uy * 0.9 * radius, back[1] - ux * 0.9 * radius),
    ]
    for colour, extra in (((0, 0, 0), line + 2), ((255, 255, 255), 0)):
        draw.line([start, back], fill=colour, width=line + extra)
    draw.polygon(head, fill=(255, 255, 255), outline=(0, 0, 0))


_NUMBER = re.compile(
    r"^\s*(?:arrow|candidate|number|choice|option|point|waypoint)?\s*#?\s*(\d+)(?!\.\d)\b"
    r"\s*[,;:+=]?\s*(.*)$",
    re.I,
)
_POINT = re.compile(
    r"^\s*(?:point|waypoint|goal)?\s*[:=]?\s*[(\[]?\s*(?:x\s*[:=])?\s*([-+]?\d*\.?\d+)\s*[,; ]\s*"
    r"(?:y\s*[:=])?\s*([-+]?\d*\.?\d+)\s*[)\]]?\s*$",
    re.I,
)


def read_choice(
    answer: str,
    justification: str,
    design: Design,
    candidates: tuple[Candidate, ...],
    space: ActionSpace,
) -> Choice:
    """The choice in a reply's final answer (``answer``, the dictionary's key).

    Arrows: a number offered, then optionally an ascend or descend from the admissible
    range ("3", "arrow 3, ascend 0.2 m"). Waypoint: a number offered, or a point as
    normalised image coordinates ("point 0.62, 0.41", "(0.62, 0.41)").

    Raises:
        ActionError: with the reason the model is told: a number not offered, other
            motions after the number, a point outside the image.
    """
    offered = ", ".join(str(c.number) for c in candidates)
    point = _POINT.match(answer) if design == "waypoint" else None
    if point is not None:
        x, y = (float(v) for v in point.groups())
        if not (0.0 <= x <= 1.0 and 0.0 <= y <= 1.0):
            raise ActionError(
                f"the point ({x:g}, {y:g}) lies outside the image: give x and y between 0 and 1, "
                "x from the left edge, y from the top"
            )
        return Choice(answer, justification, point=(x, y))
    number = _NUMBER.match(answer)
    if number is None:
        what = (
            "a number offered, or a point as 'point X, Y'"
            if design == "waypoint"
            else "the number of an arrow"
        )
        raise ActionError(f"'{answer}' is not a choice: answer with {what} (offered: {offered})")
    wanted, rest = int(number.group(1)), number.group(2).strip(" .,;:-")
    chosen = next((c for c in candidates if c.number == wanted), None)
    if chosen is None:
        raise ActionError(f"number {wanted} was not offered: choose one of {offered}")
    up = None
    if rest and _motions(rest):  # anything else after the number is words about it
        if design == "waypoint":
            raise ActionError(f"give the number alone, not '{answer}': the waypoint sets the depth")
        action = parse_action(rest, space)
        if action.forward or action.right or action.yaw_deg:
            raise ActionError(
                f"only ascend or descend may follow the number, not '{rest}': the arrow sets "
                "the direction and the step"
            )
        up = action.up or None
    return Choice(answer, justification, candidate=chosen, up_m=up)


_MOTION_WORDS = re.compile(
    r"\b(forward|ahead|back|strafe|shift|left|right|ascend|descend|up|down|rise|sink|turn|yaw|"
    r"rotate|hold)\b.*\d|\bhold\b",
    re.I,
)


def _motions(text: str) -> bool:
    """Whether ``text`` after a number asks for a motion with a magnitude (read as an
    action), rather than echoing the offer's words ("= straight ahead, 6.0 m free")."""
    return bool(_MOTION_WORDS.search(text)) and "free" not in text.lower()


def waypoint_goal(
    observation: Observation, view: FreeView, choice: Choice, rules: Rules
) -> np.ndarray:
    """The 3D goal (body frame: forward, left, up, metres) a waypoint choice stands for:
    along its direction, as far as the body's corridor stays free and the surface under
    the point lies, less the standoff.

    Raises:
        ActionError: the goal would lie within `GOAL_MIN_M` past the standoff (the point is
            on rock near the vehicle) or at or behind the vehicle.
    """
    if choice.candidate is not None:
        c = choice.candidate
        bearing, elevation, surface = c.bearing_deg, c.elevation_deg, c.free_m
    else:
        assert choice.point is not None
        bearing, elevation, surface = _point_direction(observation, *choice.point)
    i = int(np.argmin(np.abs(view.bearings_deg - bearing)))
    j = int(np.argmin(np.abs(view.elevations_deg - elevation)))
    reach = min(surface, float(view.free[i, j]))
    distance = reach - rules.standoff_m
    b, e = math.radians(bearing), math.radians(elevation)
    unit = np.array([math.cos(e) * math.cos(b), math.cos(e) * math.sin(b), math.sin(e)])
    goal = unit * distance + np.array([observation.camera_offset_m, 0.0, 0.0])
    if distance < GOAL_MIN_M or goal[0] <= 0.0:
        raise ActionError(
            f"the point marked is rock or blocked {reach:.1f} m away, within the "
            f"{rules.standoff_m:g} m standoff (or behind you): mark open water farther away, "
            "or choose a turn"
        )
    return goal


def _point_direction(observation: Observation, x: float, y: float) -> tuple[float, float, float]:
    """The bearing and elevation (degrees) of the pixel at normalised (x, y), and the
    distance from the camera to the surface there (the median over 5x5 pixels of the depth
    the pilots read, `cavenav.sensors.fusion.readable_depth`)."""
    png, _ = readable_depth(observation)
    h, w = png.shape
    u, v = min(int(x * w), w - 1), min(int(y * h), h - 1)
    patch = png[max(v - 2, 0) : v + 3, max(u - 2, 0) : u + 3]
    planar = float(np.median(denormalise_depth(patch, *observation.depth_range)))
    focal = 0.5 * w / math.tan(math.radians(observation.hfov_deg) / 2)
    left, up = (0.5 * w - (u + 0.5)) / focal, (0.5 * h - (v + 0.5)) / focal
    bearing = math.degrees(math.atan2(left, 1.0))
    elevation = math.degrees(math.atan2(up, math.hypot(1.0, left)))
    return bearing, elevation, planar * math.sqrt(1.0 + left * left + up * up)


@dataclass(frozen=True)
class _Goal:
    """The waypoint the planner flies to: body frame (forward, left, up), metres."""

    point: np.ndarray
    chosen: str  # the model's answer that set it
    steps: int = 0  # flown toward it so far


class Helm:
    """What a designed VLM pilot does without its model: find and draw the choices, read
    the model's, and fly it; with waypoints, fly toward the goal between the model's
    answers (the local planner).

    Sizing and keeping moves clear is the geometric pilot's (its memory of depth images,
    the standoff rules, the shield's judgement of a move): it is told where to go.
    """

    def __init__(self, design: Design, rules: Rules, space: ActionSpace, replan_every: int):
        self.design, self.rules, self.space, self.replan_every = design, rules, space, replan_every
        self.helmsman = GeometricPilot(GeometricPilotConfig(rules=rules), space)
        self.reset()

    def reset(self) -> None:
        self.helmsman.reset()
        self.goal: _Goal | None = None
        self.view: FreeView | None = None
        self.stopped = ""  # why the planner stopped before this request, if it did
        self._last: Action | None = None

    def planned(self, observation: Observation) -> Decision | None:
        """Survey ``observation``; then the planner's step toward the waypoint, or None
        when the model must choose (`stopped` says why the planner stopped)."""
        self.view = self.helmsman.survey(observation)
        goal = self.goal
        if goal is None:
            if self.helmsman.owes_turn_back(observation):  # from a look aside: no choice
                return self._turn_back(observation)
            return None
        moved = executed_since(observation, self._last)
        point = goal.point if moved is None else move_points(goal.point[None], moved)[0]
        self.goal = goal = _Goal(np.asarray(point, np.float64), goal.chosen, goal.steps)
        self.stopped = self._stop_reason(observation, goal)
        if self.stopped:
            self.goal = None
            return None
        return self._toward(observation, goal, planned=True)

    def _stop_reason(self, observation: Observation, goal: _Goal) -> str:
        """Why the planner stops flying toward ``goal`` ("" while it flies on)."""
        x, y, z = goal.point
        if math.hypot(x, y) < ARRIVED_M:
            return f"it arrived at the waypoint ({goal.chosen}) after {goal.steps} steps"
        if goal.steps >= self.replan_every:
            return (
                f"{goal.steps} steps flown toward the waypoint ({goal.chosen}), "
                f"{math.hypot(x, y):.1f} m short of it"
            )
        view = self.view
        assert view is not None
        ahead = goal.point - np.array([observation.camera_offset_m, 0.0, 0.0])
        bearing = math.degrees(math.atan2(ahead[1], ahead[0]))
        elevation = math.degrees(math.atan2(ahead[2], math.hypot(ahead[0], ahead[1])))
        if abs(bearing) < 0.5 * observation.hfov_deg and ahead[0] > 0:
            i = int(np.argmin(np.abs(view.bearings_deg - bearing)))
            j = int(np.argmin(np.abs(view.elevations_deg - elevation)))
            free, distance = float(view.free[i, j]), float(np.linalg.norm(ahead))
            if free < distance:
                return (
                    f"the way to the waypoint ({goal.chosen}) is no longer free: blocked "
                    f"{free:.1f} m ahead, {distance:.1f} m short of it"
                )
        return ""

    def offer(self, observation: Observation) -> tuple[tuple[Candidate, ...], np.ndarray]:
        """The candidates for the surveyed ``observation``, and its colour image with
        them drawn."""
        assert self.view is not None
        shape = observation.rgb.shape[:2]
        reach = navigable_reach_m(self.rules)
        candidates = offer_candidates(self.view, observation.hfov_deg, shape, reach)
        return candidates, draw_candidates(observation.rgb, candidates)

    def check(self, observation: Observation, choice: Choice) -> None:
        """Refuse a waypoint that makes no goal (`waypoint_goal`).

        Raises:
            ActionError: the reason, for the model.
        """
        if self.design == "waypoint" and not (choice.candidate and choice.candidate.turn):
            assert self.view is not None
            waypoint_goal(observation, self.view, choice, self.rules)

    def fly(
        self, observation: Observation, choice: Choice, candidates: tuple[Candidate, ...]
    ) -> Decision:
        """The move that carries out the model's ``choice`` (the first toward a waypoint),
        with what it chose among which ``candidates`` in the decision's ``extra``."""
        self.stopped = ""
        record = {
            "design": self.design,
            "choice": choice.to_dict(),
            "candidates": [c.to_dict() for c in candidates],
        }
        c = choice.candidate
        if self.design == "waypoint" and not (c and c.turn):
            assert self.view is not None
            point = waypoint_goal(observation, self.view, choice, self.rules)
            self.goal = _Goal(point, choice.text)
            decision = self._toward(observation, self.goal, planned=False)
            return replace(decision, extra={**decision.extra, **record})
        assert c is not None
        why = f"the model chose {choice.text}"
        decision = self.helmsman.steer(
            observation, c.bearing_deg, c.elevation_deg, why, choice.up_m
        )
        self._last = decision.action
        return replace(decision, extra={**record, "planned": False})

    def _turn_back(self, observation: Observation) -> Decision:
        """The turn back after the helmsman turned to look at a side it would shift to:
        a step of its own, not the model's."""
        decision = self.helmsman.steer(observation, 0.0, 0.0, "after a look aside")
        self._last = decision.action
        return replace(decision, extra={"design": self.design, "planned": True})

    def _toward(self, observation: Observation, goal: _Goal, planned: bool) -> Decision:
        """One admissible step toward ``goal``, no farther than it."""
        x, y, z = goal.point
        across = math.hypot(x, y)
        bearing = math.degrees(math.atan2(y, x))
        elevation = math.degrees(math.atan2(z, across))
        why = f"flying to the waypoint {across:.1f} m away, {_side(bearing)}"
        decision = self.helmsman.steer(observation, bearing, elevation, why, most_m=across)
        self.goal = replace(goal, steps=goal.steps + 1)
        self._last = decision.action
        extra: dict[str, object] = {
            "design": self.design,
            "planned": planned,
            "goal": [round(float(v), 3) for v in goal.point],
        }
        return replace(decision, extra=extra)


def _side(bearing: float) -> str:
    if abs(bearing) < 1.0:
        return "straight ahead"
    return f"{abs(bearing):.0f} degrees {'left' if bearing > 0 else 'right'}"
