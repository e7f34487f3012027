"""The Gymnasium environment: the contract every driver relies on."""

from __future__ import annotations

from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import cavenav  # noqa: F401 - registers cavenav/CaveNav-v0
from cavenav.env import CaveNavEnv, snap_action
from cavenav.errors import ActionError, ConfigError
from cavenav.types import Action
from cavenav.world.scenarios import Scenario

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def test_check_env_passes_for_s1() -> None:
    check_env(gym.make("cavenav/CaveNav-v0", scenario="S1", render_mode="rgb_array").unwrapped)


def test_check_env_passes_for_a_scenario_file_and_for_action_vectors() -> None:
    check_env(CaveNavEnv(EXAMPLES / "osrf_cave_straight.toml", action_format="vector"))


def test_gymnasium_make_needs_nothing_but_import_cavenav() -> None:
    env = gym.make("cavenav/CaveNav-v0", scenario="S4")
    assert env.spec is not None and env.spec.max_episode_steps == 150
    obs, info = env.reset(seed=0)
    assert obs["rgb"].shape == (480, 640, 3) and obs["depth"].dtype == np.uint8
    assert obs["depth_m"].max() <= 20.0 and obs["d_top"].shape == ()
    assert info["scenario"] == "S4" and info["collision"] is False


def test_a_vector_of_two_environments_steps() -> None:
    envs = gym.vector.SyncVectorEnv([lambda: CaveNavEnv("S1") for _ in range(2)])
    obs, _ = envs.reset(seed=[1, 2])
    assert obs["rgb"].shape == (2, 480, 640, 3)
    obs, reward, terminated, truncated, info = envs.step(("forward 1 m", "turn left 15 deg"))
    assert reward[0] == pytest.approx(1.0, abs=0.05) and reward[1] == pytest.approx(0.0, abs=1e-6)
    assert not terminated.any() and not truncated.any()
    envs.close()


def test_the_same_seed_and_actions_give_the_same_observations_bit_for_bit() -> None:
    actions = ["forward 1 m, turn left 10 deg", "ascend 0.3 m, strafe right 0.2 m", "forward 0.5 m"]

    def fly(seed: int) -> list[dict[str, np.ndarray]]:
        env = CaveNavEnv("S1")
        frames = [env.reset(seed=seed)[0]]
        frames += [env.step(a)[0] for a in actions]
        return frames

    first, again, other = fly(7), fly(7), fly(8)
    for a, b, c in zip(first, again, other, strict=True):
        for key in a:
            assert np.array_equal(a[key], b[key]), key
        assert np.array_equal(a["depth_m"], c["depth_m"])  # same cave, same poses
        assert not np.array_equal(a["rgb"], c["rgb"])  # another draw of sensor noise


def test_an_inadmissible_action_holds_says_why_and_counts_toward_the_budget() -> None:
    env = gym.make("cavenav/CaveNav-v0", max_episode_steps=2)
    _, start = env.reset(seed=0)
    _, reward, terminated, truncated, info = env.step("forward 0.3 m")
    assert "forward 0.3 m is not admissible" in info["invalid_action"]
    assert info["pose"] == start["pose"] and info["action"] == "hold" and reward == 0.0
    _, _, terminated, truncated, info = env.step("fly to the moon")
    assert info["invalid_action"] and truncated and not terminated


def test_a_collision_terminates_with_a_penalty_and_leaves_the_vehicle_where_it_was(
    room_scenario: Scenario,
) -> None:
    env = CaveNavEnv(room_scenario, collision_penalty=10.0)
    _, start = env.reset(seed=0)
    _, reward, terminated, truncated, info = env.step("strafe right 1 m")
    _, reward, terminated, truncated, info = env.step("strafe right 1 m")  # wall at 2 m
    assert info["collision"] and terminated and not truncated and not info["exit"]
    assert reward == pytest.approx(-10.0)
    assert info["pose"]["x"] == pytest.approx(start["pose"]["x"] - 1.0)
    assert info["collision_pose"]["x"] == pytest.approx(start["pose"]["x"] - 2.0)
    with pytest.raises(gym.error.ResetNeeded):
        env.step("hold")


def test_reaching_the_exit_terminates_and_the_rewards_add_up_to_the_progress(
    room_scenario: Scenario,
) -> None:
    env = CaveNavEnv(room_scenario)
    env.reset(seed=0)
    total, terminated, info = 0.0, False, {}
    while not terminated:
        _, reward, terminated, _, info = env.step("forward 1 m")
        total += reward
    assert info["exit"] and not info["collision"]
    assert total == pytest.approx(14.0) == pytest.approx(info["progress_m"])


def test_reset_options_choose_the_cave_for_that_reset(room_scenario: Scenario) -> None:
    env = CaveNavEnv("S1")
    _, info = env.reset(seed=0, options={"scenario": room_scenario})
    assert info["scenario"] == "room"
    _, info = env.reset(seed=0)
    assert info["scenario"] == "S1" and info["cave_seed"] == 0
    with pytest.raises(ConfigError, match="unknown reset option"):
        env.reset(options={"difficulty": 3})


def test_stepping_before_reset_says_to_reset() -> None:
    with pytest.raises(gym.error.ResetNeeded, match="Call reset"):
        CaveNavEnv("S1").step("hold")


def test_the_rendered_frame_is_the_colour_observation() -> None:
    env = CaveNavEnv("S1", render_mode="rgb_array")
    obs, _ = env.reset(seed=3)
    frame = env.render()
    assert frame is not None and np.array_equal(frame, obs["rgb"]) and frame is not obs["rgb"]


@pytest.mark.parametrize(
    ("vector", "expected"),
    [
        ((0.4, -0.14, 0.0, 12.0), Action(0.5, -0.1, 0.0, 10.0)),
        ((0.04, 0.9, 0.049, -170.0), Action(0.0, 1.0, 0.0, -180.0)),
        ((-1.0, 0.0, 0.05, 0.0), Action(-1.0, 0.0, 0.1, 0.0)),  # 0.05 m: up to the minimum
        ((0.0, 0.0, -0.734, 33.0), Action(0.0, 0.0, -0.73, 30.0)),  # rounded to the cm
        ((0.0, 0.0, 2.0, 180.0), Action(0.0, 0.0, 2.0, 180.0)),
    ],
)
def test_action_vectors_snap_to_the_nearest_admissible_values(vector, expected) -> None:
    assert snap_action(np.array(vector, np.float32)) == expected


def test_a_vector_that_is_not_four_finite_numbers_is_rejected() -> None:
    with pytest.raises(ActionError, match="4 finite numbers"):
        snap_action(np.array([0.0, np.nan, 0.0, 0.0]))
