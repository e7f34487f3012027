"""One error hierarchy for everything cavenav raises on purpose.

Each message names the bad value and, where there is one, the fix, so a command-line user
sees one precise line instead of a traceback from deep inside a library.
"""

from __future__ import annotations

__all__ = [
    "ActionError",
    "CavenavError",
    "ConfigError",
    "DependencyError",
    "MeshError",
    "PilotFailure",
    "ScenarioError",
]


class CavenavError(Exception):
    """Base class of every error cavenav raises deliberately."""


class ConfigError(CavenavError):
    """A configuration or scenario file is malformed or holds an invalid value."""


class MeshError(CavenavError):
    """A cave mesh cannot be used: missing, unreadable, empty or degenerate."""


class ScenarioError(CavenavError):
    """A scenario is inconsistent: unknown name, start pose outside the passage, ..."""


class ActionError(CavenavError, ValueError):
    """An action string cannot be parsed or lies outside the admissible magnitudes."""


class PilotFailure(CavenavError):
    """The pilot could not produce a valid action; the episode ends as `pilot_failure`."""


class DependencyError(CavenavError, ImportError):
    """An optional dependency is missing; the message carries the install command."""
