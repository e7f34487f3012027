"""One error hierarchy for everything cavenav raises on purpose.

Each message names the bad value and, where there is one, the fix, so a command-line user
sees one precise line instead of a traceback from deep inside a library.
"""

from __future__ import annotations

from typing import Any

__all__ = [
    "ActionError",
    "BackendAuthError",
    "BackendError",
    "BackendTimeout",
    "BackendUnavailable",
    "CavenavError",
    "CavenavWarning",
    "ConfigError",
    "DependencyError",
    "MeshError",
    "PilotFailure",
    "RateLimited",
    "RecordError",
    "RecordingError",
    "ScenarioError",
    "VehicleError",
    "invalid_field",
]


def invalid_field(error: Any, where: str) -> ConfigError:
    """The first problem of a pydantic ``ValidationError`` as one line, "WHERE: field
    'a.b': message": settings files and settings objects report a bad value the same way."""
    first = error.errors()[0]
    name = ".".join(str(part) for part in first["loc"]) or "(top level)"
    return ConfigError(f"{where}: field '{name}': {first['msg']}")


class CavenavError(Exception):
    """Base class of every error cavenav raises deliberately.

    Attributes:
        exit_status: what the command line exits with (docs/guides/faults.md): 2 for
            bad input, found before anything was written.
    """

    exit_status = 2


class ConfigError(CavenavError):
    """A configuration or scenario file is malformed or holds an invalid value."""


class MeshError(CavenavError):
    """A cave mesh cannot be used: missing, unreadable, empty or degenerate."""


class ScenarioError(CavenavError):
    """A scenario is inconsistent: unknown name, start pose outside the passage, ..."""


class RecordError(ConfigError):
    """A record read back is damaged: summary.json, steps.jsonl or sweep.json that is not
    JSON, not an object, or holds a field of the wrong type (`cavenav.episode.records`).

    The message names the file and the field. Nothing was written (exit status 2).
    """


class RecordingError(CavenavError):
    """A record cannot be written (a read-only folder, a full disk): the run folder, or
    what `video`, `report` and `compare --json` write from it.

    Mid-episode, the record stops at the last whole step and the command exits 1.
    """

    exit_status = 1

    @classmethod
    def cannot_write(cls, where: object, error: BaseException, then: str = "") -> RecordingError:
        """The one line for every failed write: "cannot write WHERE: WHY" and ``then``.

        WHY is the system's reason for an `OSError` ("No space left on device"), else the
        error's type and text.
        """
        if isinstance(error, OSError):
            why: object = error.strerror or error
        else:
            why = f"{type(error).__name__}: {error}"
        return cls(f"cannot write {where}: {why}{then}")


class VehicleError(CavenavError):
    """A real or simulated vehicle cannot carry out the flight: no heartbeat, a stale link,
    a refused mode or arming, a segment beyond its cap. The bridge leaves the vehicle
    with neutral sticks first (`cavenav.vehicle.mavlink`)."""

    exit_status = 3


class ActionError(CavenavError, ValueError):
    """An action string cannot be parsed or lies outside the admissible magnitudes."""


class PilotFailure(CavenavError):
    """The pilot could not produce a valid action; the episode ends as `pilot_failure`.

    Attributes:
        exchanges: the requests and replies of the failed step (plain JSON records, as
            in `Decision.exchanges`), kept for the record.
        usage: what the failed step cost (a `cavenav.core.types.Usage`), counted like any other.
        cause: why, for the summary: "reply" (no usable reply after the re-queries),
            "backend" (the transport gave up: retries, deadline, a body that is no
            reply) or "auth" (the endpoint refused the key mid-run).
    """

    exit_status = 1  # the input was fine; the model (or its server) failed

    def __init__(
        self,
        message: str,
        exchanges: tuple = (),
        usage: object | None = None,
        *,
        cause: str = "reply",
    ):
        super().__init__(message)
        self.exchanges = exchanges
        self.usage = usage
        self.cause = cause


class DependencyError(CavenavError, ImportError):
    """An optional dependency is missing; the message carries the install command."""


class BackendError(CavenavError):
    """A model backend failed after its bounded retries.

    Attributes:
        errors: one line per failed attempt, oldest first, so that the run folder shows
            what the transport went through even though no reply came.
        reply: the start of the last body the endpoint sent (an error page), if any.
    """

    def __init__(self, message: str, *, errors: tuple[str, ...] = (), reply: str = ""):
        super().__init__(message)
        self.errors = errors
        self.reply = reply


class BackendAuthError(BackendError):
    """The endpoint refused the credentials (401/403) or no key was given."""


class BackendTimeout(BackendError):
    """The endpoint did not answer within the timeout, or the deadline left no time to
    try again."""


class RateLimited(BackendError):
    """The endpoint kept answering 429 (too many requests)."""


class BackendUnavailable(BackendError):
    """Connection refused, or the endpoint kept answering 408/409/5xx or a body that is
    no reply (a proxy's HTML page)."""


class CavenavWarning(UserWarning):
    """Something cavenav can go on with but a user should hear about: a mesh whose passage
    is implausibly large or small for the vehicle (likely drawn in another unit), ...

    Issued with `warnings.warn`; the command line prints each as one line, and a script
    can turn them into errors with ``warnings.simplefilter("error", CavenavWarning)``.
    """
