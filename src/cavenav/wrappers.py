"""Wrappers that stack features on `CaveNavEnv` instead of flags inside it.

`SafetyShield` stands between any pilot and the vehicle (see `cavenav.shield` for the
rules); it judges from the observations only, so it behaves the same in front of a real
vehicle.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np

from cavenav.env import CaveNavEnv
from cavenav.shield import Shield, ShieldConfig
from cavenav.types import Action

__all__ = ["SafetyShield"]


class SafetyShield(gym.Wrapper):
    """Replaces unsafe actions by the nearest safe one before the vehicle executes them.

    Each step's ``info["shield"]`` is None when the action passed, otherwise
    ``{"proposed", "replacement", "reason"}``; `interventions` counts them over the
    episode. Inadmissible actions pass through untouched: the environment holds and
    says why in ``info["invalid_action"]``.
    """

    def __init__(self, env: gym.Env, config: ShieldConfig | None = None):
        super().__init__(env)
        base = self._base
        self.shield = Shield(config or ShieldConfig(rules=base.rules, body=base.body), base.space)
        self.interventions = 0

    @property
    def _base(self) -> CaveNavEnv:
        base = self.env.unwrapped
        if not isinstance(base, CaveNavEnv):
            raise TypeError(f"SafetyShield wraps a CaveNavEnv, not {type(base).__name__}")
        return base

    def reset(self, **kwargs: Any) -> tuple[Any, dict[str, Any]]:
        obs, info = self.env.reset(**kwargs)
        self.shield.reset()
        self.interventions = 0
        self.shield.observe(self._base.observation)
        return obs, {**info, "shield": None}

    def step(self, action: str | np.ndarray | Action) -> tuple[Any, float, bool, bool, dict]:
        proposed, invalid = self._base.command(action)
        verdict = None if invalid else self.shield.judge(proposed)
        if verdict is not None:
            action = verdict.action  # already parsed: the environment only validates it
            self.interventions += verdict.intervened
        obs, reward, terminated, truncated, info = self.env.step(action)
        self.shield.observe(self._base.observation)
        info["shield"] = verdict.to_dict() if verdict is not None and verdict.intervened else None
        return obs, reward, terminated, truncated, info
