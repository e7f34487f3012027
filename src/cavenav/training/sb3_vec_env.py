"""Stable-Baselines3 on the batched environment: a Gymnasium vector environment as SB3's
own `VecEnv`.

SB3 refuses Gymnasium's vector environments: it has a `VecEnv` of its own, and its
`DummyVecEnv` over single environments steps them one after another, each casting its
own rays. `SB3VecEnv` hands SB3 `cavenav.sim.vector_env.CaveNavVectorEnv` (or any Gymnasium
vector environment that takes ``options["reset_mask"]``) as it is, so that a learner
gets the batched rate::

    venv = gymnasium.make_vec("cavenav/CaveNav-vector-v0", num_envs=8,
                              vectorization_mode="vector_entry_point", cave_seed=3)
    venv = gymnasium.wrappers.vector.FilterObservation(venv, ["rgb", "depth", "d_top", "d_bottom"])
    model = PPO("MultiInputPolicy", VecMonitor(SB3VecEnv(venv)))

The two disagree on when an ended environment starts again. Gymnasium's resets it at
the next step (autoreset ``NEXT_STEP``); SB3 expects it reset within the step that ended
it, its last observation in the info's ``terminal_observation`` and a cut by the step
limit marked ``TimeLimit.truncated``. The adapter resets the ended environments at once,
by ``reset_mask``: with the same seeds and actions it gives what `DummyVecEnv` over single
environments gives (a test holds it to that).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import iterate

from cavenav.sim.vector_env import unbatched_infos

try:
    from stable_baselines3.common.env_util import is_wrapped
    from stable_baselines3.common.vec_env import VecEnv
except ImportError as missing:  # an optional extra
    raise ImportError(
        f"{missing}: SB3VecEnv needs Stable-Baselines3: pip install 'cavenav[learn]'"
    ) from None

__all__ = ["SB3VecEnv"]


class SB3VecEnv(VecEnv):
    """``venv`` (a Gymnasium vector environment, wrappers allowed) as SB3's `VecEnv`."""

    def __init__(self, venv: VectorEnv):
        """
        Raises:
            ValueError: ``venv`` resets its environments otherwise than at the next step.
        """
        mode = venv.metadata.get("autoreset_mode", AutoresetMode.NEXT_STEP)
        if mode != AutoresetMode.NEXT_STEP:
            raise ValueError(f"SB3VecEnv needs autoreset_mode NEXT_STEP, not {mode}")
        self.venv = venv
        self._actions: np.ndarray | None = None
        super().__init__(venv.num_envs, venv.single_observation_space, venv.single_action_space)

    def reset(self) -> Any:  # noqa: ANN401 - the observation space's
        """Reset every environment with the seeds and options `seed` and `set_options`
        gave (Gymnasium's vector environments take one options dict for all)."""
        seeds = None if all(seed is None for seed in self._seeds) else list(self._seeds)
        if any(options != self._options[0] for options in self._options):
            raise ValueError("SB3VecEnv resets every environment with the same options")
        # One seed each, as SyncVectorEnv and CaveNavVectorEnv take them (typed as one int).
        observations, infos = self.venv.reset(
            seed=seeds,  # type: ignore[arg-type]
            options=self._options[0] or None,
        )
        self.reset_infos = unbatched_infos(infos, self.num_envs)
        self._reset_seeds()
        self._reset_options()
        return observations

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = actions

    def step_wait(self) -> tuple[Any, np.ndarray, np.ndarray, list[dict[str, Any]]]:
        """Step every environment; those that ended are reset within the step (their
        last observation in ``terminal_observation``), as SB3 expects."""
        observations, rewards, terminated, truncated, batched = self.venv.step(self._actions)
        dones = terminated | truncated
        infos = unbatched_infos(batched, self.num_envs)
        for i, info in enumerate(infos):
            info["TimeLimit.truncated"] = bool(truncated[i] and not terminated[i])
        if dones.any():
            last = list(iterate(self.venv.observation_space, observations))
            for ended in np.flatnonzero(dones):
                infos[ended]["terminal_observation"] = last[ended]
            observations, reset = self.venv.reset(options={"reset_mask": dones})
            for i, info in enumerate(unbatched_infos(reset, self.num_envs)):
                if dones[i]:
                    self.reset_infos[i] = info
        return observations, rewards.astype(np.float32), dones, infos

    def close(self) -> None:
        self.venv.close()

    def get_images(self) -> Sequence[np.ndarray | None]:
        frames = self.venv.render()  # each environment's, with render_mode="rgb_array"
        return [None] * self.num_envs if frames is None else [f for f in frames]  # type: ignore[misc]

    def get_attr(self, attr_name: str, indices: Any = None) -> list[Any]:  # noqa: ANN401
        return [getattr(env, attr_name) for env in self._envs(indices)]

    def set_attr(self, attr_name: str, value: Any, indices: Any = None) -> None:  # noqa: ANN401
        for env in self._envs(indices):
            setattr(env, attr_name, value)

    def env_method(
        self,
        method_name: str,
        *method_args: Any,
        indices: Any = None,  # noqa: ANN401
        **method_kwargs: Any,
    ) -> list[Any]:
        return [
            getattr(env, method_name)(*method_args, **method_kwargs) for env in self._envs(indices)
        ]

    def env_is_wrapped(self, wrapper_class: type, indices: Any = None) -> list[bool]:  # noqa: ANN401
        return [is_wrapped(env, wrapper_class) for env in self._envs(indices)]

    def _envs(self, indices: Any) -> list[Any]:  # noqa: ANN401 - SB3's VecEnvIndices
        """The sub-environments ``indices`` names (as `DummyVecEnv` reads them)."""
        envs = getattr(self.venv.unwrapped, "envs")  # noqa: B009 - not on every VectorEnv
        return [envs[i] for i in self._get_indices(indices)]
