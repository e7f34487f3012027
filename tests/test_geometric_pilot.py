"""The geometric baseline follows the prompt's strategy from what a VLM would see."""

from __future__ import annotations

import inspect

import numpy as np
import pytest

from cavenav.actions import DEFAULT_SPACE, parse_action
from cavenav.pilots.base import Pilot
from cavenav.pilots.geometric import GeometricPilot, GeometricPilotConfig
from cavenav.sensors.rig import SensorRig
from cavenav.types import Observation, Pose
from cavenav.world.raycast import RayCaster

from .conftest import box_room
from .conftest import synthetic_observation as synthetic


def observe(room_extents, pose: Pose) -> Observation:
    return SensorRig(RayCaster(box_room(extents=room_extents))).observe(pose)


def test_it_is_a_pilot_that_sees_only_observations() -> None:
    pilot = GeometricPilot()
    assert isinstance(pilot, Pilot)
    assert list(inspect.signature(pilot.decide).parameters) == ["observation"]


def test_open_water_ahead_means_full_speed() -> None:
    decision = GeometricPilot().decide(synthetic(np.inf))
    assert decision.action.forward == 1.0
    assert decision.action.yaw_deg == 0.0


def test_answers_in_the_vlm_form() -> None:
    decision = GeometricPilot().decide(observe((8, 40, 8), Pose(0, 15, 0, 0)))
    assert parse_action(decision.action_text) == decision.action
    assert DEFAULT_SPACE.is_valid(decision.action)
    for part in ("Situation:", "Constraints:", "Choice:"):
        assert part in decision.justification


def test_no_forward_motion_within_1_5_m_of_an_obstacle_ahead() -> None:
    decision = GeometricPilot().decide(synthetic(1.2))
    assert decision.action.forward == 0.0
    assert abs(decision.action.yaw_deg) >= 45  # manoeuvre toward a clearer side
    assert "1.5 m" in decision.justification


def test_below_the_standoff_forward_is_slow_and_combined_with_another_motion() -> None:
    # A corridor 3 m wide: the walls are 1.5 m away, inside the 2.0 m standoff.
    decision = GeometricPilot().decide(observe((3, 40, 6), Pose(0, 15, 0, 0)))
    action = decision.action
    assert 0 < action.forward <= 0.2
    assert action.yaw_deg or action.right or action.up


def test_re_centres_between_ceiling_and_floor() -> None:
    decision = GeometricPilot().decide(synthetic(np.inf, d_top=4.0, d_bottom=2.0))
    assert decision.action.up == pytest.approx(1.0)


def test_turns_toward_the_open_side() -> None:
    # Heading 30 degrees to the right of a long corridor's axis: the passage opens left.
    decision = GeometricPilot().decide(observe((6, 60, 6), Pose(0, 20, 0, np.radians(-30))))
    assert decision.action.yaw_deg > 0


def test_never_reverses_by_spinning_past_half_a_circle() -> None:
    pilot = GeometricPilot()
    turned = sum(pilot.decide(synthetic(1.0)).action.yaw_deg for _ in range(8))
    assert abs(turned) <= 180


@pytest.mark.parametrize("setting", [{"stride": 0}, {"stride": -5}, {"columns": 0}])
def test_a_sampling_stride_below_one_is_refused_where_it_is_set(setting: dict) -> None:
    from cavenav.errors import ConfigError
    from cavenav.shield import DepthMemory

    with pytest.raises(ConfigError, match="stride"):
        GeometricPilotConfig(**setting)
    with pytest.raises(ConfigError, match="stride"):
        DepthMemory(**setting)
