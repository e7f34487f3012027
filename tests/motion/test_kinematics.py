"""The pose update of SPEC section 5 and its sign conventions."""

from __future__ import annotations

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from cavenav.core.types import Action, Pose
from cavenav.motion.actions import parse_action
from cavenav.motion.kinematics import Drift, Kinematic, apply


def test_heading_zero_moves_forward_along_minus_y() -> None:
    pose = apply(Pose(0, 0, 0, 0), Action(forward=1.0))
    assert (pose.x, pose.y, pose.z) == pytest.approx((0.0, -1.0, 0.0))


def test_turn_right_then_forward_moves_the_vehicle_to_its_right() -> None:
    start = Pose(0, 0, 0, 0)
    right_of_start = start.position + start.right  # one metre to the vehicle's right
    turned = apply(start, parse_action("turn right 90 deg"))
    moved = apply(turned, parse_action("forward 1.0 m"))
    assert moved.position == pytest.approx(right_of_start)


def test_turn_left_is_counter_clockwise_seen_from_above() -> None:
    pose = apply(Pose(0, 0, 0, 0), parse_action("turn left 90 deg"))
    assert pose.psi == pytest.approx(math.pi / 2)
    # heading -y turned counter-clockwise by 90 degrees heads +x
    assert pose.forward == pytest.approx([1.0, 0.0, 0.0])


def test_strafe_right_moves_to_the_right_without_turning() -> None:
    start = Pose(2, 3, 1, math.radians(30))
    pose = apply(start, parse_action("strafe right 0.5 m"))
    assert pose.position == pytest.approx(start.position + 0.5 * start.right)
    assert pose.psi == pytest.approx(start.psi)


def test_equations_are_exactly_those_of_the_spec() -> None:
    x, y, z, psi = 1.0, -2.0, 0.5, 0.3
    df, dr, dz, dpsi = 0.5, 0.2, -0.3, math.radians(15)
    pose = apply(Pose(x, y, z, psi), Action(df, dr, dz, 15.0))
    p2 = psi + dpsi
    assert pose.x == pytest.approx(x + df * math.sin(p2) - dr * math.cos(p2))
    assert pose.y == pytest.approx(y - df * math.cos(p2) - dr * math.sin(p2))
    assert pose.z == pytest.approx(z + dz)
    assert pose.psi == pytest.approx(p2)


@given(st.floats(-10, 10), st.floats(-10, 10), st.floats(-math.pi, math.pi), st.floats(0, 2))
def test_a_move_has_the_length_of_its_horizontal_command(
    x: float, y: float, psi: float, df: float
) -> None:
    pose = apply(Pose(x, y, 0, psi), Action(forward=df, right=0.5))
    assert math.hypot(pose.x - x, pose.y - y) == pytest.approx(math.hypot(df, 0.5))


def test_the_kinematics_reach_the_pose_commanded_so_they_report_no_drift() -> None:
    start, action = Pose(1.0, 2.0, -0.5, 0.4), parse_action("forward 1 m, turn left 30 deg")
    motion = Kinematic()
    assert motion.start(start) == start
    reached = motion.move(start, action)
    assert reached == apply(start, action) and motion.drift(start, action, reached) is None


def test_drift_is_how_far_and_how_much_turned_a_move_ended_from_the_command() -> None:
    start, action = Pose(0, 0, 0, 0), Action(forward=1.0)  # commanded: (0, -1, 0) heading -y
    reached = Pose(0.3, -1.0, 0.4, math.radians(-10))
    drift = Drift.of(start, action, reached)
    assert drift.commanded == apply(start, action)
    assert drift.metres == pytest.approx(0.5) and drift.degrees == pytest.approx(10.0)
    assert drift.to_info() == {
        "commanded_pose": drift.commanded.to_dict(),
        "drift_m": drift.metres,
        "drift_deg": drift.degrees,
    }
