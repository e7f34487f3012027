"""The random pilot: uniform draws from the admissible sets, the floor every pilot must beat.

It looks at nothing. Each component is drawn on its own: df, dr and dpsi uniformly from
their signed admissible values (0 included), dz as none, ascend or descend with equal
chance and, when moving, a magnitude uniform over the vertical range to the centimetre.
Seeded, and re-seeded by `reset`, so an episode's draws repeat exactly; under the safety
shield it is the shield's hardest client.
"""

from __future__ import annotations

import numpy as np

from cavenav.core.types import Action, Decision, Observation
from cavenav.motion.actions import DEFAULT_SPACE, ActionSpace, format_action

__all__ = ["RandomPilot"]


class RandomPilot:
    """Draws every action uniformly from the admissible sets."""

    name = "random"

    def __init__(self, seed: int = 0, space: ActionSpace = DEFAULT_SPACE):
        self.seed = seed
        self.space = space
        self._rng = np.random.default_rng(seed)
        self._draws = 0

    def reset(self) -> None:
        self._rng = np.random.default_rng(self.seed)
        self._draws = 0

    def _signed(self, magnitudes: tuple[float, ...]) -> float:
        values = sorted({s * m for m in magnitudes for s in (1.0, -1.0)})
        return float(values[self._rng.integers(len(values))]) + 0.0

    def decide(self, observation: Observation) -> Decision:
        lo, hi = self.space.vertical_range_m
        direction = int(self._rng.integers(3)) - 1  # descend, none, ascend
        up = direction * round(float(self._rng.uniform(lo, hi)), 2) + 0.0
        action = self.space.validate(
            Action(
                forward=self._signed(self.space.forward_m),
                right=self._signed(self.space.lateral_m),
                up=up,
                yaw_deg=self._signed(self.space.yaw_deg),
            )
        )
        self._draws += 1
        text = format_action(action)
        why = f"uniform random draw {self._draws} (seed {self.seed}); nothing was observed"
        return Decision(action=action, action_text=text, justification=why, raw=why)
