"""The random pilot: the floor every pilot must beat."""

from __future__ import annotations

from collections import Counter

import numpy as np

from cavenav.core.types import Observation
from cavenav.motion.actions import DEFAULT_SPACE, parse_action
from cavenav.pilots.base import Pilot
from cavenav.pilots.random_pilot import RandomPilot
from cavenav.sensors.depth import normalise_depth

BLANK = Observation(
    rgb=np.zeros((48, 64, 3), np.uint8),
    depth_m=np.full((48, 64), np.inf, np.float32),
    depth_png=normalise_depth(np.full((48, 64), np.inf, np.float32)),
    d_top=2.0,
    d_bottom=2.0,
    depth_range=(0.0, 20.0),
    hfov_deg=53.13,
)


def test_it_draws_every_admissible_value_and_nothing_else() -> None:
    pilot = RandomPilot(seed=1)
    assert isinstance(pilot, Pilot)
    decisions = [pilot.decide(BLANK) for _ in range(3000)]
    assert all(parse_action(d.action_text) == d.action for d in decisions)
    forwards = Counter(d.action.forward for d in decisions)
    yaws = Counter(d.action.yaw_deg for d in decisions)
    assert set(forwards) == {s * m for m in DEFAULT_SPACE.forward_m for s in (1, -1)}
    assert set(yaws) == {s * m for m in DEFAULT_SPACE.yaw_deg for s in (1, -1)}
    assert min(yaws.values()) > 3000 / 17 / 2  # uniform: each of 17 values near 176 times
    ups = [d.action.up for d in decisions]
    assert 0.25 < np.mean(np.array(ups) == 0) < 0.42  # none, ascend, descend alike
    assert min(abs(u) for u in ups if u) >= 0.1 and max(abs(u) for u in ups) <= 2.0


def test_reset_repeats_the_draws_and_seeds_differ() -> None:
    pilot = RandomPilot(seed=5)
    first = [pilot.decide(BLANK).action for _ in range(20)]
    pilot.reset()
    assert [pilot.decide(BLANK).action for _ in range(20)] == first
    assert [RandomPilot(seed=6).decide(BLANK).action for _ in range(20)] != first
