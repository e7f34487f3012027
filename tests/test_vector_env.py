"""The native batched environment: `gymnasium.make_vec` gives it, and it flies exactly as
the same number of single environments do, its sensor rays cast together."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import cavenav  # noqa: F401 - registers the environments
from cavenav.vector_env import CaveNavVectorEnv

LEARNER = "cavenav/CaveNav-vector-v0"
SMALL = (32, 24)


def test_make_vec_gives_the_native_batched_environment_by_its_vector_entry_point() -> None:
    for env_id in ("cavenav/CaveNav-v0", LEARNER):
        vector = gym.make_vec(env_id, num_envs=3, vectorization_mode="vector_entry_point",
                              resolution=SMALL)  # fmt: skip
        assert isinstance(vector.unwrapped, CaveNavVectorEnv)
        assert vector.num_envs == 3 and vector.unwrapped.max_episode_steps == 150
        observations, _ = vector.reset(seed=0)
        assert observations["rgb"].shape == (3, 24, 32, 3)
        assert observations in vector.observation_space
        vector.close()


@pytest.mark.slow
@pytest.mark.parametrize("cave_seed", [None, 0], ids=["a cave each", "one cave"])
def test_it_flies_exactly_as_single_environments_given_the_same_seeds_and_actions(
    cave_seed: int | None,
) -> None:
    """Random actions for 20 steps, episodes cut at 6 steps so that every environment
    ends and is reset (collisions too, at random), in its own cave or all in one."""
    n, options = 4, {"resolution": SMALL, "cave_seed": cave_seed, "max_episode_steps": 6}
    vector = gym.make_vec(LEARNER, num_envs=n, vectorization_mode="vector_entry_point",
                          **options)  # fmt: skip
    singles = [gym.make(LEARNER, **options) for _ in range(n)]
    batched, _ = vector.reset(seed=7)
    for i, env in enumerate(singles):
        alone, _ = env.reset(seed=7 + i)
        assert all(np.array_equal(batched[key][i], alone[key]) for key in alone)
    rng, ended, endings = np.random.default_rng(0), [False] * n, 0
    for _ in range(20):
        actions = rng.uniform(-1, 1, size=(n, 4)).astype(np.float32)
        batched, rewards, terminated, truncated, infos = vector.step(actions)
        for i, env in enumerate(singles):
            if ended[i]:  # next-step autoreset, as Gymnasium's vector environments do it
                alone, reward, stop, cut = env.reset()[0], 0.0, False, False
            else:
                alone, reward, stop, cut, _ = env.step(actions[i])
            assert all(np.array_equal(batched[key][i], alone[key]) for key in alone)
            assert (rewards[i], terminated[i], truncated[i]) == (reward, stop, cut)
            ended[i] = stop or cut
            endings += ended[i]
    assert endings >= n  # every environment was reset at least once
    caves = len(vector.unwrapped.caves)
    assert caves == (1 if cave_seed == 0 else n)  # the caves flown now, no more
    vector.close()


def test_a_collision_beside_a_step_without_one_batches_its_pose() -> None:
    """``collision_pose`` is a dict in one info and None in another: kept as objects."""
    vector = CaveNavVectorEnv(2, resolution=SMALL, action_format="vector")
    infos = vector._add_info({}, {"collision_pose": None, "progress_m": 1.0}, 0)
    infos = vector._add_info(infos, {"collision_pose": {"x": 1.0}, "progress_m": 2.0}, 1)
    assert list(infos["collision_pose"]) == [None, {"x": 1.0}]
    assert infos["_collision_pose"].all() and list(infos["progress_m"]) == [1.0, 2.0]
