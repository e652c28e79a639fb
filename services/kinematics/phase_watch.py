"""What the tracker does with the kinematics service's contact phases (docs/estimation.md#contact-phases).

Two rules for a consumer of ``handkse/{rig}/kinematics/model`` that tracks the hand:

- the model predicts the hand only while the hand is in contact: a free hand moves no joint
  (:func:`predicts_hand`);
- a body model built on the open, reaching hand fits the grasping hand badly (its fingers
  closed around the handle), so the tracker starts a new hand body when a contact phase begins
  (:class:`ContactPhaseWatch`). The kinematics service then restarts that phase's estimate on
  the new body frame (a new ``HandBody.body_epoch``; docs/protocol.md#contact-phases).

The in-process evaluation (:mod:`services.evaluation.pipeline`) and the tracker service apply the
same two rules through this module.
"""

from __future__ import annotations

from services.common.protocol import KinematicModel


def predicts_hand(model: KinematicModel | None) -> bool:
    """Whether ``model`` should drive the tracker's kinematic motion model now: not while the
    hand is free (a model from a producer that does not segment, ``phase`` None, always)."""
    return model is not None and model.phase != "free"


class ContactPhaseWatch:
    """Tells, model by model, when a new contact phase began (the tracker then starts a new
    hand body)."""

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        """Forget the phases seen (a new demonstration)."""
        self._current: tuple[int, int] | None = None
        self._first_ns: int | None = None

    def new_contact(self, model: KinematicModel) -> bool:
        """True for the first model of each contact phase (identified by its ``segment`` and
        ``segment_start_ns``), False otherwise, for models without contact phases, and for a
        phase that began with the stream (no later than the first model seen: the hand body was
        built on that grasp)."""
        if self._first_ns is None:
            self._first_ns = model.stamp_ns
        if model.phase != "contact" or model.segment_start_ns is None:
            return False
        if model.segment_start_ns <= self._first_ns:
            self._current = (model.segment, model.segment_start_ns)
            return False
        phase = (model.segment, model.segment_start_ns)
        if phase == self._current:
            return False
        self._current = phase
        return True


__all__ = ["ContactPhaseWatch", "predicts_hand"]
