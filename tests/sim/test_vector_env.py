"""The native batched environment: `gymnasium.make_vec` gives it, and it flies exactly as
the same number of single environments do, its sensor rays cast together."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import cavenav  # noqa: F401 - registers the environments
from cavenav.sim.env import CaveNavEnv
from cavenav.sim.vector_env import CaveNavVectorEnv, batched_infos

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
@pytest.mark.parametrize(
    ("cave_seed", "resolution", "workers"),
    [(None, SMALL, 1), (0, SMALL, 2), (0, (160, 120), 2)],
    ids=["a cave each, in turn", "one cave, two at once", "frames a lone one splits"],
)
def test_it_flies_exactly_as_single_environments_given_the_same_seeds_and_actions(
    cave_seed: int | None, resolution: tuple[int, int], workers: int
) -> None:
    """20 steps (12 where every reset builds a cave, seconds each), episodes cut at 6
    steps so that every environment ends and is reset;
    the first environment strafes right into the wall (collisions), the others fly at
    random; in a cave each or all in one (their rays then cast together); shaded one
    after another or two at once, each on one thread, also at a size whose frames a
    lone environment splits over every thread (on a machine with two cores or more;
    test_sensors holds frames to the same bits on 1, 2 and 3 threads anywhere)."""
    n, options = 4, {"resolution": resolution, "cave_seed": cave_seed, "max_episode_steps": 6}
    vector = gym.make_vec(LEARNER, num_envs=n, vectorization_mode="vector_entry_point",
                          workers=workers, **options)  # fmt: skip
    singles = [gym.make(LEARNER, **options) for _ in range(n)]
    batched, _ = vector.reset(seed=7)
    for i, env in enumerate(singles):
        alone, _ = env.reset(seed=7 + i)
        assert all(np.array_equal(batched[key][i], alone[key]) for key in alone)
    rng, ended, endings, collisions = np.random.default_rng(0), [False] * n, 0, 0
    for _ in range(12 if cave_seed is None else 20):
        actions = rng.uniform(-1, 1, size=(n, 4)).astype(np.float32)
        actions[0] = (0.0, 1.0, 0.0, 0.0)  # strafe right 1 m, into the wall
        batched, rewards, terminated, truncated, infos = vector.step(actions)
        collisions += int(infos["collision"][infos["_collision"]].sum())
        for i, env in enumerate(singles):
            if ended[i]:  # next-step autoreset, as Gymnasium's vector environments do it
                alone, reward, stop, cut = env.reset()[0], 0.0, False, False
            else:
                alone, reward, stop, cut, info = env.step(actions[i])
                for key in ("clearance_m", "progress_m", "collision", "collision_pose"):
                    assert infos[key][i] == info[key], key
            assert all(np.array_equal(batched[key][i], alone[key]) for key in alone)
            assert (rewards[i], terminated[i], truncated[i]) == (reward, stop, cut)
            ended[i] = stop or cut
            endings += ended[i]
    assert endings >= n and collisions >= 2  # every one was reset; the wall was met
    caves = len(vector.unwrapped.caves)
    assert caves == (1 if cave_seed == 0 else n)  # the caves flown now, no more
    vector.close()


@pytest.mark.parametrize("order", [(0, 1), (1, 0)], ids=["none first", "dict first"])
def test_infos_of_mixed_kinds_batch_whatever_order_they_come_in(order: tuple[int, int]) -> None:
    """``collision_pose`` is a dict or None, ``current_m_s`` a float or None: Gymnasium's
    own batching takes the kind of the first and fails (or misreads) on the other."""
    infos = [
        {"collision_pose": None, "current_m_s": None, "steps": 3, "pose": {"x": 1.0}},
        {"collision_pose": {"x": 2.0}, "current_m_s": 0.25, "steps": 4, "pose": {"x": 2.5}},
    ]
    batched = batched_infos([infos[i] for i in order])
    assert [batched["collision_pose"][order.index(i)] for i in (0, 1)] == [None, {"x": 2.0}]
    assert [batched["current_m_s"][order.index(i)] for i in (0, 1)] == [None, 0.25]
    assert batched["steps"].dtype == np.int64 and batched["pose"]["x"].dtype == np.float64
    assert batched["_collision_pose"].all() and batched["pose"]["_x"].all()
    partial = batched_infos([None, {"progress_m": 1.5}])
    assert list(partial["_progress_m"]) == [False, True] and partial["progress_m"][1] == 1.5


def test_a_reset_mask_resets_only_those_it_marks_and_a_bad_one_is_refused() -> None:
    vector = CaveNavVectorEnv(2, resolution=SMALL, action_format="vector")
    first, _ = vector.reset(seed=0)
    vector.step(np.array([[1.0, 0.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0]], np.float32))
    moved, _ = vector.reset(seed=5, options={"reset_mask": np.array([False, True])})
    assert not np.array_equal(moved["rgb"][0], first["rgb"][0])  # left where it flew to
    alone = CaveNavEnv(resolution=SMALL, action_format="vector").reset(seed=6)[0]
    assert np.array_equal(moved["rgb"][1], alone["rgb"])  # reset with seed 5 + 1
    for bad in (np.array([False, False]), np.array([True]), [True, False]):
        with pytest.raises(ValueError, match="reset_mask"):
            vector.reset(options={"reset_mask": bad})
    vector.close()
    assert vector.caves == {}  # closed: the caves let go


def test_a_step_budget_and_a_number_of_workers_must_be_positive_whole_numbers() -> None:
    with pytest.raises(ValueError, match="max_episode_steps"):
        CaveNavVectorEnv(2, max_episode_steps=0)
    for workers in (0, 1.5):
        with pytest.raises(ValueError, match="workers"):
            CaveNavVectorEnv(2, workers=workers)


def test_text_actions_fly_batched_too() -> None:
    vector = gym.make_vec("cavenav/CaveNav-v0", num_envs=2, resolution=SMALL)
    vector.reset(seed=0)
    _, _, _, _, infos = vector.step(("forward 0.5 m", "turn left 15 deg"))
    assert list(infos["action"]) == ["forward 0.5 m", "turn left 15 deg"]
    vector.close()
