"""The shield's rules, one behaviour at a time: the replacement it chooses, the reason it
records, and the shift away it adds inside the standoff, on synthetic views (flat depth,
sounders set by hand) and on small caves rendered by the real sensors."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from cavenav.core.types import Action, Observation, VehicleBody
from cavenav.motion.actions import format_action, parse_action
from cavenav.safety.shield import (
    DepthMemory,
    Margins,
    MoveMargins,
    Shield,
    ShieldConfig,
    Surroundings,
    Verdict,
    crawlway_move,
    move_hazard,
)
from tests.conftest import synthetic_observation as seen
from tests.safety.test_shield import WIDE, beside, cave, flown_in
from tests.safety.test_shield_memory import around

OPEN_KEEP = Margins().open_keep_m(VehicleBody())  # 0.612 m: half-diagonal plus 0.3 m


def judged(
    action: str | Action, *observations: Observation, config: ShieldConfig | None = None
) -> Verdict:
    shield = Shield(config)
    for obs in observations:
        shield.observe(obs)
    return shield.judge(parse_action(action) if isinstance(action, str) else action)


def flown_in_open(views: int = 3, **sounders: float) -> list[Observation]:
    """Synthetic views of open water, 1 m a step forward, the sounders as given."""
    step = Action(forward=1.0)
    first = seen(np.inf, **sounders)
    return [first, *(seen(np.inf, previous_action=step, **sounders) for _ in range(views - 1))]


# ------------------------------------------------------------------ the shield's life
def test_judging_before_any_observation_is_refused_with_what_to_do() -> None:
    message = "Shield.judge needs an observation first: call observe()"
    with pytest.raises(RuntimeError, match=r"^Shield\.judge needs an observation first: call"):
        Shield().judge(Action(forward=1.0))
    shield = Shield()
    shield.observe(seen(np.inf))
    shield.observe(seen(np.inf))  # nothing judged yet: the memory is not moved
    shield.judge(Action(forward=1.0))
    shield.reset()  # a new episode: what was seen before is gone
    with pytest.raises(RuntimeError) as refused:
        shield.judge(Action(forward=1.0))
    assert str(refused.value) == message


def test_a_hold_is_always_safe_and_passes_without_a_reason() -> None:
    verdict = judged(Action(), seen(0.3, d_top=0.4, d_bottom=0.4))
    assert verdict == Verdict(Action(), Action(), "")
    assert not verdict.intervened


def test_views_that_do_not_say_what_was_executed_move_by_what_the_shield_chose() -> None:
    # Without previous_action in the observations, the memory moves by the actions the
    # shield itself let through: the space beside the vehicle was seen from behind.
    shield = Shield()
    for _ in range(2):
        shield.observe(seen(np.inf))
        assert not shield.judge(Action(forward=1.0)).intervened
    shield.observe(seen(np.inf))
    verdict = shield.judge(parse_action("strafe right 0.5 m"))
    assert not verdict.intervened, verdict.reason
    # After a reset the next views start a new memory: nothing carried over is moved.
    shield.reset()
    shield.observe(seen(np.inf))
    shield.observe(seen(np.inf))
    assert shield.judge(parse_action("strafe right 0.5 m")).action == Action()


# ------------------------------------------------------------------ hold and its reason
def test_when_nothing_near_the_proposal_is_safe_the_shield_holds_and_says_so() -> None:
    # The ceiling exactly 2 m above is at the standoff, not inside it: no shift is offered,
    # and nothing to the right was ever in view.
    proposed = parse_action("strafe right 1 m")
    verdict = judged(proposed, seen(np.inf, d_top=2.0))
    assert verdict == Verdict(
        proposed,
        Action(),
        "the move would enter space never seen free (0.4 m right of the vehicle); "
        "nothing else is safe: hold",
    )
    assert verdict.to_dict()["proposed"] == "strafe right 1 m"


def test_the_standoff_starts_inside_2_m_a_ceiling_exactly_2_m_above_does_not_slow() -> None:
    assert not judged("forward 1 m", seen(np.inf, d_top=2.0)).intervened
    verdict = judged("forward 1 m", seen(np.inf, d_top=1.99))
    assert (
        verdict.reason == "nearest surface 2.0 m is inside the 2 m standoff: forward at most 0.2 m"
    )


# ------------------------------------------------------------------ where the unseen lies
@pytest.mark.parametrize(
    ("move", "where"),
    [
        ("strafe right 1 m", "0.4 m right of the vehicle"),
        ("strafe left 1 m", "0.4 m left of the vehicle"),
        ("back 1 m", "0.4 m behind the vehicle"),
        ("forward 0.5 m, ascend 1 m", "0.2 m ahead, 0.4 m above the vehicle"),
        ("forward 0.5 m, descend 0.5 m", "0.3 m ahead, 0.3 m below the vehicle"),
        ("back 0.5 m, ascend 0.5 m", "0.3 m behind, 0.3 m above the vehicle"),
        ("back 0.2 m, strafe left 0.5 m", "0.1 m behind, 0.4 m left of the vehicle"),
        ("forward 0.2 m, strafe right 0.5 m", "0.1 m ahead, 0.4 m right of the vehicle"),
    ],
)
def test_the_reason_names_where_the_first_unseen_point_of_the_move_lies(
    move: str, where: str
) -> None:
    # One view of open water: only the camera's cone ahead and the sounders' column are
    # known; the first point of the move beyond the body that is in neither is named.
    verdict = judged(move, seen(np.inf))
    assert verdict.reason.startswith(f"the move would enter space never seen free ({where})"), (
        verdict.reason
    )


# ------------------------------------------------------------------ rule 3: the sounders
def test_a_climb_that_ends_exactly_at_the_open_margin_below_the_ceiling_is_allowed() -> None:
    # The ceiling 0.3 m farther than the 0.61 m kept: 0.3 m up ends just at the margin.
    ceiling = OPEN_KEEP + 0.3
    assert not judged("ascend 0.3 m", seen(np.inf, d_top=ceiling)).intervened
    assert judged("ascend 0.31 m", seen(np.inf, d_top=ceiling)).intervened
    floor = OPEN_KEEP + 0.3
    assert not judged("descend 0.3 m", seen(np.inf, d_bottom=floor)).intervened


def test_a_slanted_climb_keeps_clear_of_the_ceiling_the_sounder_reads() -> None:
    # The mirror of the floor: backing up while climbing passes far from the point the
    # sounder read, but would end 0.29 m below the level plane it stands for.
    views = [*flown_in_open(4)[:3], seen(np.inf, d_top=0.93, previous_action=Action(forward=1.0))]
    verdict = judged("back 1 m, ascend 0.64 m", *views)
    assert verdict.reason == "the move would end within 0.61 m of the ceiling (0.93 m away)"
    assert verdict.action == Action(forward=pytest.approx(-1.0), up=pytest.approx(0.1))
    memory = DepthMemory()
    for obs in views:
        memory.update(obs, obs.previous_action)
    around = Surroundings.of(views[-1], memory, VehicleBody(), Margins(), 1.5)
    hazard = move_hazard(
        parse_action("back 1 m, ascend 0.64 m"),
        around,
        body=VehicleBody(),
        margins=Margins(),
        crawlway=False,
    )
    assert hazard.kind == "sounded" and hazard.text == verdict.reason


# ------------------------------------------------------------------ the replacement chosen
def test_a_refused_climb_keeps_half_of_it_rounded_to_the_centimetre() -> None:
    # Under a ceiling 1 m above, 0.6 m up would end 0.4 m from it; half of it, 0.3 m,
    # ends 0.7 m away. The standoff's shift (down) is farther from what was asked.
    views = seen(np.inf, d_top=1.0)
    assert judged("ascend 0.6 m", views).action == Action(up=pytest.approx(0.3))
    assert judged(Action(up=0.65), views).action == Action(up=pytest.approx(0.33))


def test_a_refused_climb_of_0_2_m_keeps_the_smallest_climb() -> None:
    # Under a ceiling 0.75 m above 0.2 m up ends 0.55 m from it; 0.1 m keeps 0.65 m.
    verdict = judged("ascend 0.2 m", seen(np.inf, d_top=0.75))
    assert verdict.action == Action(up=pytest.approx(0.1))


def test_forward_toward_a_wall_within_1_5_m_keeps_the_climb_that_came_with_it() -> None:
    verdict = judged("forward 1 m, ascend 0.2 m", seen(1.3))
    assert verdict.action == Action(up=pytest.approx(0.2))


def test_a_smaller_turn_is_nearer_than_dropping_the_forward_motion() -> None:
    # A thin pillar 1.6 m away, 22 degrees right: turning 10 degrees right puts it in the
    # corridor ahead, 5 degrees does not. 5 degrees of turn (1/9 of 45) is nearer to the
    # proposal than dropping 0.2 m of forward motion.
    views = flown_in(cave(WIDE, ((0.1, 0.1, 6.0), (-0.6, -1.47, 0.0))))
    verdict = judged("forward 0.2 m, turn right 10 deg", *views)
    assert verdict.reason.startswith("obstacle 1.3 m ahead, within 1.5 m"), verdict.reason
    assert verdict.action == Action(forward=pytest.approx(0.2), yaw_deg=-5.0)
    # Turning the other way the pillar is nowhere near the corridor.
    assert not judged("forward 0.2 m, turn left 10 deg", *views).intervened


def test_45_degrees_of_turn_weigh_as_1_m_of_translation_in_choosing_the_nearest() -> None:
    # Halving a 1.98 m climb drops 0.99 m, nearer than dropping the whole 45-degree turn.
    far = SimpleNamespace(nearest_m=math.inf, away=Action())  # outside the standoff
    nearest = Shield()._candidates(Action(up=1.98, yaw_deg=45.0), far)
    assert [format_action(a) for a in nearest[:7]] == [
        "ascend 1.98 m, turn left 30 deg",  # 15 degrees: 0.33 m
        "ascend 1.98 m, turn left 20 deg",
        "ascend 1.98 m, turn left 15 deg",
        "ascend 1.98 m, turn left 10 deg",
        "ascend 1.98 m, turn left 5 deg",  # 40 degrees: 0.89 m
        "ascend 0.99 m, turn left 45 deg",  # 0.99 m
        "ascend 1.98 m",  # 45 degrees: 1 m
    ]


# ------------------------------------------------------------------ the shift away
@pytest.fixture(scope="module")
def left_wall_0_5() -> list[Observation]:
    """A wall 0.5 m to the left (+x heading -y), the right one 3 m away."""
    extents, (x, y, z) = beside(0.5)
    return flown_in(cave((extents, (-x, y, z))))


@pytest.fixture(scope="module")
def right_wall_0_5() -> list[Observation]:
    return flown_in(cave(beside(0.5)))


def test_the_standoffs_shift_is_away_from_the_nearest_wall_on_either_side(
    left_wall_0_5, right_wall_0_5
) -> None:
    verdict = judged("strafe left 0.1 m", *left_wall_0_5)
    assert verdict.action == Action(right=pytest.approx(0.1))
    assert verdict.reason.endswith("m of a surface seen")
    verdict = judged("strafe right 0.1 m", *right_wall_0_5)
    assert verdict.action == Action(right=pytest.approx(-0.1))


@pytest.mark.parametrize(
    ("sounders", "away"),
    [
        ({"d_top": 3.0, "d_bottom": 0.9}, "forward 0.2 m, ascend 0.1 m"),
        ({"d_top": 0.9, "d_bottom": 3.0}, "forward 0.2 m, descend 0.1 m"),
        ({"d_top": 0.9, "d_bottom": 0.9}, "forward 0.2 m, ascend 0.1 m"),  # a tie: up
    ],
)
def test_inside_the_standoff_near_the_floor_or_ceiling_the_shift_is_away_from_it(
    sounders: dict, away: str
) -> None:
    verdict = judged("forward 0.2 m", seen(np.inf, **sounders))
    assert verdict.reason == "inside the standoff, forward motion must come with a turn or a shift"
    assert verdict.action == parse_action(away)


# ------------------------------------------------------------------ crawlway or not
def test_a_floor_near_below_is_no_crawlway_for_a_forward_move_either() -> None:
    # Nothing ahead blocks the open corridor: the floor 0.5 m below may come 5 cm nearer,
    # not the 11 cm the crawlway's 0.39 m would allow.
    verdict = judged("forward 0.2 m, descend 0.1 m", seen(np.inf, d_bottom=0.5))
    assert verdict.reason == "the move would pass within 0.45 m of a surface seen"


def test_a_pinch_ahead_makes_a_crawlway_only_for_a_move_forward() -> None:
    # A wall 1.2 m ahead with a hole 0.9 m across, the floor 0.5 m below: descending
    # 0.1 m goes nowhere near the pinch, so the floor may come only 5 cm nearer.
    rows, cols = np.mgrid[0:480, 0:640]
    hole = np.hypot(rows - 239.5, cols - 319.5) < 0.45 / 1.2 * 640
    verdict = judged("descend 0.1 m", seen(np.where(hole, np.inf, 1.2), d_bottom=0.5))
    assert verdict.reason == "the move would pass within 0.45 m of a surface seen"


@pytest.mark.parametrize("rim_m", [0.33, 0.4, 0.5])
def test_a_pinch_ahead_that_only_the_crawlways_corridor_passes_is_a_crawlway_to_its_rim(
    rim_m: float,
) -> None:
    # Rocks 1 m before the camera, rim_m left and right of the axis: inside the open
    # corridor (0.51 m), outside the crawlway's (0.31 m), down to a third of a metre
    # from the axis. Only the crawlway's corridor passes, and nothing blocks it.
    rocks = around([[1.2, rim_m, 0.0], [1.2, -rim_m, 0.0]])
    judged_move = crawlway_move(
        Action(forward=0.5), rocks, body=VehicleBody(), margins=Margins(), no_forward_m=1.5
    )
    assert judged_move == MoveMargins(crawlway=True, ahead_m=math.inf)
    # The rock on one side alone is a wall to keep clear of, not a pinch.
    one_side = around([[1.2, -rim_m, 0.0]])
    judged_move = crawlway_move(
        Action(forward=0.5), one_side, body=VehicleBody(), margins=Margins(), no_forward_m=1.5
    )
    assert judged_move == MoveMargins(crawlway=False, ahead_m=math.inf)


@pytest.fixture(scope="module")
def crawlway() -> list[Observation]:
    """1.15 m square: walls, ceiling and floor 0.575 m away, pinched on every side."""
    return flown_in(cave(((1.15, 20.0, 1.15), (0.0, 0.0, 0.0))))


@pytest.mark.parametrize("move", ["ascend 0.1 m", "descend 0.1 m"])
def test_in_a_crawlway_the_sounders_column_is_known_to_0_1_m_short_of_the_surface(
    crawlway, move: str
) -> None:
    # 0.1 m up puts the body's leading edge 0.41 m above the centre, 0.165 m short of the
    # ceiling: free space by the crawlway's 0.1 m, not by the open 0.3 m.
    assert not judged(move, *crawlway).intervened


# ------------------------------------------------------------------ no room to turn
def test_a_ceiling_near_above_leaves_room_to_turn() -> None:
    # Only surfaces at the body's height (its half height plus 5 cm) limit a turn.
    assert not judged("turn left 15 deg", seen(np.inf, d_top=0.5, d_bottom=0.5)).intervened


def test_a_ledge_just_above_the_bodys_top_beside_it_leaves_no_room_to_turn() -> None:
    # A ledge to the right whose underside is 0.15 m above the centre, within 5 cm of
    # the body's top (0.125 m), reaching to 0.25 m from the centre.
    ledge = ((2.75, 20.0, 2.85), (-1.625, 0.0, 0.15 + 1.425))
    verdict = judged("turn left 15 deg", *flown_in(cave(WIDE, ledge)))
    assert verdict.reason == "a surface 0.25 m beside the centre leaves no room to turn"


# ------------------------------------------------------------------ the shield's settings
def test_the_points_checked_along_a_move_are_spaced_by_the_configured_sample() -> None:
    # Spaced 1 m, no point of a 0.5 m move lies beyond the body: nothing is checked.
    coarse = ShieldConfig(sample_m=1.0)
    assert not judged("strafe right 0.5 m", seen(np.inf), config=coarse).intervened
    assert judged("strafe right 0.5 m", seen(np.inf)).intervened


def test_the_first_unseen_point_is_named_not_the_first_point_of_the_move() -> None:
    # Seen from 1 m back, the space right of the vehicle is known out to 0.7 m: a 1 m
    # strafe is refused at 0.6 m, and 0.2 m (its leading edge at 0.5 m) is kept.
    verdict = judged("strafe right 1 m", *flown_in_open(2))
    assert verdict.reason == (
        "the move would enter space never seen free (0.6 m right of the vehicle)"
    )
    assert verdict.action == Action(right=pytest.approx(0.2))


@pytest.mark.parametrize(("sounder", "move"), [("d_bottom", "descend"), ("d_top", "ascend")])
def test_in_a_crawlway_the_sounders_column_is_free_to_0_1_m_short_of_the_reading(
    sounder: str, move: str
) -> None:
    # Ceiling and floor both within 0.61 m: a crawlway. 0.1 m toward the one read
    # brings the body's leading edge 0.4 m from the centre: free when the reading is
    # 0.5 m (0.1 m short of it), never seen when it is 0.49 m (nor in the camera's view).
    other = {"d_top": 0.55, "d_bottom": 0.55}
    assert not judged(f"{move} 0.1 m", seen(np.inf, **{**other, sounder: 0.5})).intervened
    verdict = judged(f"{move} 0.1 m", seen(np.inf, **{**other, sounder: 0.49}))
    where = "below" if move == "descend" else "above"
    assert verdict.reason == (
        f"the move would enter space never seen free (0.4 m {where} the vehicle)"
    )
    assert verdict.action == parse_action(f"{'ascend' if move == 'descend' else 'descend'} 0.1 m")


@pytest.fixture(scope="module")
def slot_ahead() -> list[Observation]:
    """Two rocks whose faces stand 0.45 m left and right of the axis, from 0.5 to 0.9 m
    ahead of the centre: a slot 0.9 m wide that only the crawlway's corridor passes."""
    rock = (2.55, 0.4, 6.0)
    return flown_in(cave(WIDE, (rock, (1.725, -0.7, 0.0)), (rock, (-1.725, -0.7, 0.0))))


@pytest.mark.parametrize(
    "move", ["forward 0.2 m, turn left 5 deg", "forward 0.2 m, strafe left 0.1 m"]
)
def test_a_slot_just_ahead_pinched_from_both_sides_is_flown_as_a_crawlway(
    slot_ahead, move: str
) -> None:
    # The open margin (0.61 m) would stop the vehicle 0.3 m short of the slot's mouth;
    # the crawlway's lets it in. Shrunk to the open margin, the shield holds it back.
    assert not judged(move, *slot_ahead).intervened
    open_only = ShieldConfig(margins=Margins(crawlway_m=0.3))
    assert judged(move, *slot_ahead, config=open_only).action.forward == 0


def test_a_wall_alongside_and_a_rock_behind_on_the_other_side_are_no_pinch_ahead() -> None:
    # A wall 0.5 m to the right; on the left a rock 0.45 m from the axis, but behind the
    # vehicle: nothing pinches the way ahead, so the wall may come only 5 cm nearer.
    passage = ((3.5, 20.0, 6.0), (1.25, 0.0, 0.0))  # right wall at x = -0.5
    rock = ((2.55, 2.5, 6.0), (1.725, 1.75, 0.0))  # left, from 0.5 m to 3 m behind
    verdict = judged("forward 0.2 m, strafe right 0.1 m", *flown_in(cave(passage, rock)))
    assert verdict.reason == "the move would pass within 0.45 m of a surface seen"
    assert verdict.action == Action(forward=pytest.approx(0.2), right=pytest.approx(-0.1))
