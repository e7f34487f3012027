"""Learners welcome: the environment as Stable-Baselines3 and Gymnasium's wrappers meet it."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

import cavenav  # noqa: F401 - registers the environments
from cavenav.env import LEARNER_REWARD, CaveNavEnv, Reward
from cavenav.world.scenario import Scenario
from cavenav.wrappers import StuckLimit

VECTOR_ID = "cavenav/CaveNav-vector-v0"
FORWARD_1M = np.array([1.0, 0.0, 0.0, 0.0], np.float32)


def test_the_vector_id_gives_numbers_for_actions_small_images_and_the_learners_reward():
    env = gym.make(VECTOR_ID)
    assert env.spec is not None and env.spec.max_episode_steps == 150
    assert isinstance(env.action_space, gym.spaces.Box) and env.action_space.shape == (4,)
    space = env.observation_space
    assert space["rgb"].shape == (84, 84, 3) and space["depth"].shape == (84, 84, 1)
    assert space["depth"].dtype == np.uint8  # an image to a learning library
    assert space["d_top"].shape == space["d_bottom"].shape == (1,)
    assert env.unwrapped.reward == LEARNER_REWARD
    bigger = gym.make(VECTOR_ID, resolution=(160, 120), reward=Reward())
    assert bigger.observation_space["rgb"].shape == (120, 160, 3)
    assert bigger.unwrapped.reward == Reward()


def test_the_reward_is_the_sum_of_its_terms_and_by_default_the_methods_reward():
    default = CaveNavEnv("S1", resolution=(84, 84), action_format="vector")
    learner = CaveNavEnv("S1", resolution=(84, 84), action_format="vector", reward=LEARNER_REWARD)
    for env in (default, learner):
        env.reset(seed=0)
    _, plain, *_, info = default.step(FORWARD_1M)
    _, shaped, *_, shaped_info = learner.step(FORWARD_1M)
    terms = shaped_info["reward_terms"]
    assert set(terms) == {"progress", "collision", "standoff", "exit"}
    assert shaped == pytest.approx(sum(terms.values()))
    assert info["reward_terms"]["standoff"] == 0.0 and plain == info["reward_terms"]["progress"]
    assert terms["progress"] == pytest.approx(plain)  # the same move in the same cave
    short = max(2.0 - info["clearance_m"], 0.0)  # the standoff is 2 m
    assert terms["standoff"] == pytest.approx(-0.5 * short)


def test_a_collision_costs_its_term_and_the_old_keyword_still_sets_it(room_scenario: Scenario):
    env = CaveNavEnv(room_scenario, collision_penalty=3.0)
    assert env.reward.collision == 3.0 and env.collision_penalty == 3.0
    env.reset(seed=0)
    env.step("strafe right 1 m")
    _, reward, terminated, _, info = env.step("strafe right 1 m")  # the wall is 2 m off
    assert terminated and info["collision"] and info["reward_terms"]["collision"] == -3.0
    assert reward == pytest.approx(sum(info["reward_terms"].values()))


def test_the_exit_bonus_is_paid_on_the_step_that_leaves_the_cave(room_scenario: Scenario):
    env = CaveNavEnv(room_scenario, reward=Reward(exit=7.0))
    env.reset(seed=0)
    bonuses, terminated, info = [], False, {}
    while not terminated:
        *_, terminated, _, info = env.step("forward 1 m")
        bonuses.append(info["reward_terms"]["exit"])
    assert info["exit"] and bonuses == [0.0] * (len(bonuses) - 1) + [7.0]


def test_episode_statistics_sum_the_rewards_and_the_time_limit_truncates():
    env = gym.wrappers.RecordEpisodeStatistics(gym.make(VECTOR_ID, max_episode_steps=3))
    env.reset(seed=0)
    rewards, done = [], False
    while not done:
        _, reward, terminated, truncated, info = env.step(np.zeros(4, np.float32))  # hold
        rewards.append(reward)
        done = terminated or truncated
    assert truncated and not terminated  # the budget truncates; nothing ended the flight
    assert info["episode"]["l"] == 3 and info["episode"]["r"] == pytest.approx(sum(rewards))


def test_the_stuck_limit_truncates_and_the_statistics_close_the_episode():
    stuck = StuckLimit(gym.make(VECTOR_ID), 3)  # three steps that make no headway
    env = gym.wrappers.RecordEpisodeStatistics(stuck)
    env.reset(seed=0)
    for _ in range(3):
        _, _, terminated, truncated, info = env.step(np.zeros(4, np.float32))
    assert truncated and not terminated and info["stuck"] and info["episode"]["l"] == 3


def test_a_learning_library_refusing_action_strings_names_the_vector_id():
    # Stable-Baselines3 refuses a text action space and prints it: the repr points on.
    space = gym.make("cavenav/CaveNav-v0", resolution=(84, 84)).action_space
    assert VECTOR_ID in repr(space) and "action_format='vector'" in str(space)


@pytest.mark.slow
def test_stable_baselines3_check_env_passes_for_the_vector_id():
    env_checker = pytest.importorskip("stable_baselines3.common.env_checker")
    with pytest.warns(UserWarning):  # advice only: depth_m is metres, not an image
        env_checker.check_env(gym.make(VECTOR_ID).unwrapped)


@pytest.mark.slow
@pytest.mark.parametrize("algorithm", ["PPO", "SAC"])
def test_ppo_and_sac_train_on_the_vector_id_with_no_wrapper(algorithm: str):
    sb3 = pytest.importorskip("stable_baselines3")
    env = gym.make(VECTOR_ID)
    options = {"n_steps": 64, "batch_size": 32} if algorithm == "PPO" else {"buffer_size": 500}
    model = getattr(sb3, algorithm)("MultiInputPolicy", env, seed=0, device="cpu", **options)
    model.learn(total_timesteps=128 if algorithm == "PPO" else 96)
    obs, _ = env.reset(seed=1)
    action, _ = model.predict(obs, deterministic=True)
    assert action.shape == (4,) and env.action_space.contains(action)


@pytest.mark.slow
def test_stable_baselines3_refuses_action_strings_with_the_way_to_the_vector_id():
    sb3 = pytest.importorskip("stable_baselines3")
    with pytest.raises(AssertionError, match="CaveNav-vector-v0"):
        sb3.PPO("MultiInputPolicy", gym.make("cavenav/CaveNav-v0", resolution=(84, 84)))


@pytest.mark.slow
def test_the_training_example_trains_saves_and_plots_within_its_budget(tmp_path: Path):
    pytest.importorskip("stable_baselines3")
    script = Path(__file__).resolve().parents[1] / "examples" / "train_ppo.py"
    run = [sys.executable, str(script), "--steps", "64", "--caves", "1", "--evaluate", "1"]
    run += ["--out", str(tmp_path)]
    done = subprocess.run(run, capture_output=True, text=True, timeout=600, check=False)
    assert done.returncode == 0, done.stderr[-2000:]
    assert (tmp_path / "ppo_cavenav.zip").stat().st_size > 0
    assert (tmp_path / "curve.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    (log,) = tmp_path.glob("monitor-*.monitor.csv")
    header = log.read_text().splitlines()[1]
    assert header == "r,l,t,exit,collision"
    flown = json.loads((tmp_path / "evaluation.json").read_text())["ppo_cavenav"]
    assert flown["caves"] == 1 and 0.0 <= flown["exit_share"] <= 1.0
