"""A session's learner rebuilt from its journal: the latest checkpoint that restores, then the
done rollouts after it told again, each proposal checked against the θ the journal says ran.

The learner is deterministic given its state: restored from the state after rollout c and told
the (θ, r) of rollouts c+1, c+2, … in order (each after an `ask`, as the session did), it holds
the state an uninterrupted session had, and proposes exactly what that session would have. A
checkpoint that does not restore (corrupt, of another algorithm) is skipped for the one before
it, and named; a rollout whose θ came from the learner's proposal (not an abort's retry θ) but
differs from what the rebuilt learner proposes means the journal was changed after it was
written: refused, naming the first such rollout. θ and r in m.
"""

from __future__ import annotations

import numpy as np

from archery.protocol.text import cut, shown
from archery.services.learner.algorithms.base import Learner, LearnerError, with_history
from archery.services.learner.algorithms.registry import restore_learner
from archery.services.learner.journal import Checkpoint, JournalError, JournalState

__all__ = ["rebuild_learner"]


def rebuild_learner(state: JournalState) -> tuple[Learner, list[str]]:
    """The learner after every done rollout of `state`, and what was skipped (one line per
    checkpoint that did not restore, newest first).

    Raises:
        JournalError: no state restores (not even the header's), or a done rollout after the
            checkpoint used ran a θ the learner would not have proposed (named).
    """
    skipped: list[str] = []
    for checkpoint in reversed(state.checkpoints):
        try:
            learner = _restored(state, checkpoint)
        except (LearnerError, KeyError, TypeError, ValueError, ArithmeticError) as exc:
            skipped.append(
                f"{checkpoint.where} (after rollout {checkpoint.rollout}): {cut(str(exc))}"
            )
            continue
        _tell_after(learner, state, checkpoint)
        return learner, skipped
    raise JournalError(
        f"no learner state of session {state.session} restores: {'; '.join(skipped)}"
    )


def _restored(state: JournalState, checkpoint: Checkpoint) -> Learner:
    """The learner of `checkpoint`, its history taken from the done records before it."""
    before = state.done[: checkpoint.rollout]
    whole = with_history(dict(checkpoint.state), [d.theta for d in before], [d.r_m for d in before])
    return restore_learner(whole)


def _tell_after(learner: Learner, state: JournalState, checkpoint: Checkpoint) -> None:
    """Ask and tell `learner` every done rollout after `checkpoint`, checking each proposal."""
    aborted = {record.index for record in state.aborted}
    for done in state.done[checkpoint.rollout :]:
        proposal = learner.ask()  # the session asked before every attempt
        if done.index - 1 not in aborted and not np.array_equal(proposal, done.theta):
            raise JournalError(
                f"journal of session {state.session}: rollout {done.rollout} (attempt "
                f"{done.index}) ran θ {shown(done.theta)} m, but the learner rebuilt from "
                f"{checkpoint.where} proposes {shown(proposal.tolist())} m: the journal was "
                f"changed after it was written"
            )
        try:
            learner.tell(np.array(done.theta), np.array(done.r_m))
        except LearnerError as exc:
            where = f"done rollout {done.rollout} (attempt {done.index})"
            raise JournalError(f"journal of session {state.session}: {where}: {exc}") from None
