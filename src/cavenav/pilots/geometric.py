"""The geometric baseline: the paper's strategy, executed by arithmetic on depth.

It sees exactly what the VLM sees (the normalised depth image, d_top and d_bottom, and
its own short history), never the mesh, and answers in the VLM's form: one admissible
action string and a justification in words (situation, constraints, choice). It follows
the prompt's strategy (SPEC section 3), so it is the yardstick a VLM pilot must beat:

1. Read the depth image as a point cloud in the camera frame and measure, for bearings
   across the field of view, how far a corridor the vehicle's size stays free: the body's
   section plus a margin, and where nothing new passes that or the walls are already
   nearer than the margin, plus a thin margin only (a crawlway the body fits through,
   flown with small steps and centring shifts).
2. Steer toward the middle of the farthest-reaching bearings (the passage's continuation)
   that lead somewhere new: the pilot's map of what it saw and where it flew
   (`cavenav.safety.cave_map`, placed by dead reckoning) tells a new direction from the way back.
   At a fork it keeps to the way the passage has led from the start, not to the branch
   that looks biggest from where the vehicle happens to point.
3. When nothing new is in view, turn toward an unexplored opening the map remembers;
   failing that, search by turning in place one way (never back and forth) through a full
   circle; only then is it a dead end, and the pilot backs out along the way it came,
   taking the unexplored opening it passes that leads on most nearly the way the passage
   has led. Turning back and forth on one spot (a heading it cannot take) starts that
   search too. Follow, search and back out are the pilot's modes (`_Mode`), changed
   only by the named transitions of its `_State`.
4. Centre vertically between ceiling and floor, following the passage's slope ahead.
5. Cap forward motion by the standoff rules: none within 1.5 m of an obstacle ahead,
   0.1-0.2 m (with a turn or a shift) below the 2.0 m standoff, otherwise 0.5-1.0 m.
6. Shrink the move until it is safe by the safety shield's own judgement of a move
   (`cavenav.safety.shield.move_hazard`, from the same memory of recent depth images that
   ``--shield`` judges any pilot with, the same `Margins` and the same choice of them,
   `cavenav.safety.shield.crawlway_move`): its half-diagonal plus a margin from every surface
   seen (already nearer, at most 5 cm nearer; in a crawlway, the reach of its corners
   plus a thin margin), clear of the ceiling and floor the sounders read, and into no
   space it has not seen free. A sideways shift toward a side never seen is made only
   after turning to look at it, and turning back.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Literal, NamedTuple

import numba
import numpy as np
from scipy import ndimage

from cavenav.core.types import DEFAULT_RULES, Action, Decision, Observation, Rules, VehicleBody
from cavenav.motion.actions import DEFAULT_SPACE, ActionSpace, format_action
from cavenav.safety.cave_map import CaveMap, Opening
from cavenav.safety.reckoning import DepthSamples, executed_since, sampling_stride
from cavenav.safety.shield import (
    DepthMemory,
    Hazard,
    Margins,
    Surroundings,
    crawlway_move,
    move_hazard,
)

__all__ = ["FreeView", "GeometricPilot", "GeometricPilotConfig"]

# Candidate directions, degrees: bearings span the 53-degree view, elevations most of the
# 41-degree vertical view (left and up positive).
_BEARINGS = np.arange(-25.0, 25.01, 2.5)
_ELEVATIONS = np.arange(-18.0, 18.01, 3.0)
# This many turns in place in a row that add up to less than a search's turn are
# dithering between two headings it cannot take: it searches instead.
_DITHER_STEPS = 6


@numba.njit(cache=True, nogil=True)
def free_lengths(
    points: np.ndarray,  # (n, 3) float32 surface points seen, in any frame
    directions: np.ndarray,  # (k, 3) float64 unit directions from that frame's origin
    radius: float,  # the corridor's radius
    limit: float,  # the length of a corridor nothing blocks
) -> np.ndarray:
    """(k,) float64: how far a cylinder of ``radius`` along each direction stays free of
    ``points`` (the first point inside it, ahead of the origin), at most ``limit``.

    In numpy this was six passes over an (n, k) array through OpenBLAS, 25 ms for 12,000
    points and 255 directions, and OpenBLAS left its threads spinning on both cores for
    the environment's next ray cast (70 ms instead of 48). Here it is one pass without
    temporaries, on one thread: 5 ms, and nothing left running.
    """
    k = directions.shape[0]
    free = np.full(k, limit)
    radius2 = radius * radius
    for i in range(points.shape[0]):
        px, py, pz = float(points[i, 0]), float(points[i, 1]), float(points[i, 2])
        norm2 = px * px + py * py + pz * pz
        for j in range(k):
            along = px * directions[j, 0] + py * directions[j, 1] + pz * directions[j, 2]
            if 0.0 < along < free[j] and norm2 - along * along < radius2:
                free[j] = along
    return free


@dataclass(frozen=True)
class GeometricPilotConfig:
    """Numbers of the strategy; the rules are the prompt's (SPEC section 3).

    The field of view, the depth range and where the camera sits come with each
    observation, as a real camera's calibration would.

    Attributes:
        rules: standoff, no-forward distance and the forward step inside the standoff.
        margins: the safety shield's margins (`cavenav.safety.shield.Margins`), one definition
            for both. ``open_m`` (0.3 m) widens the corridor tested along a bearing
            beyond the body's section (its half-diagonal across, 0.21 m), room for rough
            walls, and is kept beyond the body's half-diagonal from every surface;
            ``crawlway_m`` (0.1 m) is the thinner margin of a crawlway: the view is read
            with it where no corridor of the open margin leads anywhere new or a surface
            is nearer than the open margin allows, and moves keep it where the shield
            would judge them by it (`cavenav.safety.shield.crawlway_move`).
        open_range_m: a bearing free this far counts as the passage's continuation.
        stride: use every n-th pixel of the depth image; None follows the image's
            width to keep about `columns` of them: 5 at 640x480 (128x96 points), 2 at
            320x240, 1 at 160x120 and below, where every pixel counts.
        columns: about how many columns of the depth image the pilot reads when
            ``stride`` is None: 128, one every 0.4 degrees of the 53-degree view, as the
            strategy was tuned at 640x480.
        memory_frames: how many recent depth images the pilot remembers as points, moved
            by the actions the vehicle executed, to know the walls beside it that are out
            of view (the safety shield's memory: one piece of code serves both).
        body: the vehicle, whose half-diagonal every move keeps from remembered surfaces.
    """

    rules: Rules = DEFAULT_RULES
    margins: Margins = field(default_factory=Margins)
    open_range_m: float = 8.0
    stride: int | None = None
    columns: int = 128
    memory_frames: int = 8
    body: VehicleBody = field(default_factory=VehicleBody)

    def __post_init__(self) -> None:
        sampling_stride(640, self.stride, self.columns)  # refuse a bad setting here

    def corridor_radius(self, tight: bool = False) -> float:
        """Radius of the corridor tested along a bearing: the body's section plus a margin."""
        return self.margins.corridor_m(self.body, tight)


@dataclass(frozen=True)
class FreeView:
    """How far a corridor the body fits stays free along directions across the view
    (`GeometricPilot.survey`): ``free[i, j]`` metres along ``bearings_deg[i]`` (left
    positive) and ``elevations_deg[j]`` (up positive), from the camera; with the
    crawlway's thin margin where ``crawling``."""

    bearings_deg: np.ndarray
    elevations_deg: np.ndarray
    free: np.ndarray
    crawling: bool


@dataclass(frozen=True)
class _ViewOpening:
    """A far-reaching opening in view (degrees, metres; left and up positive)."""

    bearing: float  # its middle
    elevation: float
    free_m: float  # the farthest free length among its directions
    size: float  # the sum of its directions' free lengths: how big it looks
    visited: bool  # whether it leads back along the path flown
    tight: bool  # seen with the crawlway's thin margin only


@dataclass(frozen=True)
class _Scene:
    """What the pilot measured in one depth image (metres, degrees; left and up positive)."""

    free: np.ndarray  # (bearings, elevations) free corridor length along each direction
    tight_free: np.ndarray | None  # the same for the crawlway corridor, when it was needed
    openings: tuple[_ViewOpening, ...]  # largest first: full-margin ones, then crawlways
    ahead_m: float  # free corridor straight ahead
    nearest_m: float  # nearest remembered surface point beside or ahead, from the centre
    nearest_left: bool  # whether it lies to the left
    around: Surroundings  # what the shield's judgement of a move reads, measured once
    crawling: bool  # a surface is nearer than the open margin allows
    beside_m: float  # sideways distance of the nearer wall over the next 2 m
    left_offset_m: float  # sideways distance of the walls beside and up to 8 m ahead
    right_offset_m: float
    left_room_m: float  # mean depth of the left and right thirds of the image
    right_room_m: float

    @property
    def way_free(self) -> np.ndarray:
        """The free lengths a way on is read from: the crawlway corridor's in a crawlway
        (where it was measured), the full margin's elsewhere."""
        return self.tight_free if self.crawling and self.tight_free is not None else self.free


@dataclass(frozen=True)
class _Heading:
    """Where the pilot decided to go before sizing the move."""

    yaw: float
    elevation: float
    target_free: float  # free corridor along the new heading (0 when only turning)
    tight: bool  # through a crawlway: thin margins, small steps
    situation: str


@dataclass(frozen=True)
class _Search:
    """A search for a way on by turning in place one way, never back and forth, until a
    full circle has been seen."""

    origin: np.ndarray  # (3,) map position where it began
    side: float  # the way it turns: 1 left, -1 right
    turned_deg: float = 0.0


@dataclass(frozen=True)
class _Mode:
    """What the pilot is doing: following the way on, searching round for one, or backing
    out of a dead end.

    It follows while no search is under way and it is not backing out. A search ends when
    a new way on is found or the vehicle has moved 2 m from where it began; backing out
    begins once a search has turned all round, and ends when a new way on is found. The
    search that found the dead end stays under way while backing out begins, so that
    turning on that spot goes on the same way.
    """

    search: _Search | None = None
    backing_out: bool = False

    @property
    def name(self) -> Literal["follow", "search", "back out"]:
        return "back out" if self.backing_out else "search" if self.search else "follow"

    @property
    def searched_deg(self) -> float:
        """Degrees turned by the search under way (0 when none is)."""
        return self.search.turned_deg if self.search is not None else 0.0

    @property
    def strict(self) -> bool:
        """Whether a new opening must reach far: while searching or backing out, the
        short diagonals of the chamber it is turning in are no way on."""
        return self.backing_out or self.search is not None


@dataclass(frozen=True)
class _State:
    """Everything the pilot carries from one decision to the next besides its map and its
    memory of depth images; each change is a named transition that returns a new state.

    Attributes:
        mode: follow, search or back out (`_Mode`).
        last: the action it chose last (the memory and the map move by it when an
            observation does not say what was executed).
        recent: its latest actions, oldest first, at most `_DITHER_STEPS`.
        look_back: the turn back after turning to look at a side, if one is due.
        looked_from: map position of the last look at a side.
        dead_ends: map positions of dead ends searched all round.
        set_aside: map positions of remembered openings found impassable.
    """

    mode: _Mode = field(default_factory=_Mode)
    last: Action | None = None
    recent: tuple[Action, ...] = ()
    look_back: float = 0.0
    looked_from: np.ndarray | None = None
    dead_ends: tuple[np.ndarray, ...] = ()
    set_aside: tuple[np.ndarray, ...] = ()

    # ------------------------------------------------------------------ queries
    def dithering(self) -> bool:
        """Whether its latest actions turned back and forth on one spot."""
        recent = self.recent
        return (
            len(recent) == _DITHER_STEPS
            and not any(a.forward or a.right or a.up for a in recent)
            and abs(sum(a.yaw_deg for a in recent)) < 45.0
        )

    def in_dead_end(self, point: np.ndarray) -> bool:
        """Whether a map point lies in a dead end searched all round (the vehicle stops
        short of its end wall, out of the path's reach)."""
        return _near_any(point, self.dead_ends, 5.0)

    # ------------------------------------------------------------------ transitions
    def search_started(self, position: np.ndarray, side: float) -> _State:
        """A search begins here, turning toward ``side``."""
        return replace(self, mode=replace(self.mode, search=_Search(position.copy(), side)))

    def dithered(self, position: np.ndarray, side: float) -> _State:
        """Turning back and forth on one spot: a search begins instead, and the turns that
        were dithering are forgotten."""
        return replace(self.search_started(position, side), recent=())

    def moved_to(self, position: np.ndarray) -> _State:
        """The vehicle is at ``position``: a search it has moved 2 m away from found a way
        on, and ends."""
        search = self.mode.search
        if search is None or np.linalg.norm(position - search.origin) <= 2.0:
            return self
        return replace(self, mode=replace(self.mode, search=None))

    def following(self) -> _State:
        """A new way on was found: follow it."""
        return replace(self, mode=_Mode())

    def setting_aside(self, points: tuple[np.ndarray, ...]) -> _State:
        """Remembered openings at ``points`` were found impassable, for good."""
        return replace(self, set_aside=self.set_aside + points) if points else self

    def backing_out_of(self, dead_end: np.ndarray | None) -> _State:
        """A dead end searched all round (at ``dead_end`` when newly found): back out."""
        ends = self.dead_ends + ((dead_end.copy(),) if dead_end is not None else ())
        return replace(self, mode=replace(self.mode, backing_out=True), dead_ends=ends)

    def search_turned(self) -> _State:
        """The search turns one more step (45 degrees)."""
        search = self.mode.search
        assert search is not None
        turned = replace(search, turned_deg=search.turned_deg + 45.0)
        return replace(self, mode=replace(self.mode, search=turned))

    def looking(self, turn_back: float, position: np.ndarray) -> _State:
        """It turns to look at a side from ``position``; ``turn_back`` is the turn after."""
        return replace(self, look_back=turn_back, looked_from=position.copy())

    def turned_back(self) -> _State:
        """No turn back is due any more: made, or the look was not made as chosen."""
        return replace(self, look_back=0.0)

    def acted(self, action: Action) -> _State:
        """It chose ``action``."""
        return replace(self, last=action, recent=(*self.recent, action)[-_DITHER_STEPS:])


class GeometricPilot:
    """A passage follower with a memory; see the module docstring for the strategy.

    Between decisions it carries its map, its memory of depth images and one `_State`
    (its mode, follow, search or back out, and what it remembers of its own moves), which
    each decision replaces through named transitions.
    """

    name = "geometric"

    def __init__(
        self, config: GeometricPilotConfig | None = None, space: ActionSpace = DEFAULT_SPACE
    ):
        self.config = config or GeometricPilotConfig()
        self.space = space
        self.memory = DepthMemory(frames=self.config.memory_frames)  # the shield's memory
        self.map = CaveMap()  # where it has been and what it saw free
        bearings, elevations = np.meshgrid(_BEARINGS, _ELEVATIONS, indexing="ij")
        b, e = np.radians(bearings.ravel()), np.radians(elevations.ravel())
        # (k, 3) unit directions in (forward, left, up) for every (bearing, elevation).
        self._directions = np.stack([np.cos(e) * np.cos(b), np.cos(e) * np.sin(b), np.sin(e)], 1)
        self.reset()

    def reset(self) -> None:
        self.state = _State()
        self._surveyed: tuple[Observation, _Scene] | None = None
        self.memory.reset()
        self.map.reset()

    # ------------------------------------------------------------------ perception
    def _remember(self, observation: Observation, state: _State) -> None:
        """Remember what was seen: surfaces beside the vehicle are out of view now but were
        in view a few steps ago (the safety shield's memory, in the body frame), and the
        map of free space and the path flown. Both move by each executed action, or by the
        one chosen when the observation does not say."""
        moved_by = executed_since(observation, state.last)
        self.memory.update(observation, moved_by)
        self.map.update(observation, moved_by)

    def _measure(self, obs: Observation, state: _State) -> _Scene:
        """What the remembered surfaces and the current depth image say (`_Scene`)."""
        cfg = self.config
        height, width = obs.depth_png.shape
        seen = DepthSamples.of(obs, sampling_stride(width, cfg.stride, cfg.columns, height))
        around = Surroundings.of(
            obs, self.memory, cfg.body, cfg.margins, cfg.rules.no_forward_within_m
        )
        # In a crawlway (a surface nearer than the full keep-clear margin) the full
        # corridor fits nowhere but along the axis, and a slight offset reads it blocked:
        # only the thin margin's corridors tell the way on.
        crawling = around.nearest_m < cfg.margins.open_keep_m(cfg.body)
        free, tight_free, openings = self._view(seen, obs, crawling, state)
        # "At the vehicle's height" follows the passage's slope, so that a ceiling or floor
        # ahead of a descent or a climb is not mistaken for a side wall.
        elevation = openings[0].elevation if openings else 0.0
        walls = _walls(self.memory.cloud, elevation, cfg, obs.hfov_deg / 2, obs.depth_range[1])
        third = max(1, seen.depth.shape[1] // 3)  # an image 1 or 2 samples wide: both sides
        return _Scene(
            free=free,
            tight_free=tight_free,
            openings=tuple(openings),
            ahead_m=float(free[len(_BEARINGS) // 2, len(_ELEVATIONS) // 2]),
            nearest_m=walls.nearest_m,
            nearest_left=walls.nearest_left,
            around=around,
            crawling=crawling,
            beside_m=walls.beside_m,
            left_offset_m=walls.left_offset_m,
            right_offset_m=walls.right_offset_m,
            left_room_m=float(seen.depth[:, :third].mean()),
            right_room_m=float(seen.depth[:, -third:].mean()),
        )

    def _view(
        self, seen: DepthSamples, obs: Observation, crawling: bool, state: _State
    ) -> tuple[np.ndarray, np.ndarray | None, list[_ViewOpening]]:
        """Free length of a corridor the body fits along every direction, with the full
        margin, and, in a crawlway or where that finds nothing new, with the crawlway's
        thin one; and the openings they show."""
        cfg = self.config
        points = seen.points()[seen.surface]  # no-hit pixels read as D_max: they block nothing

        def free_for(tight: bool) -> np.ndarray:
            radius = float(cfg.corridor_radius(tight))
            free = free_lengths(points, self._directions, radius, float(obs.depth_range[1]))
            return free.reshape(len(_BEARINGS), len(_ELEVATIONS))

        free, tight_free = free_for(False), None
        openings = self._openings(free, obs.camera_offset_m, False, state)
        if crawling or all(o.visited for o in openings):
            tight_free = free_for(True)
            tight_openings = self._openings(tight_free, obs.camera_offset_m, True, state)
            openings = tight_openings if crawling else openings + tight_openings
        return free, tight_free, openings

    def _openings(
        self, free: np.ndarray, camera_offset_m: float, tight: bool, state: _State
    ) -> list[_ViewOpening]:
        """The far-reaching openings in ``free``, largest first, each marked new or visited.

        Directions that reach far are grouped into connected openings, so that two gaps
        either side of a boulder are never averaged into a bearing straight at it. An
        opening leads back when a point 8 m into it (or as far as it reaches) lies on the
        path flown.
        """
        best = float(free.max())
        if best < self._open_beyond_m:
            return []
        reach = free >= min(self.config.open_range_m, 0.85 * best)
        labels, count = ndimage.label(reach)
        found = []
        for label in range(1, count + 1):
            members = labels == label
            bi, ei = np.nonzero(members)
            bearing, elevation = _BEARINGS[bi].mean(), _ELEVATIONS[ei].mean()
            if not members[
                np.argmin(np.abs(_BEARINGS - bearing)), np.argmin(np.abs(_ELEVATIONS - elevation))
            ]:
                # A curved opening whose middle is blocked: take its member nearest the middle.
                k = np.argmin(np.hypot(_BEARINGS[bi] - bearing, _ELEVATIONS[ei] - elevation))
                bearing, elevation = _BEARINGS[bi[k]], _ELEVATIONS[ei[k]]
            reaches = float(free[members].max())
            b, e = math.radians(bearing), math.radians(elevation)
            far = min(reaches, 8.0) * np.array(
                [math.cos(e) * math.cos(b), math.cos(e) * math.sin(b), math.sin(e)]
            )
            far[0] += camera_offset_m
            visited = self._explored(self.map.to_map(far[None])[0], state)
            size = float(free[members].sum())
            found.append(
                _ViewOpening(float(bearing), float(elevation), reaches, size, visited, tight)
            )
        return sorted(found, key=lambda o: -o.size)

    @property
    def _open_beyond_m(self) -> float:
        """An opening must stay free this far: less is a wall to turn away from."""
        return max(self.config.rules.no_forward_within_m + 1.0, 0.35 * self.config.open_range_m)

    def _explored(self, point: np.ndarray, state: _State) -> bool:
        """Whether a map point lies in a dead end searched all round or on the path flown."""
        return state.in_dead_end(point) or bool(self.map.visited(point[None])[0])

    # ------------------------------------------------------------------ where to go
    def _snap_up(self, metres: float) -> float:
        lo, hi = self.space.vertical_range_m
        if abs(metres) < 0.5 * lo:
            return 0.0
        return math.copysign(round(min(max(abs(metres), lo), hi), 2), metres)

    def _free_along(self, free: np.ndarray, bearing: float, elevation: float) -> float:
        i = int(np.argmin(np.abs(_BEARINGS - bearing)))
        j = int(np.argmin(np.abs(_ELEVATIONS - elevation)))
        return float(free[i, j])

    def _choose_yaw(
        self, free: np.ndarray, bearing: float, elevation: float, half_view: float
    ) -> float:
        """The admissible yaw nearest ``bearing`` whose corridor is open; else the nearest."""
        options = sorted(
            (y for a in self.space.yaw_deg for y in {a, -a} if abs(y) <= half_view),
            key=lambda y: abs(y - bearing),
        )
        for yaw in options[:3]:
            if self._free_along(free, yaw, elevation) >= 2 * self.config.rules.no_forward_within_m:
                return float(yaw)
        return float(options[0])

    def _turn_toward(self, bearing: float) -> float:
        """The admissible yaw nearest ``bearing``, at most 90 degrees: a big turn is made
        in steps, looking at each."""
        options = [y for a in self.space.yaw_deg for y in (a, -a) if 0 < abs(y) <= 90]
        return float(min(options, key=lambda y: (abs(y - bearing), -abs(y))))

    def _follow(self, scene: _Scene, opening: _ViewOpening, why: str, half_view: float) -> _Heading:
        """Head into ``opening`` in view."""
        free = scene.tight_free if opening.tight else scene.free
        assert free is not None
        yaw = self._choose_yaw(free, opening.bearing, opening.elevation, half_view)
        target_free = self._free_along(free, yaw, opening.elevation)
        where = _bearing_words(opening.bearing, opening.elevation)
        crawl = " through a crawlway the body just fits" if opening.tight else ""
        return _Heading(
            yaw,
            opening.elevation,
            target_free,
            opening.tight,
            f"{why} {opening.free_m:.1f} m toward {where}{crawl}",
        )

    def _heading(self, scene: _Scene, half_view: float, state: _State) -> tuple[_Heading, _State]:
        """Where to go, and the state that follows: back toward the way on after a look at
        a side; else new ground in view, else new ground remembered, else back out of a
        dead end searched all round, else search round."""
        if state.look_back:
            side = "left" if state.look_back < 0 else "right"
            situation = f"looked at the {side} side; turning back to the way on"
            return _turn(state.look_back, situation), state.turned_back()
        position = self.map.position
        if state.dithering() and state.mode.search is None:
            state = state.dithered(position, _toward_roomier(scene, 1.0))  # look round
        state = state.moved_to(position)
        reach = self.config.open_range_m if state.mode.strict else 0.0
        new = [o for o in scene.openings if not o.visited and o.free_m >= reach]
        if new:
            heading = self._follow(scene, self._way_on(new), "the passage continues", half_view)
            return heading, state.following()
        remembered, in_view, impassable = self._unexplored(scene, half_view, state)
        state = state.setting_aside(impassable)
        if in_view is not None:
            why = "an unexplored opening seen before continues"
            return self._follow(scene, in_view, why, half_view), state
        if remembered is not None:
            situation = (
                f"nothing new in view; an unexplored opening seen before lies "
                f"{_bearing_words(remembered.bearing_deg, 0.0)}"
            )
            return _turn(self._turn_toward(remembered.bearing_deg), situation), state
        if state.mode.backing_out or state.mode.searched_deg >= 360.0:
            way_back, state = self._back_out(scene, half_view, state)
            if way_back is not None:
                return way_back, state
        return self._search_round(scene, state)

    def _way_led(self) -> np.ndarray | None:
        """(2,) unit horizontal direction in the map from the start (its origin) to here:
        the way the passage has led; None within 5 m of the start, where it has led
        nowhere yet."""
        travel = self.map.position[:2]
        distance = float(np.linalg.norm(travel))
        return travel / distance if distance >= 5.0 else None

    def _way_on(self, new: list[_ViewOpening]) -> _ViewOpening:
        """Of the new openings in view, the one to follow: at a fork, the one that leads
        on most nearly the way the passage has led (`_way_led`), the largest of those
        within 15 degrees of it. How big an opening looks says more about where the
        vehicle happens to point than about the cave: a side passage straight ahead
        looks bigger than the main one at the edge of the view."""
        forks = [o for o in new if o.tight == new[0].tight]
        led = self._way_led()
        if len(forks) < 2 or led is None:
            return new[0]
        off_heading = math.degrees(self.map.heading - math.atan2(led[1], led[0]))
        turns = [abs(_wrap_deg(off_heading + o.bearing)) for o in forks]
        near = [o for o, t in zip(forks, turns, strict=True) if t <= min(turns) + 15.0]
        return max(near, key=lambda o: o.size)

    def _unexplored(
        self, scene: _Scene, half_view: float, state: _State
    ) -> tuple[Opening | None, _ViewOpening | None, tuple[np.ndarray, ...]]:
        """The nearest-bearing opening the map remembers that leads somewhere new, the
        opening in view that continues it when it lies in view, and the ends of those
        found impassable on the way.

        One that lies in view while the view finds no opening along it is impassable (a
        crack too narrow for the body): the caller sets it aside for good.
        """
        impassable: list[np.ndarray] = []
        for opening in self._in_order(self.map.openings(), state):
            end = np.asarray(opening.end)
            set_aside = state.set_aside + tuple(impassable)
            if self._explored(end, state) or _near_any(end, set_aside, 2.0):
                continue
            if abs(opening.bearing_deg) > half_view - 5.0:
                return opening, None, tuple(impassable)
            along = [
                o
                for o in scene.openings
                if not o.visited and abs(o.bearing - opening.bearing_deg) <= 10.0
            ]
            if along:
                return opening, along[0], tuple(impassable)
            impassable.append(end)
        return None, None, tuple(impassable)

    def _in_order(self, openings: list[Opening], state: _State) -> list[Opening]:
        """Remembered openings in the order to try them: the one nearest the heading
        first; but backing out of a dead end, the one that leads on most nearly the way
        the passage has led (`_way_led`). The heading then points back along the dead
        end, and the opening nearest it is often the next side passage across the one
        the vehicle was following (a maze's junction): the way on is the one that keeps
        going away from the entrance."""
        led = self._way_led()
        if not state.mode.backing_out or led is None:
            return sorted(openings, key=lambda o: abs(o.bearing_deg))

        def turn_from_led(opening: Opening) -> float:
            way = np.asarray(opening.end[:2]) - self.map.position[:2]
            return -float(way @ led / (np.linalg.norm(way) + 1e-9))

        return sorted(openings, key=turn_from_led)

    def _back_out(
        self, scene: _Scene, half_view: float, state: _State
    ) -> tuple[_Heading | None, _State]:
        """Searched all round and found nothing new: a dead end; the way it came, if it
        sees or remembers one."""
        position = self.map.position
        found = not state.mode.backing_out and not state.in_dead_end(position)
        state = state.backing_out_of(position if found else None)
        ways_back = [o for o in scene.openings if o.visited] or list(scene.openings)
        if ways_back:
            why = "dead end: backing out along the way it came,"
            return self._follow(scene, ways_back[0], why, half_view), state
        back = [o for o in self.map.openings() if self._explored(np.asarray(o.end), state)]
        if not back:
            return None, state
        way = min(back, key=lambda o: abs(o.bearing_deg))
        situation = f"dead end: turning to the way it came, {_bearing_words(way.bearing_deg, 0)}"
        return _turn(self._turn_toward(way.bearing_deg), situation), state

    def _search_round(self, scene: _Scene, state: _State) -> tuple[_Heading, _State]:
        """Search: turn in place one way, never back and forth, until a full circle is seen."""
        if state.mode.search is None:
            state = state.search_started(self.map.position, _toward_roomier(scene, 1.0))
        state = state.search_turned()
        search = state.mode.search
        assert search is not None
        best = float(scene.free.max())
        what = (
            "the only way on in view leads back"
            if scene.openings
            else f"no direction in view stays free beyond {best:.1f} m"
        )
        situation = f"{what}; searching round ({search.turned_deg:.0f} deg)"
        return _turn(search.side * 45.0, situation), state

    # ------------------------------------------------------------------ how far
    def _hazard(self, action: Action, around: Surroundings) -> Hazard:
        """Why the move of ``action`` is unsafe by the shield's own judgement of a move,
        with the shield's margins; falsy when it is safe."""
        cfg = self.config
        judged = crawlway_move(
            action,
            around,
            body=cfg.body,
            margins=cfg.margins,
            no_forward_m=cfg.rules.no_forward_within_m,
        )
        return move_hazard(
            action, around, body=cfg.body, margins=cfg.margins, crawlway=judged.crawlway
        )

    def _keep_clear(self, action: Action, around: Surroundings) -> tuple[Action, str]:
        """Shrink ``action`` until its move is safe (`_hazard`): the sideways shift dropped
        first, then the forward step shortened (a climb or a descent straight up or down
        stays in the sounders' column, seen free), then the vertical shift dropped too; a
        turn in place is always left.

        Returns the action to take and, if it had to be changed, why.
        """
        why = self._hazard(action, around)
        if not why:
            return action, ""
        shorter = [f for f in (0.5, 0.2, 0.1, 0.0) if f < action.forward]
        candidates = [replace(action, right=0.0)]
        candidates += [replace(action, right=0.0, forward=f) for f in shorter]
        candidates += [replace(action, right=0.0, up=0.0, forward=f) for f in shorter]
        turn_only = Action(yaw_deg=action.yaw_deg)
        for candidate in dict.fromkeys(candidates):  # each once, in order
            if candidate not in (action, turn_only) and not self._hazard(candidate, around):
                return candidate, f"{why.text}, so it becomes '{format_action(candidate)}'"
        return turn_only, f"{why.text}: turning in place only"

    def _look_first(self, move: Action, scene: _Scene, state: _State) -> float:
        """The turn to look at the side that ``move``, with a sideways shift, would enter
        when that space was never seen free (0 when it was, or when a look cannot help)."""
        if not move.right or scene.crawling:  # in a crawlway the turn itself has no room
            return 0.0
        if state.looked_from is not None and (
            np.linalg.norm(self.map.position - state.looked_from) < 0.5
        ):
            return 0.0  # it looked from here already: what stays unseen stays unknown
        if self._hazard(move, scene.around).kind != "unseen":
            return 0.0
        look = max(y for y in self.space.yaw_deg if y <= 90.0)
        return look if move.right < 0 else -look

    def _lateral(
        self, scene: _Scene, forward: float, yaw: float, state: _State
    ) -> tuple[float, float]:
        """The sideways shift, and the turn to look first at the side it enters (0: none).

        It shifts away from a wall seen closer than the standoff when the other side has
        more room (0.2 m more: back to the middle, where the standoff may hold again); a
        side out of view that was never seen free is looked at first.
        """
        cfg = self.config
        near_offset = min(scene.left_offset_m, scene.right_offset_m)
        gap = abs(scene.left_offset_m - scene.right_offset_m)
        if not (near_offset < cfg.rules.standoff_m and gap > 0.2 and abs(yaw) <= 20):
            return 0.0, 0.0
        # Never nearer the far wall than a crawlway's margin: the wall beside the body is
        # out of view and known only as far as it was seen ahead.
        room = max(scene.left_offset_m, scene.right_offset_m) - cfg.corridor_radius(True)
        wanted = 0.5 if gap > 2.0 else 0.2 if gap > 1.0 else 0.1
        magnitude = max((m for m in self.space.lateral_m if m <= min(wanted, room)), default=0)
        right = magnitude if scene.left_offset_m < scene.right_offset_m else -magnitude
        look = self._look_first(Action(forward=forward, right=right, yaw_deg=yaw), scene, state)
        return right, look

    def _propose(
        self, heading: _Heading, scene: _Scene, obs: Observation, nearest: float, state: _State
    ) -> tuple[Action, str, _State]:
        """The move toward ``heading`` by the standoff rules, before it is kept clear of
        what was seen; why it is capped; the state after a look at a side."""
        rules, yaw = self.config.rules, heading.yaw
        forward, constraint = _cap_forward(rules, heading, nearest, obs.hfov_deg / 2)
        # Vertical: centre between ceiling and floor (where both sounders read: an unknown
        # side is never moved toward to centre), and follow the passage's slope.
        centre = 0.5 * (obs.d_top - obs.d_bottom) if math.isfinite(obs.d_top - obs.d_bottom) else 0
        up = centre + math.tan(math.radians(heading.elevation)) * forward
        up = self._snap_up(float(np.clip(up, -1.0, 1.0)))
        right, look = self._lateral(scene, forward, yaw, state)
        # Below the standoff, forward motion must come with a turn or a shift: in a
        # crawlway, or where the side it would shift to was never seen, a 5-degree turn,
        # which costs no room; elsewhere a shift away from the nearer wall.
        if forward > 0 and nearest < rules.standoff_m and not (yaw or right or up):
            shift = 0.1 if scene.left_offset_m < scene.right_offset_m else -0.1
            if heading.tight or self._hazard(Action(right=shift), scene.around).kind == "unseen":
                yaw = _toward_roomier(scene, 5.0)
            else:
                right = shift
        if not (forward or right or up or yaw):  # never idle: look for a way on
            yaw = _toward_roomier(scene, 20.0)
        if look:
            side = "left" if right < 0 else "right"
            constraint += (
                f"; the {side} side was never seen free: turning to look before moving to it"
            )
            return Action(yaw_deg=look), constraint, state.looking(-look, self.map.position)
        return Action(forward=forward, right=right, up=up, yaw_deg=yaw), constraint, state

    def _make_safe(self, proposed: Action, scene: _Scene, nearest: float) -> tuple[Action, str]:
        """``proposed`` kept clear of what was seen (`_keep_clear`), still with a turn or a
        shift inside the standoff, and admissible; and why it had to change, if it did."""
        action, shielded = self._keep_clear(proposed, scene.around)
        if (
            action.forward
            and nearest < self.config.rules.standoff_m
            and not (action.yaw_deg or action.right or action.up)
        ):
            # The shift that came with it was refused: a 5-degree turn instead, as the
            # standoff asks, toward the roomier side.
            turn = _toward_roomier(scene, 5.0)
            action = replace(action, yaw_deg=turn)
            if self._hazard(action, scene.around):
                action = Action(yaw_deg=turn)
        return self.space.validate(action), shielded

    def decide(self, observation: Observation) -> Decision:
        state = self.state
        self._remember(observation, state)
        scene = self._measure(observation, state)
        state = self._looked_as_chosen(observation, state)
        heading, state = self._heading(scene, observation.hfov_deg / 2, state)
        return self._move(observation, scene, heading, state)

    # ------------------------------------------------------------------ steered by another
    def survey(self, observation: Observation) -> FreeView:
        """Remember and measure ``observation`` for a pilot that chooses where to go
        another way (a VLM's numbered arrow or waypoint, `cavenav.pilots.designs`); then
        `steer` sizes and keeps clear the move toward its choice, once per observation."""
        self._remember(observation, self.state)
        scene = self._measure(observation, self.state)
        self._surveyed = (observation, scene)
        return FreeView(_BEARINGS, _ELEVATIONS, scene.way_free, scene.crawling)

    def steer(
        self,
        observation: Observation,
        bearing: float,
        elevation: float,
        why: str,
        up_m: float | None = None,
        most_m: float = math.inf,
    ) -> Decision:
        """The move toward ``bearing`` and ``elevation`` (degrees, left and up positive)
        that this pilot's standoff rules and keep-clear judgement allow, for the
        observation last surveyed: at most ``most_m`` forward, ``up_m`` up or down
        where given instead of centring between ceiling and floor.

        A bearing outside the view is turned toward first, in admissible steps.
        """
        assert self._surveyed is not None and self._surveyed[0] is observation, (
            "survey the observation before steering by it"
        )
        scene = self._surveyed[1]
        state = self._looked_as_chosen(observation, self.state)
        half_view = observation.hfov_deg / 2
        if state.look_back:
            heading, state = (
                _turn(state.look_back, "turning back to the way chosen"),
                state.turned_back(),
            )
        elif abs(bearing) > half_view:
            heading = _turn(self._turn_toward(bearing), f"{why}: turning toward it")
        else:
            reach = self._free_along(scene.way_free, bearing, elevation)
            chosen = _ViewOpening(bearing, elevation, reach, reach, False, scene.crawling)
            heading = self._follow(scene, chosen, why, half_view)
        forward = max((f for f in self.space.forward_m if f <= most_m), default=0.0)
        return self._move(observation, scene, heading, state, up_m, forward)

    def owes_turn_back(self, observation: Observation) -> bool:
        """Whether the next move must turn back from a look at a side (`steer` makes it,
        whatever it is told): a pilot that steers this one need not choose that step."""
        return bool(self._looked_as_chosen(observation, self.state).look_back)

    def _looked_as_chosen(self, observation: Observation, state: _State) -> _State:
        """``state``, without the turn back it owes when its look at a side was not made
        as chosen (a shield changed it): there is nothing to turn back from."""
        executed = observation.previous_action
        if state.look_back and executed is not None and executed.yaw_deg != -state.look_back:
            return state.turned_back()
        return state

    def _move(
        self,
        observation: Observation,
        scene: _Scene,
        heading: _Heading,
        state: _State,
        up_m: float | None = None,
        most_forward: float = math.inf,
    ) -> Decision:
        """The decision that flies toward ``heading``: sized by the standoff rules, at
        most ``most_forward`` ahead, ``up_m`` up where given, kept clear of what was seen."""
        d_top, d_bottom = observation.d_top, observation.d_bottom
        # The standoff counts walls beside the next move's path: they will be beside us. A
        # sounder that reads nothing sure (NaN) counts for nothing here; the moves toward
        # it are refused as never seen free (`_keep_clear`).
        sounded = [d for d in (d_top, d_bottom) if not math.isnan(d)]
        nearest = min(*sounded, scene.nearest_m, scene.ahead_m, scene.beside_m)
        proposed, constraint, state = self._propose(heading, scene, observation, nearest, state)
        if proposed.forward > most_forward:
            proposed = replace(proposed, forward=most_forward)
        if up_m is not None:
            proposed = replace(proposed, up=up_m)
        action, shielded = self._make_safe(proposed, scene, nearest)
        if shielded:
            constraint += f"; {shielded}"
        self.state = state.acted(action)
        text = format_action(action)
        justification = (
            f"Situation: {heading.situation}; free straight ahead {scene.ahead_m:.1f} m; "
            f"ceiling {_metres(d_top)}, floor {_metres(d_bottom)}; nearest surface "
            f"{scene.nearest_m:.1f} m {'left' if scene.nearest_left else 'right'}. "
            f"Constraints: {constraint}. Choice: {text}"
            f"{_why(action.yaw_deg, action.up, action.right)}."
        )
        return Decision(
            action=action, action_text=text, justification=justification, raw=justification
        )


def _metres(distance: float) -> str:
    return "unknown" if math.isnan(distance) else f"{distance:.1f} m"


def _toward_roomier(scene: _Scene, degrees: float) -> float:
    """A turn of ``degrees`` toward the side whose third of the image reaches farther on
    average; to the left when both reach as far."""
    return degrees if scene.left_room_m >= scene.right_room_m else -degrees


def _bearing_words(bearing: float, elevation: float) -> str:
    words = []
    if abs(bearing) >= 2.5:
        words.append(f"{abs(bearing):.0f} deg {'left' if bearing > 0 else 'right'}")
    if abs(elevation) >= 3:
        words.append(f"{abs(elevation):.0f} deg {'up' if elevation > 0 else 'down'}")
    return ", ".join(words) if words else "straight ahead"


def _why(yaw: float, up: float, right: float) -> str:
    reasons = []
    if yaw:
        reasons.append("turning toward the open passage")
    if up:
        reasons.append("re-centring between ceiling and floor")
    if right:
        reasons.append("moving away from the nearer wall")
    return (", " + " and ".join(reasons)) if reasons else ", holding the passage centre"


class _Walls(NamedTuple):
    """Where the remembered surfaces lie beside and ahead of the body (metres)."""

    nearest_m: float  # nearest surface point beside or ahead, from the centre
    nearest_left: bool  # whether it lies to the left
    beside_m: float  # sideways distance of the nearer wall over the next 2 m
    left_offset_m: float  # sideways distance of the walls beside and up to 8 m ahead
    right_offset_m: float


def _walls(
    cloud: np.ndarray, elevation: float, cfg: GeometricPilotConfig, half_view: float, d_max: float
) -> _Walls:
    """Measure the walls in ``cloud`` (n, 3), the remembered surfaces in the body frame,
    "at the vehicle's height" along a passage climbing at ``elevation`` degrees."""
    slope = math.tan(math.radians(elevation))
    at_height = (
        np.abs(cloud[:, 2] - slope * np.maximum(cloud[:, 0], 0.0))
        < 0.5 * cfg.body.height + cfg.margins.open_m + 0.3
    )
    beside = at_height & (cloud[:, 0] > -1.5) & (cloud[:, 0] < 8.0)
    # Ahead, not beside: nearer the axis than a crawlway's corridor, beyond the bow.
    beside &= ~((np.abs(cloud[:, 1]) < cfg.corridor_radius(tight=True)) & (cloud[:, 0] > 1.0))
    span = 8.0 * math.tan(math.radians(half_view))  # an unseen wall is at least this far
    left_offset, right_offset = _wall_offsets(cloud, beside, (span, span))  # to the middle
    # For the standoff: what lies beside the body and the longest move (1 m) ahead;
    # a side the recent images do not show there (out of view at the start, or
    # creeping: eight images cover 1.6 m) is taken to continue the wall seen up to
    # 5 m ahead. Surfaces behind the body's middle fall behind as it moves on.
    not_behind = cloud[:, 0] > -0.25
    soon = _wall_offsets(cloud, beside & not_behind & (cloud[:, 0] < 5.0), (span, span))
    beside_now = _wall_offsets(cloud, beside & not_behind & (cloud[:, 0] < 2.0), soon)
    distance = np.where(not_behind, np.linalg.norm(cloud, axis=1), np.inf)
    nearest = int(np.argmin(distance)) if not_behind.any() else -1
    return _Walls(
        nearest_m=float(distance[nearest]) if nearest >= 0 else d_max,
        nearest_left=bool(cloud[nearest, 1] > 0) if nearest >= 0 else True,
        beside_m=min(beside_now),
        left_offset_m=left_offset,
        right_offset_m=right_offset,
    )


def _wall_offsets(
    cloud: np.ndarray, window: np.ndarray, unseen: tuple[float, float]
) -> tuple[float, float]:
    """Sideways distances of the left and right walls among the points of ``cloud`` in
    ``window`` (n,) bool; ``unseen`` where a side shows none. The 5th percentile: the
    wall, not the single most protruding knob of rock."""
    lefts, rights = (
        cloud[window & (cloud[:, 1] > 0), 1],
        -cloud[window & (cloud[:, 1] < 0), 1],
    )
    return (
        float(np.percentile(lefts, 5)) if lefts.size else unseen[0],
        float(np.percentile(rights, 5)) if rights.size else unseen[1],
    )


def _cap_forward(
    rules: Rules, heading: _Heading, nearest: float, half_view: float
) -> tuple[float, str]:
    """The forward step the standoff rules allow toward ``heading``, ``nearest`` the
    nearest surface, and the rule that set it in words."""
    yaw, target_free = heading.yaw, heading.target_free
    if target_free < rules.no_forward_within_m:
        return 0.0, f"obstacle within {rules.no_forward_within_m} m ahead: no forward motion"
    if abs(yaw) > half_view:
        return 0.0, "the new heading lies outside the view: turn first, no forward motion"
    if nearest < rules.standoff_m:
        slowest, slow = rules.slow_forward_m
        forward = slow if target_free > 3.0 else slowest
        return forward, (
            f"nearest surface {nearest:.1f} m is inside the {rules.standoff_m} m standoff: "
            f"forward capped at {forward} m"
        )
    if abs(yaw) >= 15:
        # In a bend the inner wall is beside the vehicle, out of view: go gently.
        return 0.5, "turning into a bend whose inner wall is out of view: forward 0.5 m"
    forward = 1.0 if target_free > 6.0 else 0.5
    return forward, f"all clearances above the {rules.standoff_m} m standoff"


def _turn(yaw: float, situation: str) -> _Heading:
    """A turn in place."""
    return _Heading(yaw, 0.0, 0.0, False, situation)


def _wrap_deg(angle: float) -> float:
    """``angle`` in degrees, wrapped into [-180, 180)."""
    return (angle + 180.0) % 360.0 - 180.0


def _near_any(point: np.ndarray, points: tuple[np.ndarray, ...], distance: float) -> bool:
    """Whether ``point`` lies within ``distance`` of any of ``points``."""
    return any(np.linalg.norm(point - p) < distance for p in points)
