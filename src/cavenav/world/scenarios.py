"""Scenarios: a cave mesh with a start pose and an exit portal, by name or from a file.

The front door to the world's scenarios, and the path the rest of the tree and users'
scripts import them by. It holds nothing of its own; each concern has its module:

- `cavenav.world.scenario`: the `Scenario` and `ExitPortal` types, `Difficulty` and its
  knobs (each declared once), and the families by name (`SCENARIOS`,
  `procedural_scenario`): S1-S5 of SPEC section 6, then crawl, maze and long.
- `cavenav.world.families`: one builder per family, from a seed and the knobs.
- `cavenav.world.scenario_file`: the scenario TOML file (any user mesh, or a family at
  a chosen difficulty), `load_scenario` for a name or a path, and the start check.

Seeds in `HELD_OUT_SEEDS` are the test split.
"""

from __future__ import annotations

from cavenav.world.scenario import (
    HELD_OUT_SEEDS,
    KNOBS,
    SCENARIOS,
    Difficulty,
    ExitPortal,
    Scenario,
    difficulty_table,
    parse_difficulty,
    procedural_scenario,
)
from cavenav.world.scenario_file import (
    check_scenario,
    load_scenario,
    load_scenario_file,
    validate_start,
)

__all__ = [
    "HELD_OUT_SEEDS",
    "KNOBS",
    "SCENARIOS",
    "Difficulty",
    "ExitPortal",
    "Scenario",
    "check_scenario",
    "difficulty_table",
    "load_scenario",
    "load_scenario_file",
    "parse_difficulty",
    "procedural_scenario",
    "validate_start",
]
