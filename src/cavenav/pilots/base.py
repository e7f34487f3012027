"""The pilot contract: observations in, one decision out.

A pilot sees only `Observation`s and its own history, never the mesh or the pose: a
pilot that peeks at the geometry would make every comparison dishonest.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

from cavenav.core.types import Decision, Observation

__all__ = ["Pilot"]


@runtime_checkable
class Pilot(Protocol):
    """Anything that turns observations into decisions.

    Attributes:
        name: short identifier written to run folders and tables.
    """

    name: str

    def reset(self) -> None:
        """Forget the history of a previous episode."""

    def decide(self, observation: Observation) -> Decision:
        """Return the next action for ``observation``.

        Raises:
            PilotFailure: when no valid action can be produced; the episode then ends
                as ``pilot_failure``. A pilot never hides a failure behind a default move.
        """
        ...
