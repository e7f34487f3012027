"""Many cave environments stepped as one: a native `gymnasium.vector.VectorEnv`.

``gymnasium.make_vec("cavenav/CaveNav-v0", num_envs=16,
vectorization_mode="vector_entry_point", resolution=(84, 84))`` returns a
`CaveNavVectorEnv`, and ``cavenav/CaveNav-vector-v0`` its learner's version.

Each sub-environment is a `CaveNavEnv` and flies exactly as it would alone: with the same
seeds and actions, the same observations, rewards, endings and infos as N single
environments stepped as `gymnasium.vector.SyncVectorEnv` steps them (a test holds it to
that, bit for bit). What is shared is what sharing makes cheaper:

- environments in the same cave share its ray caster (one BVH in memory, built once),
  and a cave no environment flies any more is let go at the next reset;
- each step casts the sensor rays of all the environments in one cave in one call
  (`CaveNavEnv.begin_step`, `sensor_rays`, `end_step`), which the ray caster spreads
  over every core, instead of one small cast each;
- then the environments' frames are shaded at once, one environment to a thread on as
  many threads as Numba may use (``workers``), Numba's threads shared out between them:
  the shading kernels let go of Python's lock, and a small frame shaded on one core
  wastes none of it waiting for the others, as a small frame split over the cores does.

Physics and collisions stay per environment, in turn. A frame is the same bits on any
number of threads (the rig's kernels make sure of it), so batching changes no
observation. Autoreset is Gymnasium's default (``NEXT_STEP``): the step after an
episode ends resets that environment and returns its first observation with reward 0.
Episodes are cut at ``max_episode_steps`` (the registration's 150), as
`gymnasium.wrappers.TimeLimit` cuts a single environment's. The infos are batched by
`batched_infos`, which Gymnasium's own batching cannot replace here (its docstring says
why).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor, wait
from copy import deepcopy
from typing import Any

import numba
import numpy as np
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space, concatenate, create_empty_array, iterate

from cavenav.sensors.kernels import KERNELS_RUN_CONCURRENTLY
from cavenav.sim.env import CaveNavEnv, Move, learner_env

__all__ = ["CaveNavVectorEnv", "batched_infos", "learner_vector_env", "unbatched_infos"]


class CaveNavVectorEnv(VectorEnv):
    """``num_envs`` `CaveNavEnv` made by ``make(**options)``, stepped together."""

    metadata = {"autoreset_mode": AutoresetMode.NEXT_STEP, **CaveNavEnv.metadata}

    def __init__(
        self,
        num_envs: int = 1,
        *,
        max_episode_steps: int | None = None,
        make: Callable[..., CaveNavEnv] = CaveNavEnv,
        workers: int | None = None,
        **options: Any,
    ):
        """
        Args:
            max_episode_steps: truncate an episode after this many steps; None never
                (`gymnasium.make_vec` gives the registration's 150).
            make: builds each sub-environment from ``options`` (`CaveNavEnv`'s keywords).
            workers: threads that shade the environments' frames at once, sharing
                Numba's threads out between them; None: as many as Numba has here (the
                cores, or ``NUMBA_NUM_THREADS``), at most one an environment; 1 shades
                them in turn, each as a lone environment would. Where Numba's threading
                layer cannot launch kernels from several threads
                (`cavenav.sensors.kernels.KERNELS_RUN_CONCURRENTLY`), always 1.
        """
        if num_envs < 1:
            raise ValueError(f"num_envs must be at least 1, got {num_envs}")
        if workers is not None and not (isinstance(workers, int) and workers > 0):
            raise ValueError(f"workers must be a positive int or None: {workers}")
        if max_episode_steps is not None and not (
            isinstance(max_episode_steps, int) and max_episode_steps > 0
        ):
            raise ValueError(
                f"max_episode_steps must be a positive int or None: {max_episode_steps}"
            )
        self.caves: dict[Any, Any] = {}  # shared by the sub-environments (CaveNavEnv.caves)
        self.envs = [make(**options, caves=self.caves) for _ in range(num_envs)]
        self.num_envs, self.max_episode_steps = num_envs, max_episode_steps
        first = self.envs[0]
        self.render_mode = first.render_mode
        self.single_observation_space = first.observation_space
        self.single_action_space = first.action_space
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.action_space = batch_space(self.single_action_space, num_envs)
        self._observations = create_empty_array(self.single_observation_space, num_envs)
        self._elapsed = np.zeros(num_envs, np.int64)
        self._autoreset = np.zeros(num_envs, bool)
        cores = numba.get_num_threads()
        workers = min(workers or cores, num_envs) if KERNELS_RUN_CONCURRENTLY else 1
        self._shaders = (
            ThreadPoolExecutor(
                workers, "cavenav-shade", numba.set_num_threads, (max(1, cores // workers),)
            )
            if workers > 1
            else None
        )

    # Per environment, as SyncVectorEnv has them: VectorEnv types them as one.
    @property  # type: ignore[misc]
    def np_random(self) -> tuple[np.random.Generator, ...]:  # type: ignore[override]
        """The sub-environments' generators, as `SyncVectorEnv` gives them."""
        return tuple(env.np_random for env in self.envs)

    @property
    def np_random_seed(self) -> tuple[int, ...]:  # type: ignore[override]
        return tuple(env.np_random_seed for env in self.envs)

    def reset(
        self, *, seed: int | Sequence[int | None] | None = None, options: dict | None = None
    ) -> tuple[Any, dict[str, Any]]:
        """Reset every sub-environment, seeded ``seed + i`` (as `SyncVectorEnv` seeds them),
        or those ``options["reset_mask"]`` marks (a bool array, one per environment)."""
        if seed is None or isinstance(seed, int):
            seeds = [None if seed is None else seed + i for i in range(self.num_envs)]
        else:
            seeds = list(seed)
            if len(seeds) != self.num_envs:
                raise ValueError(f"{len(seeds)} seeds for {self.num_envs} environments")
        options = dict(options or {})
        mask = _reset_mask(options.pop("reset_mask", None), self.num_envs)
        observations, infos = [], [None] * self.num_envs  # type: list[Any], list[dict | None]
        for i, env in enumerate(self.envs):
            if mask[i]:
                observation, infos[i] = env.reset(seed=seeds[i], options=options or None)
                self._elapsed[i], self._autoreset[i] = 0, False
            else:
                observation = env._observation_dict()
            observations.append(observation)
        self._let_go_of_unflown_caves()
        return self._batched(observations), batched_infos(infos)

    def step(
        self,
        actions: Any,  # noqa: ANN401 - the batched action space's
    ) -> tuple[Any, np.ndarray, np.ndarray, np.ndarray, dict]:
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

        def sense(job: tuple[int, dict[str, np.ndarray], float]) -> None:
            i, cast, cast_ms = job
            results[i] = self.envs[i].end_step(moves[i], cast, cast_ms)

        jobs = self._cast_together(list(moves))
        if self._shaders is None:
            for job in jobs:
                sense(job)
        else:  # every frame finished before a failure is raised: none is left shading
            shading = [self._shaders.submit(sense, job) for job in jobs]
            wait(shading)
            for frame in shading:
                frame.result()
        self._elapsed[list(moves)] += 1
        if any(self._autoreset):
            self._let_go_of_unflown_caves()
        return self._gathered(results)

    def _cast_together(self, stepped: list[int]) -> list[tuple[int, dict[str, np.ndarray], float]]:
        """Cast the sensor rays of the environments ``stepped``, all those in one cave in
        one call; what each environment's own rays gave, and its share of the cast's
        time (ms, by rays)."""
        by_cave: dict[int, list[int]] = {}
        for i in stepped:
            by_cave.setdefault(id(self.envs[i].caster), []).append(i)
        casts = []
        for members in by_cave.values():
            rays = [self.envs[i].sensor_rays() for i in members]
            started = time.perf_counter()
            cast = self.envs[members[0]].caster.cast_raw_rays(np.concatenate(rays))
            per_ray_ms = 1e3 * (time.perf_counter() - started) / len(cast["t_hit"])
            start = 0
            for i, own in zip(members, rays, strict=True):
                end = start + len(own)
                part = {key: value[start:end] for key, value in cast.items()}
                casts.append((i, part, per_ray_ms * len(own)))
                start = end
        return casts

    def _gathered(self, results: list[Any]) -> tuple[Any, np.ndarray, np.ndarray, np.ndarray, dict]:
        observations, infos = [], []
        rewards = np.zeros(self.num_envs, np.float64)
        terminated = np.zeros(self.num_envs, bool)
        truncated = np.zeros(self.num_envs, bool)
        for i, (observation, reward, ended, cut, info) in enumerate(results):
            observations.append(observation)
            infos.append(info)
            rewards[i], terminated[i] = reward, ended
            limit = self.max_episode_steps
            truncated[i] = cut or (limit is not None and self._elapsed[i] >= limit)
        self._autoreset = terminated | truncated
        return self._batched(observations), rewards, terminated, truncated, batched_infos(infos)

    def _batched(self, observations: list[Any]) -> Any:  # noqa: ANN401
        space = self.single_observation_space
        return deepcopy(concatenate(space, observations, self._observations))  # type: ignore[arg-type]

    def _let_go_of_unflown_caves(self) -> None:
        """Forget the caves no sub-environment flies any more (their BVHs with them)."""
        flown = {env._world.key for env in self.envs if env._world is not None}
        for key in set(self.caves) - flown:
            del self.caves[key]

    def render(self) -> tuple[np.ndarray | None, ...]:  # type: ignore[override]
        """Each sub-environment's frame (``render_mode="rgb_array"``), as `SyncVectorEnv`."""
        return tuple(env.render() for env in self.envs)

    def close_extras(self, **kwargs: Any) -> None:
        """Close the sub-environments and let their caves go."""
        if self._shaders is not None:
            self._shaders.shutdown()
        for env in self.envs:
            env.close()
            env._world = None
        self.caves.clear()


def _reset_mask(mask: Any, count: int) -> np.ndarray:  # noqa: ANN401
    """``options["reset_mask"]`` checked as `SyncVectorEnv` checks it; None: all."""
    if mask is None:
        return np.ones(count, bool)
    if not isinstance(mask, np.ndarray) or mask.dtype != np.bool_ or mask.shape != (count,):
        raise ValueError(f"options['reset_mask'] must be a bool numpy array of shape ({count},)")
    if not mask.any():
        raise ValueError("options['reset_mask'] must mark at least one environment")
    return mask


def batched_infos(infos: Sequence[Mapping[str, Any] | None]) -> dict[str, Any]:
    """The sub-environments' ``infos`` (None: not reset) as Gymnasium's vector environments
    batch them: each key an array over the environments, with a ``_key`` mask of those
    that gave it; a key that is a dict in each info that has it, a dict of such arrays.

    The array's type is chosen from every environment's value, not the first's:
    Gymnasium's own batching takes it from the first and then fails or misreads a value
    of another type (``collision_pose``, a dict or None, raises AttributeError in
    `SyncVectorEnv`; a None after a float is read as NaN). Bools, ints and floats that are
    all of one kind give arrays of it (ints and floats, floats); anything else, objects.
    """
    batched: dict[str, Any] = {}
    count = len(infos)
    keys = dict.fromkeys(key for info in infos if info for key in info)
    for key in keys:
        given = {i: info[key] for i, info in enumerate(infos) if info and key in info}
        mask = np.zeros(count, bool)
        mask[list(given)] = True
        values = list(given.values())
        if all(isinstance(value, Mapping) for value in values):
            batched[key] = batched_infos([given.get(i) for i in range(count)])
        else:
            batched[key] = _array_of(given, count)
        batched[f"_{key}"] = mask
    return batched


def unbatched_infos(batched: Mapping[str, Any], count: int) -> list[dict[str, Any]]:
    """The inverse of `batched_infos`: one info dict per environment, holding the keys its
    ``_key`` masks mark, numpy scalars as plain Python values (what a learner that takes
    a list of infos, as Stable-Baselines3 does, expects)."""
    infos: list[dict[str, Any]] = [{} for _ in range(count)]
    for key, values in batched.items():
        mask = batched.get(f"_{key}")
        if mask is None:  # a mask itself
            continue
        per_env = unbatched_infos(values, count) if isinstance(values, Mapping) else values
        for i in np.flatnonzero(mask):
            value = per_env[i]
            infos[i][key] = value.item() if isinstance(value, np.generic) else value
    return infos


def _array_of(given: Mapping[int, Any], count: int) -> np.ndarray:
    """One value per environment in the narrowest array that holds them all."""
    kinds = {type(value) for value in given.values()}
    dtype: Any = object
    if kinds <= {bool, np.bool_}:
        dtype = np.bool_
    elif kinds and all(issubclass(kind, int | np.integer) and kind is not bool for kind in kinds):
        dtype = np.int64
    elif kinds and all(
        issubclass(kind, float | int | np.floating | np.integer) and kind is not bool
        for kind in kinds
    ):
        dtype = np.float64
    array = np.zeros(count, dtype) if dtype is not object else np.full(count, None, object)
    for i, value in given.items():
        array[i] = value
    return array


def learner_vector_env(num_envs: int = 1, **options: Any) -> CaveNavVectorEnv:
    """``cavenav/CaveNav-vector-v0`` batched: `learner_env`'s sub-environments."""
    return CaveNavVectorEnv(num_envs, make=learner_env, **options)
