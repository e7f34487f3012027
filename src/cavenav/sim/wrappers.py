"""Wrappers that stack features on `CaveNavEnv` instead of flags inside it.

`SafetyShield` stands between any pilot and the vehicle (see `cavenav.safety.shield` for the
rules); it judges from the observations only, so it behaves the same in front of a real
vehicle. Both drive the environment through Gymnasium's API alone: `reset`, `step` and the
``info`` they return, and the settings any wrapper reads (`gym.Env.get_wrapper_attr`).
`StuckLimit` ends an episode that has stopped getting anywhere, whoever flies it.
"""

from __future__ import annotations

from typing import Any, SupportsFloat

import gymnasium as gym
import numpy as np

from cavenav.core.types import Action
from cavenav.safety.headway import GROUND_CELL_M, STUCK_PROGRESS_M, Headway
from cavenav.safety.shield import Shield, ShieldConfig
from cavenav.sim.env import CaveNavEnv, read_action

# GROUND_CELL_M and STUCK_PROGRESS_M, StuckLimit's measures of headway, lived here before
# `cavenav.safety.headway`; they stay importable from here.
__all__ = ["GROUND_CELL_M", "STUCK_PROGRESS_M", "SafetyShield", "StuckLimit"]


class SafetyShield(gym.Wrapper):
    """Replaces unsafe actions by the nearest safe one before the vehicle executes them.

    Each step's ``info["shield"]`` is None when the action passed, otherwise
    ``{"proposed", "replacement", "reason"}``; `interventions` counts them over the
    episode. Inadmissible actions pass through untouched: the environment holds and
    says why in ``info["invalid_action"]``. It wraps a `cavenav.sim.env.CaveNavEnv`, whose
    ``rules``, ``body``, ``space`` and ``action_format`` it reads, and whose
    ``info["observation"]`` it judges from.
    """

    def __init__(self, env: gym.Env, config: ShieldConfig | None = None):
        """Refuses here, not with a missing attribute later, an ``env`` that does not
        wrap the `CaveNavEnv` whose settings and ``info`` the shield reads.

        Raises:
            TypeError: ``env``'s innermost environment is not a `CaveNavEnv`.
        """
        if not isinstance(env.unwrapped, CaveNavEnv):
            raise TypeError(f"SafetyShield wraps a CaveNavEnv, not {type(env.unwrapped).__name__}")
        super().__init__(env)
        rules, body = env.get_wrapper_attr("rules"), env.get_wrapper_attr("body")
        self._space = env.get_wrapper_attr("space")
        self._action_format = env.get_wrapper_attr("action_format")
        self.shield = Shield(config or ShieldConfig(rules=rules, body=body), self._space)
        self.interventions = 0

    def reset(self, **kwargs: Any) -> tuple[Any, dict[str, Any]]:
        obs, info = self.env.reset(**kwargs)
        self.shield.reset()
        self.interventions = 0
        self.shield.observe(info["observation"])
        return obs, {**info, "shield": None}

    def step(
        self, action: str | np.ndarray | Action
    ) -> tuple[Any, SupportsFloat, bool, bool, dict]:
        proposed, invalid = read_action(action, self._space, self._action_format)
        verdict = None if invalid else self.shield.judge(proposed)
        if verdict is not None:
            action = verdict.action  # already parsed: the environment only validates it
            self.interventions += verdict.intervened
        obs, reward, terminated, truncated, info = self.env.step(action)
        self.shield.observe(info["observation"])
        info["shield"] = verdict.to_dict() if verdict is not None and verdict.intervened else None
        return obs, reward, terminated, truncated, info


class StuckLimit(gym.Wrapper):
    """Truncates an episode after ``steps`` steps in a row without headway.

    Headway is as `cavenav.safety.headway` defines it (the results judge a budget ending by the
    same count): new progress toward the exit, or ground never entered; turning on one
    spot, going to and fro, or circling over old ground makes none. The step that ends it
    has ``truncated`` and ``info["stuck"]`` true (false on every other step).
    """

    def __init__(self, env: gym.Env, steps: int):
        super().__init__(env)
        if steps < 1:
            raise ValueError(f"StuckLimit needs at least 1 step, got {steps}")
        self.steps = steps
        self._headway: Headway | None = None  # from the start of the episode
        self._without_headway = 0

    def reset(self, **kwargs: Any) -> tuple[Any, dict[str, Any]]:
        obs, info = self.env.reset(**kwargs)
        self._headway = Headway(info["progress_m"], _position(info["pose"]))
        self._without_headway = 0
        return obs, {**info, "stuck": False}

    def step(self, action: Any) -> tuple[Any, SupportsFloat, bool, bool, dict]:  # noqa: ANN401
        obs, reward, terminated, truncated, info = self.env.step(action)
        if self._headway is None:
            raise gym.error.ResetNeeded("StuckLimit: call reset before step")
        if self._headway.advance(info["progress_m"], _position(info["pose"])):
            self._without_headway = 0
        else:
            self._without_headway += 1
        info["stuck"] = not terminated and self._without_headway >= self.steps
        return obs, reward, terminated, truncated or info["stuck"], info


def _position(pose: dict[str, float]) -> tuple[float, float, float]:
    return pose["x"], pose["y"], pose["z"]
