"""The closed loop that flies each move on an ArduSub vehicle (`cavenav.vehicle.control`):
the goal of a step, the sticks toward it, and when a vehicle counts as still or stalled."""

from __future__ import annotations

import math

import pytest

from cavenav.vehicle.control import Goal, Measured, Settling, goal_of, manual_sticks, still
from cavenav.vehicle.mavlink import BridgeConfig

SETTINGS = BridgeConfig().control  # the defaults, tuned on ArduSub's SITL


def test_a_step_turns_first_then_translates_in_the_new_heading() -> None:
    facing_north = Measured(10.0, 20.0, 5.0, 0.0)
    goal = goal_of(facing_north, forward=1.0, right=0.0, down=-0.5, turn=math.pi / 2)
    assert (goal.north, goal.east, goal.down) == pytest.approx((10.0, 21.0, 4.5))
    assert goal.yaw == pytest.approx(math.pi / 2)


def test_far_from_the_goal_the_sticks_cruise_along_a_straight_line() -> None:
    """The wanted velocity points at the goal as a whole: forward and up in the goal's
    proportion, each stick beyond its dead band."""
    at_rest = Measured(0.0, 0.0, 5.0, 0.0)
    sticks = manual_sticks(Goal(4.0, 0.0, 4.0, 0.0), at_rest, SETTINGS)
    assert SETTINGS.stick_dead_band < sticks["x"] <= SETTINGS.stick_limit
    assert sticks["y"] == 0 and sticks["r"] == 0
    assert sticks["z"] > 500 + SETTINGS.throttle_dead_band  # up, out of the dead band


def test_a_vehicle_faster_than_wanted_near_its_goal_is_braked() -> None:
    coasting = Measured(0.0, 0.0, 5.0, 0.0, v_north=0.3)
    sticks = manual_sticks(Goal(0.05, 0.0, 5.0, 0.0), coasting, SETTINGS)
    assert sticks["x"] < -SETTINGS.stick_dead_band  # astern, out of the dead band


def test_within_half_the_tolerances_the_sticks_hold() -> None:
    """Neutral yaw (ALT_HOLD holds the heading) and throttle (it holds the depth); no
    horizontal push too small to matter."""
    nearly = Measured(0.0, 0.0, 5.0, math.radians(0.5))
    sticks = manual_sticks(Goal(0.0, 0.0, 5.04, 0.0), nearly, SETTINGS)
    assert sticks == {"x": 0, "y": 0, "z": 500, "r": 0}


def test_a_heading_error_turns_the_short_way() -> None:
    facing_350 = Measured(0.0, 0.0, 5.0, math.radians(-10.0))
    sticks = manual_sticks(Goal(0.0, 0.0, 5.0, math.radians(10.0)), facing_350, SETTINGS)
    assert sticks["r"] == SETTINGS.stick_dead_band + round(SETTINGS.yaw_gain * 20)


@pytest.mark.parametrize(
    ("measured", "is_still"),
    [
        (Measured(0, 0, 5, 0), True),
        (Measured(0, 0, 5, 0, v_north=0.04, v_down=0.15), True),  # a depth hold's waver
        (Measured(0, 0, 5, 0, v_east=0.06), False),
        (Measured(0, 0, 5, 0, v_down=0.25), False),
        (Measured(0, 0, 5, 0, yaw_rate=math.radians(3.0)), False),
    ],
)
def test_still_is_judged_from_the_vehicles_own_rates(measured: Measured, is_still: bool) -> None:
    assert still(measured, SETTINGS) is is_still


def test_a_still_vehicle_short_of_its_goal_has_stalled_but_a_slow_approach_has_not() -> None:
    goal = Goal(1.0, 0.0, 5.0, 0.0)
    stopped = Settling(SETTINGS, 0.5)
    for clock in (0.0, 0.3, 0.6):
        steady, stalled = stopped.update(goal, Measured(0.5, 0.0, 5.0, 0.0), clock)
    assert steady and stalled
    creeping = Settling(SETTINGS, 0.5)
    for clock, north in ((0.0, 0.5), (0.3, 0.55), (0.6, 0.6)):  # 0.04 m/s: still, nearing
        steady, stalled = creeping.update(goal, Measured(north, 0.0, 5.0, 0.0, 0.04), clock)
    assert steady and not stalled
