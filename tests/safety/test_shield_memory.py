"""The shield's memory and measures: what it remembers of each depth image, where it
places it after a move, which space it calls seen free, and the margins it keeps.

Most tests read hand-made depth images (a wall with a hole, a rock one block wide) or
hand-made frames and clouds, whose answers are known by hand: they run in milliseconds.
Body frame: (forward, left, up) in metres from the vehicle's centre. The simulator's
camera (`synthetic_observation`) is 640x480 with a focal length of 640 px, 0.2 m ahead
of the centre; at that size the memory keeps one block of 10 x 10 pixels per point.
"""

from __future__ import annotations

import math
import re
from dataclasses import replace

import numpy as np
import pytest

from cavenav.core.errors import ConfigError
from cavenav.core.types import Action, Observation, VehicleBody
from cavenav.motion.actions import parse_action
from cavenav.safety.shield import (
    DepthMemory,
    Margins,
    SeenFrame,
    Shield,
    Surroundings,
    crawlway_move,
    move_hazard,
)
from cavenav.sensors.depth import normalise_depth
from tests.conftest import synthetic_observation as seen

BODY = VehicleBody()  # half-diagonal 0.312 m, corners' reach 0.286 m, section 0.211 m
FOCAL_PX = 640.0  # the simulator's camera: 53.13 degrees across 640 pixels
CAMERA_M = 0.2  # the camera sits this far ahead of the centre


def judged(action: str, *observations: Observation):
    shield = Shield()
    for obs in observations:
        shield.observe(obs)
    return shield.judge(parse_action(action))


def sized(
    depth_m: float | np.ndarray,
    width: int,
    height: int,
    depth_range: tuple[float, float] = (0.0, 20.0),
    **fields: object,
) -> Observation:
    """`synthetic_observation` at ``width`` x ``height`` pixels (same field of view)."""
    depth = np.broadcast_to(np.float32(depth_m), (height, width)).astype(np.float32)
    return replace(
        seen(np.inf, **fields),
        rgb=np.zeros((height, width, 3), np.uint8),
        depth_m=depth,
        depth_png=normalise_depth(depth, *depth_range),
        depth_range=depth_range,
    )


def remembered(*observations: Observation, **settings: object) -> DepthMemory:
    memory = DepthMemory(**settings)
    for obs in observations:
        memory.update(obs, obs.previous_action)
    return memory


def through_pixel(col_px: float, row_px: float, ahead_m: float) -> np.ndarray:
    """(1, 3) the body-frame point ``ahead_m`` in front of the simulator's camera, seen
    at pixel (col_px, row_px) of the 640x480 image."""
    left = (320.0 - col_px) / FOCAL_PX * ahead_m
    up = (240.0 - row_px) / FOCAL_PX * ahead_m
    return np.array([[CAMERA_M + ahead_m, left, up]])


def block(row: int, col: int, ahead_m: float) -> np.ndarray:
    """(1, 3) the point ``ahead_m`` in front of the camera at the centre of 10 x 10 block."""
    return through_pixel(10 * col + 5, 10 * row + 5, ahead_m)


def frame(depth: np.ndarray, yaw_deg: float = 0.0, origin=(0.0, 0.0, 0.0)) -> SeenFrame:
    """A remembered 640x480 image read in blocks of 10 px: ``depth`` is (48, 64) metres."""
    assert depth.shape == (48, 64)
    return SeenFrame(
        points=np.empty((0, 3), np.float32),
        depth=depth.astype(np.float32),
        origin=np.asarray(origin, np.float32),
        yaw_deg=yaw_deg,
        focal_px=FOCAL_PX,
        stride=10,
        width=640,
        height=480,
    )


def around(cloud, memory: DepthMemory | None = None, d_top=3.0, d_bottom=3.0) -> Surroundings:
    """What a move is judged by when the surfaces remembered are the points ``cloud``."""
    cloud = np.asarray(cloud, np.float32).reshape(-1, 3)
    return Surroundings(
        cloud=cloud,
        memory=memory or DepthMemory(),
        d_top=d_top,
        d_bottom=d_bottom,
        camera_offset_m=CAMERA_M,
        nearest_m=float(np.linalg.norm(cloud, axis=1).min()) if len(cloud) else math.inf,
        pinched=False,
    )


# ------------------------------------------------------------------ memory settings
@pytest.mark.parametrize(("stride", "columns"), [(0, 64), (-2, 64), (None, 0), (3, 0)])
def test_a_stride_or_column_count_below_1_is_refused_when_the_memory_is_built(
    stride: int | None, columns: int
) -> None:
    message = (
        f"stride {stride} and columns {columns}: give a stride of at least 1 (or None) "
        "and at least 1 column"
    )
    with pytest.raises(ConfigError, match=re.escape(message)):
        DepthMemory(stride=stride, columns=columns)


@pytest.mark.parametrize(
    ("width", "height", "settings", "stride"),
    [
        (640, 480, {}, 10),  # about 64 columns: every 10th pixel
        (160, 120, {}, 2),
        (84, 84, {}, 1),  # a coarser block would see an 84-pixel view as a few pixels
        (640, 480, {"stride": 4}, 4),  # a stride given is kept
        (84, 84, {"stride": 1}, 1),
        (84, 84, {"columns": 1}, 84),  # one column: the whole width in one block
        (640, 480, {"columns": 1, "stride": 16}, 16),
        (8192, 10, {}, 10),  # never more than the height: a wide, flat image keeps a row
        (640, 4, {"stride": 16}, 4),
    ],
)
def test_the_memory_reads_every_nth_pixel_as_set_or_about_64_columns(
    width: int, height: int, settings: dict, stride: int
) -> None:
    memory = remembered(sized(5.0, width, height), **settings)
    (kept,) = memory.frames
    assert kept.stride == stride
    assert kept.depth.shape == (height // stride, width // stride)
    # One surface point per stride-th pixel, and the two sounders' readings.
    rows, cols = len(range(0, height, stride)), len(range(0, width, stride))
    assert len(memory.cloud) == rows * cols + 2


def test_the_memory_keeps_the_last_8_depth_images_by_default() -> None:
    memory = remembered(*[seen(5.0, previous_action=Action(forward=0.1)) for _ in range(10)])
    assert len(memory.frames) == 8
    assert len(remembered(seen(5.0), seen(5.0), frames=1).frames) == 1


def test_surfaces_beyond_10_m_are_not_remembered_as_points_by_default() -> None:
    # Sounders reading 50 m (nothing in range) add no points either.
    assert remembered(seen(10.5, d_top=50.0, d_bottom=50.0)).cloud.shape == (0, 3)
    near = remembered(seen(9.5, d_top=50.0, d_bottom=50.0)).cloud
    assert len(near) == 48 * 64
    assert near[:, 0] == pytest.approx(9.5 + CAMERA_M, abs=0.05)  # 8-bit depth: 8 cm steps


def test_where_nothing_is_in_range_no_surface_is_remembered_however_far_the_memory_reaches():
    memory = remembered(seen(np.inf, d_top=50.0, d_bottom=50.0), max_range_m=100.0)
    assert memory.cloud.tolist() == [[0.0, 0.0, 50.0], [0.0, 0.0, -50.0]]


def test_the_sounders_readings_are_remembered_straight_above_and_below_the_centre() -> None:
    memory = remembered(seen(np.inf, d_top=1.5, d_bottom=2.5))
    assert memory.cloud.tolist() == [[0.0, 0.0, 1.5], [0.0, 0.0, -2.5]]


def test_a_depth_image_is_read_in_its_own_depth_range() -> None:
    # A wall 3 m from the camera, in an image whose grey levels span 0-10 m, not 0-20 m.
    memory = remembered(sized(3.0, 640, 480, depth_range=(0.0, 10.0)))
    surface = memory.cloud[:-2]  # the sounders' two points come last
    assert len(surface) == 48 * 64
    assert surface[:, 0] == pytest.approx(3.0 + CAMERA_M, abs=0.05)  # 8-bit depth: 4 cm steps
    in_front, behind = block(24, 32, 2.6), block(24, 32, 3.5)
    assert memory.seen_free(np.concatenate([in_front, behind]), 0.3).tolist() == [True, False]


# ------------------------------------------------------------------ free space seen
@pytest.fixture(scope="module")
def rock_in_one_block() -> DepthMemory:
    """Open water but for a rock 1 m from the camera filling one block (row 20, col 30)."""
    depth = np.full((480, 640), np.inf, np.float32)
    depth[200:210, 300:310] = 1.0
    return remembered(seen(depth))


@pytest.mark.parametrize(
    ("row", "col", "free"),
    [
        (20, 30, False),  # behind the rock
        (19, 30, False),  # its neighbours: the map of free space is conservative
        (21, 30, False),
        (20, 29, False),
        (20, 31, False),
        (21, 31, False),
        (18, 30, True),  # two blocks away it is open water
        (22, 30, True),
        (20, 28, True),
        (20, 32, True),
        (40, 10, True),
    ],
)
def test_a_rock_in_one_block_hides_its_neighbours_and_no_farther(
    rock_in_one_block: DepthMemory, row: int, col: int, free: bool
) -> None:
    point = block(row, col, 3.0)
    assert rock_in_one_block.seen_free(point, 0.3).tolist() == [free]


def test_a_near_block_darkens_all_eight_blocks_around_it_and_no_farther() -> None:
    # The free-space map keeps each block's nearest depth among its 3 x 3 neighbours:
    # a rock 1 m away in block (20, 30) shows in rows 19-21 and columns 29-31 alike,
    # above and left of it as well as below and right; the ring around them reads far.
    depth = np.full((480, 640), np.inf, np.float32)
    depth[200:210, 300:310] = 1.0
    (kept,) = remembered(seen(depth)).frames
    rock = 13 * 20.0 / 255  # 1 m in 8-bit levels of 0-20 m: level 13
    expected = np.full((5, 5), 20.0)
    expected[1:4, 1:4] = rock
    assert kept.depth[18:23, 28:33] == pytest.approx(expected, rel=1e-6)


def test_a_depth_image_just_remembered_is_read_along_the_current_heading() -> None:
    # The right half of the view (pixels 320 on) is a wall 1 m away, the left half open
    # water. 5 m out, the blocks left of the wall's edge are free but for the one beside
    # it (the map is conservative by a block); a heading read 1 degree off would shift
    # them by 9 cm, more than a block.
    depth = np.full((480, 640), np.inf, np.float32)
    depth[:, 320:] = 1.0
    memory = remembered(seen(depth))
    assert memory.frames[-1].yaw_deg == 0.0
    points = np.concatenate([block(24, col, 5.0) for col in (28, 29, 30, 31, 32, 33)])
    assert memory.seen_free(points, 0.3).tolist() == [True, True, True, False, False, False]


def test_a_point_is_seen_free_only_a_margin_before_the_surface() -> None:
    wall = frame(np.full((48, 64), 3.0))
    points = np.array([[2.5, 0.0, 0.0], [2.8, 0.0, 0.0], [1.0, 0.0, 0.0]])
    assert wall.sees_free(points, 0.5).tolist() == [True, False, True]  # 3.0 m: just so
    assert wall.sees_free(points, 0.6).tolist() == [False, False, True]
    assert wall.sees_free(points, 0.3).tolist() == [True, False, True]
    # The answer is a mask: it picks the points seen free.
    assert points[wall.sees_free(points, 0.3)].tolist() == [[2.5, 0.0, 0.0], [1.0, 0.0, 0.0]]


@pytest.fixture(scope="module")
def hole_in_a_rock_face() -> SeenFrame:
    """A rock face 0.3 m before the camera with a hole below right of the view's centre
    (rows 30-37, columns 40-47 of 10 px blocks: pixels 300-379 down, 400-479 across)."""
    depth = np.full((48, 64), 0.3)
    depth[30:38, 40:48] = 20.0
    return frame(depth, origin=(CAMERA_M, 0.0, 0.0))


@pytest.mark.parametrize("ahead_m", [0.25, 1.0, 3.0, 8.0])
def test_space_seen_through_a_hole_is_free_and_beside_it_not(
    hole_in_a_rock_face: SeenFrame, ahead_m: float
) -> None:
    margin = 0.1
    through = through_pixel(440, 340, ahead_m)  # the hole's centre
    assert hole_in_a_rock_face.sees_free(through, margin).tolist() == [True]
    for col_px, row_px in [(300, 340), (440, 200), (380, 340), (500, 340), (440, 280)]:
        beside = through_pixel(col_px, row_px, ahead_m)
        assert hole_in_a_rock_face.sees_free(beside, margin).tolist() == [False]


def edge_wall(edge: str) -> np.ndarray:
    """(48, 64) open water but for a wall 1 m away in the outermost blocks of one edge."""
    depth = np.full((48, 64), 20.0)
    index = {"top": (0, slice(None)), "bottom": (-1, slice(None))}
    index |= {"left": (slice(None), 0), "right": (slice(None), -1)}
    depth[index[edge]] = 1.0
    return depth


# 2 m ahead the view spans 1 m to either side and 0.75 m above and below; 0.1 m beyond.
OUTSIDE = {
    "top": (2.0, 0.0, 0.85),
    "bottom": (2.0, 0.0, -0.85),
    "left": (2.0, 1.1, 0.0),
    "right": (2.0, -1.1, 0.0),
}


@pytest.mark.parametrize("edge", ["top", "bottom", "left", "right"])
def test_a_point_just_outside_the_view_is_judged_by_the_nearest_edge_block(edge: str) -> None:
    # The wall at the edge of the view, 1 m away, hides what lies just beyond the edge.
    walled = frame(edge_wall(edge))
    point = np.array([OUTSIDE[edge]])
    assert walled.sees_free(point, 0.3).tolist() == [False]
    assert walled.sees_free(np.array([[2.0, 0.0, 0.0]]), 0.3).tolist() == [True]
    # Without the wall the same point counts as seen free.
    assert frame(np.full((48, 64), 20.0)).sees_free(point, 0.3).tolist() == [True]


def test_points_more_than_the_edge_tolerance_outside_the_view_are_never_seen() -> None:
    open_water = frame(np.full((48, 64), 20.0))
    # 2 m ahead the view spans 1 m to either side and 0.75 m above and below.
    beyond = np.array(
        [[2.0, 1.2, 0.0], [2.0, -1.2, 0.0], [2.0, 0.0, 0.95], [2.0, 0.0, -0.95], [-1.0, 0, 0]]
    )
    assert open_water.sees_free(beyond, 0.3).tolist() == [False] * 5
    # "Up to" edge_m outside counts as in view: 0.25 m beyond the edge, exactly.
    at_the_edge = np.array([[2.0, 1.25, 0.0], [2.0, -1.25, 0.0], [2.0, 0.0, 1.0], [2, 0, -1.0]])
    assert open_water.sees_free(at_the_edge, 0.3, edge_m=0.25).tolist() == [True] * 4
    assert open_water.sees_free(at_the_edge, 0.3, edge_m=0.2).tolist() == [False] * 4


def test_a_frame_seen_before_a_turn_is_read_along_its_own_heading() -> None:
    # Seen 40 degrees to the left of the current heading: a wall 3 m away with a hole
    # right of its view's centre, below it.
    depth = np.full((48, 64), 3.0)
    depth[30:38, 40:48] = 20.0
    turned = frame(depth, yaw_deg=40.0)
    a = math.radians(40.0)

    def along(ahead: float, left: float, up: float) -> list:
        """The body-frame point at (ahead, left, up) in that frame's own axes."""
        return [
            ahead * math.cos(a) - left * math.sin(a),
            ahead * math.sin(a) + left * math.cos(a),
            up,
        ]

    points = np.array(
        [
            along(2.5, 0.0, 0.0),  # on its axis, 0.5 m before the wall
            along(2.8, 0.0, 0.0),  # 0.2 m before it
            along(2.5, 0.5, 0.3),  # up and left
            along(5.0, -5.0 * 0.1875, -5.0 * 0.15625),  # through the hole, behind the wall
            along(5.0, 5.0 * 0.1875, 5.0 * 0.15625),  # the opposite side: behind the wall
            [2.5, -1.0, 0.0],  # ahead of the vehicle now, right: outside that view
        ]
    )
    assert turned.sees_free(points, 0.3).tolist() == [True, False, True, True, False, False]


# ------------------------------------------------------------------ memory after a move
def test_remembered_surfaces_shift_opposite_to_a_strafe_and_turn_opposite_to_a_turn() -> None:
    first = replace(frame(np.full((48, 64), 20.0)), points=np.array([[2.0, 1.0, 0.5]], np.float32))
    strafed = first.moved(parse_action("strafe right 1 m"))
    assert strafed.points.tolist() == [[2.0, 2.0, 0.5]]  # now 2 m to the left
    turned = first.moved(parse_action("turn left 90 deg"))
    assert turned.points == pytest.approx(np.array([[1.0, -2.0, 0.5]]), abs=1e-6)
    both = first.moved(Action(forward=1.0, yaw_deg=90.0))
    assert both.points == pytest.approx(np.array([[0.0, -2.0, 0.5]]), abs=1e-6)


def test_space_seen_ahead_before_a_left_turn_is_known_free_on_the_right() -> None:
    # Before turning 90 degrees left the camera looked along what is now the right.
    before, after = seen(np.inf), seen(np.inf, previous_action=parse_action("turn left 90 deg"))
    assert not judged("strafe right 1 m", before, after).intervened
    # The left was behind the vehicle then, and is still unseen.
    assert "never seen free" in judged("strafe left 1 m", before, after).reason
    # Turned right instead, the space ahead before the turn is now on the left.
    after = seen(np.inf, previous_action=parse_action("turn right 90 deg"))
    assert not judged("strafe left 1 m", before, after).intervened
    assert "never seen free" in judged("strafe right 1 m", before, after).reason


# ------------------------------------------------------------------ rule 3's measures
def test_a_move_that_passes_a_rock_midway_is_refused_though_it_starts_and_ends_clear() -> None:
    # A rock 0.55 m ahead of the middle of a 1 m strafe left: 0.74 m from where the move
    # starts and from where it ends, 0.55 m from its path, within the 0.61 m kept.
    rock = around([[0.55, 0.5, 0.0]])
    hazard = move_hazard(
        parse_action("strafe left 1 m"), rock, body=BODY, margins=Margins(), crawlway=False
    )
    assert (hazard.kind, hazard.text) == (
        "surface",
        "the move would pass within 0.61 m of a surface seen",
    )
    # Moved 0.1 m farther out, the same rock lets the path by (what comes next is rule 4).
    farther = around([[0.65, 0.5, 0.0]])
    hazard = move_hazard(
        parse_action("strafe left 1 m"), farther, body=BODY, margins=Margins(), crawlway=False
    )
    assert hazard.kind == "unseen"


def test_a_wall_nearer_than_the_crawlways_reach_refuses_any_move_that_comes_nearer() -> None:
    # A wall 0.25 m to the right, within the turning corners' reach plus 0.1 m (0.39 m).
    wall = around([[x, -0.25, z] for x in np.arange(-1, 1.01, 0.1) for z in (-0.2, 0.0, 0.2)])
    for crawlway in (False, True):
        toward = move_hazard(
            parse_action("strafe right 0.1 m"),
            wall,
            body=BODY,
            margins=Margins(),
            crawlway=crawlway,
        )
        assert (toward.kind, toward.text) == (
            "surface",
            "the move would pass within 0.25 m of a surface seen",
        )


def test_a_move_straight_away_from_a_wall_nearer_than_the_crawlways_reach_is_allowed() -> None:
    # A rock 0.35 m away on the right, within the turning corners' reach plus 0.1 m: a
    # move may come no nearer to it, and 0.1 m to the left, turning or not, goes away from
    # it wherever it lies on that side. The turn rounds the rock's distance in float32,
    # which must not read as coming nearer. The space on the left was seen free.
    looked_left = DepthMemory()
    looked_left.frames = [frame(np.full((48, 64), 20.0), yaw_deg=90.0)]
    refused = []
    for bearing in range(-150, -31, 2):
        a = math.radians(bearing)
        rock = around([[0.35 * math.cos(a), 0.35 * math.sin(a), 0.0]], looked_left)
        for turn in (-10.0, -5.0, 0.0, 5.0, 10.0):
            move = Action(right=-0.1, yaw_deg=turn)
            hazard = move_hazard(move, rock, body=BODY, margins=Margins(), crawlway=False)
            if hazard:
                refused.append((bearing, turn, hazard.text))
    assert refused == []


def test_how_near_a_move_may_pass_a_surface_seen() -> None:
    margins = Margins()
    open_keep = BODY.bounding_radius + 0.3  # 0.612 m
    reach = BODY.turn_radius + 0.1  # 0.386 m
    assert margins.keep_clear_m(BODY, 2.0, crawlway=False) == pytest.approx(open_keep)
    assert margins.keep_clear_m(BODY, 2.0, crawlway=True) == pytest.approx(reach)
    # Exactly at the open margin is not yet nearer than it.
    assert margins.keep_clear_m(BODY, open_keep, crawlway=False) == pytest.approx(open_keep)
    # Nearer: at most 5 cm nearer, down to the crawlway's distance.
    assert margins.keep_clear_m(BODY, 0.5, crawlway=False) == pytest.approx(0.45)
    assert margins.keep_clear_m(BODY, 0.42, crawlway=False) == pytest.approx(reach)
    # Nearer than the crawlway's distance: no nearer at all.
    assert margins.keep_clear_m(BODY, 0.25, crawlway=False) == pytest.approx(0.25, abs=1e-5)
    assert margins.keep_clear_m(BODY, 0.25, crawlway=True) == pytest.approx(0.25, abs=1e-5)


def test_near_the_floor_space_is_seen_free_the_open_margin_before_a_wall_not_the_crawlways():
    # The floor 0.5 m below lets a move come only 5 cm nearer to it (0.45 m kept), but
    # that is no crawlway: space must still lie 0.3 m before a surface to count as seen
    # free. A wall 1.05 m to the right, seen looking right: a 0.5 m strafe toward it puts
    # the body's leading edge 0.8 m out, 0.25 m before the wall.
    looked_right = DepthMemory()
    looked_right.frames = [frame(np.full((48, 64), 1.05), yaw_deg=-90.0)]
    wall = [[x, -1.05, z] for x in np.arange(-1, 1.01, 0.1) for z in (-0.2, 0.0, 0.2)]
    near_floor = around([*wall, [0.0, 0.0, -0.5]], looked_right, d_bottom=0.5)
    assert Margins().keep_clear_m(BODY, near_floor.nearest_m, crawlway=False) == pytest.approx(0.45)
    strafe = parse_action("strafe right 0.5 m")
    hazard = move_hazard(strafe, near_floor, body=BODY, margins=Margins(), crawlway=False)
    assert (hazard.kind, hazard.text) == (
        "unseen",
        "the move would enter space never seen free (0.8 m right of the vehicle)",
    )
    # In a crawlway 0.1 m before the wall is enough.
    assert not move_hazard(strafe, near_floor, body=BODY, margins=Margins(), crawlway=True)


def test_margins_of_zero_and_a_crawlway_margin_as_wide_as_the_open_one_are_accepted() -> None:
    zero = Margins(open_m=0.0, crawlway_m=0.0, closer_m=0.0)
    assert zero.open_keep_m(BODY) == pytest.approx(BODY.bounding_radius)
    same = Margins(open_m=0.2, crawlway_m=0.2)
    assert same.corridor_m(BODY, True) == same.corridor_m(BODY, False)


def test_a_crawlway_margin_above_the_open_one_is_refused_saying_which_is_the_thinner() -> None:
    message = (
        "margins crawlway_m = 0.3 exceeds open_m = 0.2: the crawlway's margin is the thinner one"
    )
    with pytest.raises(ConfigError, match=re.escape(message)):
        Margins(open_m=0.2, crawlway_m=0.3)


def test_rule_1_reports_the_nearest_obstacle_in_the_open_corridor() -> None:
    # A rock 0.8 m before the camera, 0.45 m off the axis: inside the open corridor (the
    # section's 0.21 m plus 0.3 m), outside the crawlway's (plus 0.1 m); and a wall 1.2 m
    # before the camera on the axis, blocking both. Rule 1 reads the open corridor.
    cloud = [[CAMERA_M + 0.8, 0.45, 0.0], [CAMERA_M + 1.2, 0.0, 0.0]]
    judged_move = crawlway_move(
        parse_action("forward 1 m"), around(cloud), body=BODY, margins=Margins(), no_forward_m=1.5
    )
    assert judged_move.crawlway is False
    assert judged_move.ahead_m == pytest.approx(0.8)
    assert Margins().corridor_m(BODY, crawlway=False) == pytest.approx(BODY.section_radius + 0.3)
    assert Margins().corridor_m(BODY, crawlway=True) == pytest.approx(BODY.section_radius + 0.1)


# ------------------------------------------------------------------ surroundings
def test_open_water_with_nothing_in_range_passes_a_move_untouched() -> None:
    # No surface in view and the sounders read their 50 m limit: nothing is remembered.
    empty = seen(np.inf, d_top=50.0, d_bottom=50.0)
    memory = remembered(empty)
    measured = Surroundings.of(empty, memory, BODY, Margins(), 1.5)
    assert measured.nearest_m == math.inf and not measured.pinched
    verdict = judged("forward 1 m, turn left 15 deg", empty)
    assert not verdict.intervened, verdict.reason


def surfaces_at(*bearings_deg: float | tuple, distance_m: float = 0.5) -> Surroundings:
    """Measured where the only surfaces seen lie ``distance_m`` from the centre at the
    given bearings in the horizontal plane (0 ahead, 90 left), or along given directions
    (forward, left, up)."""
    directions = [
        np.asarray(b)
        if isinstance(b, tuple)
        else (math.cos(math.radians(b)), math.sin(math.radians(b)), 0.0)
        for b in bearings_deg
    ]
    points = [distance_m * np.asarray(d) / np.linalg.norm(d) for d in directions]
    memory = DepthMemory()
    memory.frames = [replace(frame(np.full((48, 64), 20.0)), points=np.array(points, np.float32))]
    return Surroundings.of(seen(np.inf), memory, BODY, Margins(), 1.5)


@pytest.mark.parametrize(
    ("bearings", "distance_m", "pinched"),
    [
        ((90.0, -90.0), 0.5, True),  # a wall on either side
        ((-90.0, 35.0), 0.5, True),  # 125 degrees apart
        ((-90.0, 35.0), 0.3, True),
        ((-90.0, 45.0), 0.55, True),
        ((-90.0, 10.0), 0.5, False),  # 100 degrees apart: a corner, not a pinch
        ((-90.0, 0.0), 0.3, False),  # 90 degrees: a wall beside and one ahead
        ((-90.0, -80.0, -100.0), 0.5, False),  # one wall
        ((90.0, -90.0), 0.7, False),  # both beyond the open margin
        # A rock above, ahead and left, and a wall right, a little ahead and above: 101 deg.
        (((1.0, 1.0, 1.0), (0.327, -0.923, 0.203)), 0.5, False),
    ],
)
def test_a_passage_is_pinched_by_surfaces_near_on_opposite_sides(
    bearings: tuple, distance_m: float, pinched: bool
) -> None:
    # Opposite: more than 120 degrees apart seen from the centre (within about 10 degrees).
    assert surfaces_at(*bearings, distance_m=distance_m).pinched is pinched
