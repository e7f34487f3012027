"""Headway: whether the vehicle is still getting anywhere, defined once.

`cavenav.sim.wrappers.StuckLimit` ends an episode after a number of steps in a row without
headway (termination "stuck"), and `cavenav.evaluation.results.outcome` tells a budget
ending that was still making headway from one that was not by the same count, replayed
over the recorded steps: an episode is never ended for want of headway by one definition
and reported as making it by another.

A step makes headway when the best progress toward the exit grows by `STUCK_PROGRESS_M`
over the best counted before, or the vehicle enters a `GROUND_CELL_M` cube of the cave it
was never in: a side passage explored is headway; flying back over old ground, turning on
one spot or going to and fro is not.
"""

from __future__ import annotations

__all__ = ["GROUND_CELL_M", "STUCK_PROGRESS_M", "Headway"]

STUCK_PROGRESS_M = 0.5
GROUND_CELL_M = 2.0

_Position = tuple[float, float, float]


def _cell(position: _Position) -> tuple[int, int, int]:
    """The `GROUND_CELL_M` cube a position (metres, world frame) lies in."""
    x, y, z = (int(c // GROUND_CELL_M) for c in position)
    return x, y, z


class Headway:
    """The best progress counted as headway and the cubes entered, from a starting point.

    Args:
        progress_m: the progress toward the exit at the start, metres.
        position: where the vehicle starts, (x, y, z) metres.
    """

    def __init__(self, progress_m: float, position: _Position):
        self._best = progress_m
        self._ground = {_cell(position)}

    def advance(self, progress_m: float, position: _Position) -> bool:
        """Count a step that reached ``position`` at ``progress_m``: True if it made
        headway, which then becomes the mark to beat."""
        cell = _cell(position)
        if progress_m < self._best + STUCK_PROGRESS_M and cell in self._ground:
            return False
        self._best = max(self._best, progress_m)
        self._ground.add(cell)
        return True
