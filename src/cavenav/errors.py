"""One error hierarchy for everything cavenav raises on purpose.

Each message names the bad value and, where there is one, the fix, so a command-line user
sees one precise line instead of a traceback from deep inside a library.
"""

from __future__ import annotations

__all__ = [
    "ActionError",
    "BackendAuthError",
    "BackendError",
    "BackendTimeout",
    "BackendUnavailable",
    "CavenavError",
    "ConfigError",
    "DependencyError",
    "MeshError",
    "PilotFailure",
    "RateLimited",
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
    """The pilot could not produce a valid action; the episode ends as `pilot_failure`.

    Attributes:
        exchanges: the requests and replies of the failed step (plain JSON records, as
            in `Decision.exchanges`), kept for the record.
        usage: what the failed step cost (a `cavenav.types.Usage`), counted like any other.
    """

    def __init__(self, message: str, exchanges: tuple = (), usage: object | None = None):
        super().__init__(message)
        self.exchanges = exchanges
        self.usage = usage


class DependencyError(CavenavError, ImportError):
    """An optional dependency is missing; the message carries the install command."""


class BackendError(CavenavError):
    """A model backend failed after its bounded retries."""


class BackendAuthError(BackendError):
    """The endpoint refused the credentials (401/403) or no key was given."""


class BackendTimeout(BackendError):
    """The endpoint did not answer within the timeout."""


class RateLimited(BackendError):
    """The endpoint kept answering 429 (too many requests)."""


class BackendUnavailable(BackendError):
    """Connection refused, or the endpoint kept answering 408/409/5xx."""
