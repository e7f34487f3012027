"""Dead reckoning and back-projection: one account of where what was seen lies, shared by
the shield's memory, the cave map and the geometric pilot."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from cavenav.core.errors import ConfigError
from cavenav.core.types import Action, DvlReading
from cavenav.safety.reckoning import (
    COMMANDED_DRIFT,
    DepthSamples,
    ReckonedPose,
    executed_since,
    move_points,
    reckon,
    sampling_stride,
    to_body,
    to_map,
    translation,
)
from tests.conftest import synthetic_observation as synthetic

actions = st.builds(
    Action,
    forward=st.sampled_from([0.0, 0.1, 0.5, 1.0]),
    right=st.sampled_from([-0.5, 0.0, 0.2]),
    up=st.sampled_from([-1.0, 0.0, 0.3]),
    yaw_deg=st.sampled_from([-90.0, -15.0, 0.0, 5.0, 45.0, 180.0]),
)


@given(actions, st.floats(-3.0, 3.0), st.floats(-math.pi, math.pi))
def test_the_memory_and_the_map_move_what_was_seen_alike(
    action: Action, x: float, heading: float
) -> None:
    # A point fixed in the cave, seen from the body before and after the action: the
    # memory moves it by move_points, the map moves the vehicle by reckon.
    position = np.array([x, 1.0, -0.5])
    seen = np.array([[4.0, -1.0, 0.5], [0.0, 2.0, -1.0]])
    fixed = to_map(seen, position, heading)
    after, turned = reckon(position, heading, action)
    expected = to_body(fixed, after, turned)
    assert move_points(seen.astype(np.float32), action) == pytest.approx(expected, abs=1e-5)


def test_turn_right_then_forward_moves_the_vehicle_to_its_right_in_the_map() -> None:
    position, heading = reckon(np.zeros(3), 0.0, Action(forward=1.0, yaw_deg=-90.0))
    assert position == pytest.approx([0.0, -1.0, 0.0], abs=1e-12)  # y is left: -1 is right
    assert math.degrees(heading) == pytest.approx(-90.0)
    assert translation(Action(forward=1.0, yaw_deg=-90.0)) == pytest.approx([0.0, -1.0, 0.0])


def test_the_action_executed_is_the_one_reported_else_the_last_one_chosen() -> None:
    chosen, executed = Action(forward=1.0), Action(yaw_deg=45.0)
    assert executed_since(synthetic(5.0, previous_action=executed), chosen) == executed
    assert executed_since(synthetic(5.0), chosen) == chosen
    assert executed_since(synthetic(5.0), None) is None


def test_a_wall_back_projects_to_its_plane_ahead_of_the_camera() -> None:
    # A wall 4 m ahead, the camera 0.2 m ahead of the centre: every pixel's point lies on
    # the plane 4.2 m ahead in the body frame, spread across the 53-degree view.
    seen = DepthSamples.of(synthetic(4.0), stride=10)
    assert seen.depth.shape == (48, 64) and seen.surface.all()
    points = seen.points(ahead_m=0.2).reshape(-1, 3)
    assert points[:, 0] == pytest.approx(4.2, abs=0.05)  # 8-bit depth: 8 cm a level
    half_width = float(np.abs(points[:, 1]).max())
    assert half_width == pytest.approx(4.0 * math.tan(math.radians(53.13 / 2)), rel=0.03)


def test_points_lie_in_the_camera_frame_unless_an_offset_is_given() -> None:
    # A wall 4 m away (8-bit level 51 of 0-20 m: exactly 4 m).
    seen = DepthSamples.of(synthetic(4.0), stride=10)
    camera = seen.points()
    assert np.unique(camera[..., 0]).tolist() == [4.0]
    assert np.unique(seen.points(ahead_m=0.25)[..., 0]).tolist() == [4.25]


def test_points_are_placed_at_the_depth_given_along_each_pixels_ray() -> None:
    # The cave map places each pixel's point at its reach (the depth, clipped): 2 m
    # along the same rays is half as far to the side as the wall 4 m away.
    seen = DepthSamples.of(synthetic(4.0), stride=10)
    at_two = seen.points(np.full(seen.depth.shape, 2.0, np.float32))
    assert np.unique(at_two[..., 0]).tolist() == [2.0]
    assert (at_two[..., 1:] * 2 == seen.points()[..., 1:]).all()


def test_nothing_in_range_is_no_surface() -> None:
    assert not DepthSamples.of(synthetic(np.inf), stride=8).surface.any()


def test_the_stride_follows_the_width_unless_given() -> None:
    assert sampling_stride(640, None, 128) == 5
    assert sampling_stride(84, None, 128) == 1
    assert sampling_stride(640, 3, 128) == 3
    with pytest.raises(ConfigError, match="stride"):
        sampling_stride(640, 0, 128)


def dvl_reading(velocity: tuple[float, float, float], seconds: float = 2.0, locked: bool = True):
    return DvlReading(
        velocity_m_s=np.array(velocity if locked else (np.nan,) * 3),
        locked=locked,
        altitude_m=2.0 if locked else np.nan,
        beam_ranges_m=np.full(4, 2.2),
        seconds=seconds,
        sigma_m_s=0.003,
    )


def test_with_bottom_lock_the_move_is_what_the_dvl_measured() -> None:
    commanded = Action(forward=1.0, yaw_deg=10.0)
    # The current set the vehicle 0.3 m to its left: the DVL says so, the command cannot.
    seen = synthetic(5.0, previous_action=commanded, dvl=dvl_reading((0.5, 0.15, 0.0)))
    moved = executed_since(seen, None)
    assert moved == Action(forward=1.0, right=-0.3, up=0.0, yaw_deg=10.0)
    lost = synthetic(5.0, previous_action=commanded, dvl=dvl_reading((0, 0, 0), locked=False))
    assert executed_since(lost, None) == commanded


def test_dead_reckoning_drifts_less_with_the_dvl() -> None:
    start = ReckonedPose.launched(0.0, 0.0, 0.0, 0.0)  # heading -y
    with_dvl = synthetic(5.0, previous_action=Action(forward=1.0), dvl=dvl_reading((0.5, 0, 0)))
    without = synthetic(5.0, previous_action=Action(forward=1.0))
    reckoned = start.after(with_dvl, None)
    assert reckoned.position == pytest.approx([0.0, -1.0, 0.0])
    assert reckoned.dvl_moves == 1 and reckoned.moves == 1
    blind = start.after(without, None)
    assert blind.position == pytest.approx([0.0, -1.0, 0.0])
    assert reckoned.sigma_m < blind.sigma_m == pytest.approx(COMMANDED_DRIFT)
    # A calibration's error grows with the distance, not its square root.
    assert blind.after(without, None).sigma_m == pytest.approx(2 * COMMANDED_DRIFT)
    assert start.after(synthetic(5.0), None) is start  # no move known: no move reckoned
