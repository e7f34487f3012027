"""A teacher flying in the shadow of the pilot that steers: DAgger's relabelling.

A student trained on its teacher's flights only ever saw the states its teacher led it
into; once it drifts off them it meets states nobody labelled. DAgger (Ross et al. 2011)
flies the student and asks the teacher, at every state the student reached, what it
would have done. `ShadowedPilot` does that during any flight: the student's decision
steers, the teacher decides on the very same observation, and its answer rides along in
the step's record (``steps.jsonl``: ``teacher``) for `cavenav dataset --labels teacher`.

The teacher is fed the actions actually executed: every observation carries the action
carried out before it (`Observation.previous_action`), which is what the geometric
pilot's memory moves by, whatever the teacher itself had chosen.
"""

from __future__ import annotations

from dataclasses import replace

from cavenav.core.types import Decision, Observation
from cavenav.pilots.base import Pilot

__all__ = ["ShadowedPilot"]


class ShadowedPilot:
    """``student`` steers; ``teacher`` answers the same observations alongside it."""

    def __init__(self, student: Pilot, teacher: Pilot):
        self.student, self.teacher = student, teacher
        self.name = student.name
        # The student's own draws (a random student's), recorded as the episode's pilot seed.
        self.seed: int | None = getattr(student, "seed", None)

    def reset(self) -> None:
        self.student.reset()
        self.teacher.reset()

    def decide(self, observation: Observation) -> Decision:
        decision = self.student.decide(observation)
        advice = self.teacher.decide(observation)
        label = {
            "pilot": self.teacher.name,
            "action": advice.action_text,
            "justification": advice.justification,
        }
        return replace(decision, extra={**decision.extra, "teacher": label})
