"""The environment with the acoustic instruments and the stereo camera: what a learner
gets, and what dead reckoning does with the DVL."""

from __future__ import annotations

import numpy as np

from cavenav.sensors.config import SensorConfig
from cavenav.sensors.sonar import PING360
from cavenav.sim.env import CaveNavEnv
from cavenav.world.scenarios import Scenario


def test_the_observation_carries_the_sonar_and_the_dvl(room_scenario: Scenario) -> None:
    env = CaveNavEnv(room_scenario, sensors=SensorConfig(sonar="ping360", dvl=True))
    observation, info = env.reset(seed=0)
    assert env.observation_space.contains(observation)
    assert observation["sonar"].shape == (400, PING360.samples, 1)
    # At the start the head has swept its whole sector; the DVL has measured no move yet.
    assert info["observation"].sonar.fresh.sum() == 133
    assert observation["dvl"][4] == 0.0
    observation, *_, info = env.step("forward 1")
    seen = info["observation"]
    assert seen.dvl.locked and seen.dvl.velocity_m_s[0] > 0.4
    assert observation["dvl"][4] == 1.0 and np.isfinite(observation["dvl"]).all()
    assert 0 < seen.sonar.fresh.sum() < 133  # two seconds of sweeping


def test_without_the_instruments_the_observation_is_as_before(room_scenario: Scenario) -> None:
    env = CaveNavEnv(room_scenario)
    observation, info = env.reset(seed=0)
    assert set(observation) == {"rgb", "depth", "depth_m", "d_top", "d_bottom"}
    assert info["observation"].sonar is None and info["observation"].dvl is None
    assert info["observation"].depth_source == "exact"
