"""Wrappers that stack features on `CaveNavEnv` instead of flags inside it.

`SafetyShield` stands between any pilot and the vehicle (see `cavenav.shield` for the
rules); it judges from the observations only, so it behaves the same in front of a real
vehicle. Both drive the environment through Gymnasium's API alone: `reset`, `step` and the
``info`` they return, and the settings any wrapper reads (`gym.Env.get_wrapper_attr`).
`StuckLimit` ends an episode that has stopped getting anywhere, whoever flies it.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np

from cavenav.env import read_action
from cavenav.shield import Shield, ShieldConfig
from cavenav.types import Action

__all__ = ["SafetyShield", "StuckLimit"]

# Headway, for `StuckLimit`: the best progress toward the exit grows by this much, or the
# vehicle enters a cube of this side it never was in (a side passage explored is headway;
# flying back over old ground, or to and fro on one spot, is not).
STUCK_PROGRESS_M = 0.5
GROUND_CELL_M = 2.0


class SafetyShield(gym.Wrapper):
    """Replaces unsafe actions by the nearest safe one before the vehicle executes them.

    Each step's ``info["shield"]`` is None when the action passed, otherwise
    ``{"proposed", "replacement", "reason"}``; `interventions` counts them over the
    episode. Inadmissible actions pass through untouched: the environment holds and
    says why in ``info["invalid_action"]``. It wraps a `cavenav.env.CaveNavEnv`, whose
    ``rules``, ``body``, ``space`` and ``action_format`` it reads, and whose
    ``info["observation"]`` it judges from.
    """

    def __init__(self, env: gym.Env, config: ShieldConfig | None = None):
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

    def step(self, action: str | np.ndarray | Action) -> tuple[Any, float, bool, bool, dict]:
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

    Headway is `STUCK_PROGRESS_M` more progress toward the exit than the best counted
    before, or a `GROUND_CELL_M` cube of the cave entered for the first time; turning on
    one spot, going to and fro, or circling over old ground makes none. The step that ends it has
    ``truncated`` and ``info["stuck"]`` true (false on every other step).
    """

    def __init__(self, env: gym.Env, steps: int):
        super().__init__(env)
        if steps < 1:
            raise ValueError(f"StuckLimit needs at least 1 step, got {steps}")
        self.steps = steps
        self._best = 0.0  # the best progress counted as headway, metres
        self._ground: set[tuple[int, int, int]] = set()  # the cubes entered
        self._without_headway = 0

    def reset(self, **kwargs: Any) -> tuple[Any, dict[str, Any]]:
        obs, info = self.env.reset(**kwargs)
        self._best = info["progress_m"]
        self._ground = {_cell(info["pose"])}
        self._without_headway = 0
        return obs, {**info, "stuck": False}

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict]:  # noqa: ANN401
        obs, reward, terminated, truncated, info = self.env.step(action)
        cell = _cell(info["pose"])
        if info["progress_m"] >= self._best + STUCK_PROGRESS_M or cell not in self._ground:
            self._best = max(self._best, info["progress_m"])
            self._ground.add(cell)
            self._without_headway = 0
        else:
            self._without_headway += 1
        info["stuck"] = not terminated and self._without_headway >= self.steps
        return obs, reward, terminated, truncated or info["stuck"], info


def _cell(pose: dict[str, float]) -> tuple[int, int, int]:
    return (
        int(pose["x"] // GROUND_CELL_M),
        int(pose["y"] // GROUND_CELL_M),
        int(pose["z"] // GROUND_CELL_M),
    )
