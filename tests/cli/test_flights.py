"""The acceptance flights: the geometric pilot through every shipped cave, no collision.

These are among the slowest tests (5-25 s each): whole episodes on the full sensor rig,
marked `slow` but for the short straight tube, which keeps one whole flight in a quick
`pytest -m "not slow"`.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from cavenav.episode.loop import run_episode
from cavenav.episode.settings import EpisodeConfig
from cavenav.pilots.geometric import GeometricPilot
from cavenav.world.scenarios import load_scenario

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"
SLOW = pytest.mark.slow
CAVES = [pytest.param(name, marks=SLOW) for name in ("S1", "S2", "S3", "S4", "S5")] + [
    pytest.param(str(EXAMPLES / "osrf_cave_straight.toml")),
    pytest.param(str(EXAMPLES / "osrf_cave_L.toml"), marks=SLOW),
    pytest.param(str(EXAMPLES / "osrf_cave_3way.toml"), marks=SLOW),
]


@pytest.mark.parametrize("cave", CAVES, ids=lambda c: Path(c).stem)
def test_the_geometric_pilot_reaches_the_exit_without_collision(cave: str) -> None:
    result = run_episode(load_scenario(cave, seed=0), GeometricPilot(), EpisodeConfig(plots=False))
    assert result.termination == "exit", result.summary
    assert result.summary["collisions"] == 0
    assert result.summary["steps"] <= 150
    assert result.summary["min_clearance_m"] > 0.5
