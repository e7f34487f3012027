"""Many cave environments stepped as one: a native `gymnasium.vector.VectorEnv`.

``gymnasium.make_vec("cavenav/CaveNav-v0", num_envs=16,
vectorization_mode="vector_entry_point", resolution=(84, 84))`` returns a
`CaveNavVectorEnv`, and ``cavenav/CaveNav-vector-v0`` its learner's version.

Each sub-environment is a `CaveNavEnv` and flies exactly as it would alone: with the same
seeds and actions, the same observations, rewards and endings as N environments under
`gymnasium.vector.SyncVectorEnv` (a test holds it to that, bit for bit). What is shared
is what sharing makes cheaper:

- environments in the same cave share its ray caster (one BVH in memory, built once),
  and a cave no environment flies any more is let go at the next reset;
- each step casts the sensor rays of all the environments in one cave in one call
  (`CaveNavEnv.begin_step`, `sensor_rays`, `end_step`), which the ray caster spreads
  over every core, instead of one small cast each.

Physics, collisions and shading stay per environment. Autoreset is Gymnasium's default
(``NEXT_STEP``): the step after an episode ends resets that environment and returns its
first observation with reward 0. Episodes are cut at ``max_episode_steps`` (the
registration's 150), as `gymnasium.wrappers.TimeLimit` cuts a single environment's.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from copy import deepcopy
from typing import Any

import numpy as np
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space, concatenate, create_empty_array, iterate

from cavenav.env import CaveNavEnv, Move, learner_env

__all__ = ["CaveNavVectorEnv", "learner_vector_env"]

SOMETIMES_A_DICT = ("collision_pose",)  # `CaveNavEnv` info keys that are a dict or None


class CaveNavVectorEnv(VectorEnv):
    """``num_envs`` `CaveNavEnv` made by ``make(**options)``, stepped together."""

    metadata = {"autoreset_mode": AutoresetMode.NEXT_STEP, "render_modes": []}

    def __init__(
        self,
        num_envs: int = 1,
        *,
        max_episode_steps: int | None = None,
        make: Callable[..., CaveNavEnv] = CaveNavEnv,
        **options: Any,
    ):
        """
        Args:
            max_episode_steps: truncate an episode after this many steps; None never.
            make: builds each sub-environment from ``options`` (`CaveNavEnv`'s keywords).
        """
        if num_envs < 1:
            raise ValueError(f"num_envs must be at least 1, got {num_envs}")
        self.caves: dict[Any, Any] = {}  # shared by the sub-environments (CaveNavEnv.caves)
        self.envs = [make(**options, caves=self.caves) for _ in range(num_envs)]
        self.num_envs, self.max_episode_steps = num_envs, max_episode_steps
        first = self.envs[0]
        self.single_observation_space = first.observation_space
        self.single_action_space = first.action_space
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.action_space = batch_space(self.single_action_space, num_envs)
        self._observations = create_empty_array(self.single_observation_space, num_envs)
        self._elapsed = np.zeros(num_envs, np.int64)
        self._autoreset = np.zeros(num_envs, bool)

    def reset(
        self, *, seed: int | Sequence[int | None] | None = None, options: dict | None = None
    ) -> tuple[Any, dict[str, Any]]:
        """Reset every sub-environment, seeded ``seed + i`` (as `SyncVectorEnv` seeds them),
        or those ``options["reset_mask"]`` marks."""
        if seed is None or isinstance(seed, int):
            seeds = [None if seed is None else seed + i for i in range(self.num_envs)]
        else:
            seeds = list(seed)
            if len(seeds) != self.num_envs:
                raise ValueError(f"{len(seeds)} seeds for {self.num_envs} environments")
        options = dict(options or {})
        mask = np.asarray(options.pop("reset_mask", np.ones(self.num_envs, bool)))
        observations, infos = [], {}
        for i, env in enumerate(self.envs):
            if mask[i]:
                observation, info = env.reset(seed=seeds[i], options=options or None)
                self._elapsed[i], self._autoreset[i] = 0, False
                infos = self._add_info(infos, info, i)
            else:
                observation = env._observation_dict()
            observations.append(observation)
        self._let_go_of_unflown_caves()
        return self._batched(observations), infos

    def step(self, actions: Any) -> tuple[Any, np.ndarray, np.ndarray, np.ndarray, dict]:  # noqa: ANN401
        """Step every sub-environment; one that ended last step is reset instead."""
        results: list[Any] = [None] * self.num_envs
        moves: dict[int, Move] = {}
        for i, (env, action) in enumerate(zip(self.envs, iterate(self.action_space, actions),
                                              strict=True)):  # fmt: skip
            if self._autoreset[i]:
                observation, info = env.reset()
                self._elapsed[i] = 0
                results[i] = (observation, 0.0, False, False, info)
            else:
                moves[i] = env.begin_step(action)
        for i, cast in self._cast_together(list(moves)):
            results[i] = self.envs[i].end_step(moves[i], cast)
            self._elapsed[i] += 1
        if any(self._autoreset):
            self._let_go_of_unflown_caves()
        return self._gathered(results)

    def _cast_together(self, stepped: list[int]) -> list[tuple[int, dict[str, np.ndarray]]]:
        """Cast the sensor rays of the environments ``stepped``, all those in one cave in
        one call; what each environment's own rays gave."""
        by_cave: dict[int, list[int]] = {}
        for i in stepped:
            by_cave.setdefault(id(self.envs[i].caster), []).append(i)
        casts = []
        for members in by_cave.values():
            rays = [self.envs[i].sensor_rays() for i in members]
            cast = self.envs[members[0]].caster.cast_raw_rays(np.concatenate(rays))
            start = 0
            for i, own in zip(members, rays, strict=True):
                end = start + len(own)
                casts.append((i, {key: value[start:end] for key, value in cast.items()}))
                start = end
        return casts

    def _gathered(self, results: list[Any]) -> tuple[Any, np.ndarray, np.ndarray, np.ndarray, dict]:
        observations, infos = [], {}
        rewards = np.zeros(self.num_envs, np.float64)
        terminated = np.zeros(self.num_envs, bool)
        truncated = np.zeros(self.num_envs, bool)
        for i, (observation, reward, ended, cut, info) in enumerate(results):
            observations.append(observation)
            rewards[i], terminated[i] = reward, ended
            limit = self.max_episode_steps
            truncated[i] = cut or (limit is not None and self._elapsed[i] >= limit)
            infos = self._add_info(infos, info, i)
        self._autoreset = terminated | truncated
        return self._batched(observations), rewards, terminated, truncated, infos

    def _batched(self, observations: list[Any]) -> Any:  # noqa: ANN401
        space = self.single_observation_space
        return deepcopy(concatenate(space, observations, self._observations))

    def _let_go_of_unflown_caves(self) -> None:
        """Forget the caves no sub-environment flies any more (their BVHs with them)."""
        flown = {env._world.key for env in self.envs if env._world is not None}
        for key in set(self.caves) - flown:
            del self.caves[key]

    def _add_info(self, vector_infos: dict, env_info: dict, env_num: int) -> dict:
        """Gymnasium's batching of the infos, but for the keys whose value is a dict in
        one environment's info and None in another's (``collision_pose``): those are kept
        as object arrays, where Gymnasium's own recursion into the dicts fails
        (`SyncVectorEnv` raises AttributeError at the first collision beside a step
        without one)."""
        sometimes = {key: env_info[key] for key in SOMETIMES_A_DICT if key in env_info}
        rest = {key: value for key, value in env_info.items() if key not in sometimes}
        vector_infos = super()._add_info(vector_infos, rest, env_num)
        for key, value in sometimes.items():
            array = vector_infos.get(key)
            if array is None:
                array = np.full(self.num_envs, None, dtype=object)
            mask = vector_infos.get(f"_{key}", np.zeros(self.num_envs, bool))
            array[env_num], mask[env_num] = value, True
            vector_infos[key], vector_infos[f"_{key}"] = array, mask
        return vector_infos

    def close_extras(self, **kwargs: Any) -> None:
        for env in self.envs:
            env.close()


def learner_vector_env(num_envs: int = 1, **options: Any) -> CaveNavVectorEnv:
    """``cavenav/CaveNav-vector-v0`` batched: `learner_env`'s sub-environments."""
    return CaveNavVectorEnv(num_envs, make=learner_env, **options)
