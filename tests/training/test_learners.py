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
from cavenav.sim.env import LEARNER_REWARD, CaveNavEnv, Reward
from cavenav.sim.wrappers import StuckLimit
from cavenav.world.scenario import Scenario

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
    script = Path(__file__).resolve().parents[2] / "examples" / "train_ppo.py"
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


def _sb3_vec_env(options: dict, n: int):  # noqa: ANN202 - SB3's VecEnv, imported here
    """The batched environment with ``options`` as SB3's VecEnv (`SB3VecEnv`)."""
    from cavenav.training.sb3_vec_env import SB3VecEnv

    return SB3VecEnv(
        gym.make_vec(VECTOR_ID, num_envs=n, vectorization_mode="vector_entry_point", **options)
    )


@pytest.mark.slow
def test_sb3_vec_env_flies_as_dummy_vec_env_over_single_environments() -> None:
    """Same seeds and actions: the same observations, rewards, ends, last observations and
    step-limit marks; environment 0 strafes into the wall (ended by collisions), the
    others fly at random and are cut at 5 steps."""
    vec_env = pytest.importorskip("stable_baselines3.common.vec_env")
    n, options = 3, {"resolution": (32, 24), "cave_seed": 0, "max_episode_steps": 5}
    batched = _sb3_vec_env(options, n)
    singles = vec_env.DummyVecEnv([lambda: gym.make(VECTOR_ID, **options)] * n)
    for venv in (batched, singles):
        venv.seed(7)
    observations, expected = batched.reset(), singles.reset()
    assert all(np.array_equal(observations[key], expected[key]) for key in expected)
    rng, collided, cut = np.random.default_rng(0), 0, 0
    for _ in range(14):
        actions = rng.uniform(-1, 1, size=(n, 4)).astype(np.float32)
        actions[0] = (0.0, 1.0, 0.0, 0.0)
        got, want = batched.step(actions), singles.step(actions)
        assert all(np.array_equal(got[0][key], want[0][key]) for key in want[0])
        assert np.array_equal(got[1], want[1]) and got[1].dtype == want[1].dtype
        assert np.array_equal(got[2], want[2])
        for info, alone in zip(got[3], want[3], strict=True):
            last, want_last = (
                info.pop("terminal_observation", None),
                alone.pop("terminal_observation", None),
            )
            assert info == alone  # infos one by one, as the single environments gave them
            if want_last is not None:
                assert all(np.array_equal(last[key], want_last[key]) for key in want_last)
                collided += bool(info["collision"])
                cut += bool(info["TimeLimit.truncated"])
    assert collided >= 2 and cut >= 2  # both kinds of ending were met, and reset
    assert batched.get_attr("render_mode") == [None] * n
    assert batched.env_is_wrapped(vec_env.VecMonitor) == [False] * n
    batched.close()


@pytest.mark.slow
def test_ppo_trains_on_the_batched_environment_through_sb3_vec_env() -> None:
    sb3 = pytest.importorskip("stable_baselines3")
    from stable_baselines3.common.vec_env import VecMonitor

    from cavenav.training.sb3_vec_env import SB3VecEnv

    venv = gym.make_vec(VECTOR_ID, num_envs=4, vectorization_mode="vector_entry_point",
                        cave_seed=0, max_episode_steps=8)  # fmt: skip
    seen = gym.wrappers.vector.FilterObservation(venv, ["rgb", "depth", "d_top", "d_bottom"])
    env = VecMonitor(SB3VecEnv(seen), info_keywords=("exit", "collision"))
    model = sb3.PPO("MultiInputPolicy", env, n_steps=16, batch_size=32, seed=0, device="cpu")
    before = [p.detach().clone() for p in model.policy.parameters()]
    model.learn(total_timesteps=128)
    assert model.num_timesteps == 128
    assert len(model.ep_info_buffer) >= 4  # episodes ended, were counted and reset
    assert {"r", "l", "exit", "collision"} <= model.ep_info_buffer[0].keys()
    changed = [not p.equal(b) for p, b in zip(model.policy.parameters(), before, strict=True)]
    assert all(changed)  # every layer learned something
    env.close()


def test_sb3_vec_env_refuses_a_same_step_autoreset_and_names_the_extra_it_needs(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    pytest.importorskip("stable_baselines3")
    from cavenav.training.sb3_vec_env import SB3VecEnv

    same_step = gym.vector.SyncVectorEnv(
        [lambda: gym.make("CartPole-v1")], autoreset_mode=gym.vector.AutoresetMode.SAME_STEP
    )
    with pytest.raises(ValueError, match="autoreset_mode NEXT_STEP"):
        SB3VecEnv(same_step)
    monkeypatch.setitem(sys.modules, "stable_baselines3.common.vec_env", None)
    monkeypatch.delitem(sys.modules, "cavenav.training.sb3_vec_env")
    with pytest.raises(ImportError, match=r"pip install 'cavenav\[learn\]'"):
        import cavenav.training.sb3_vec_env  # noqa: F401
