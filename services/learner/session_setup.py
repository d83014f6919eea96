"""How a learning session begins: a new one (learner built, checked against the controller's θ
box, header journaled) or one continued from its journal (learner restored, `resumed`
journaled). The runner is `services.learner.session.Session`; θ is in m.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import msgspec
import numpy as np

from archery.protocol.errors import BadRequest
from archery.protocol.journal_records import HeaderRecord, ResumedRecord
from archery.services.learner.algorithms.base import Learner, LearnerError
from archery.services.learner.algorithms.registry import make_learner, transferred_learner
from archery.services.learner.config import SessionConfig
from archery.services.learner.journal import JOURNAL_NAME, Journal, JournalError
from archery.services.learner.replay import rebuild_learner
from archery.services.learner.rig_protocol import Rig
from archery.services.learner.transfer import TransferSource

__all__ = ["new_session_id", "reopened_session", "started_session"]

log = logging.getLogger("archery.learner")


def new_session_id(algorithm: str, seed: int) -> str:
    """A new session id: UTC time, algorithm, seed and 4 random hex digits."""
    stamp = time.strftime("%Y%m%d-%H%M%S", time.gmtime())
    return f"{stamp}-{algorithm}-s{seed}-{np.random.default_rng().integers(16**4):04x}"


def started_session(
    config: SessionConfig,
    rig: Rig,
    runs: Path,
    session_id: str | None = None,
    source: TransferSource | None = None,
) -> tuple[Journal, Learner]:
    """The journal (`runs/<session>/journal.jsonl`, its header written) and learner of a new
    session; the learner seeded from `source`'s learned model (recorded as the header's
    `from`).

    Raises:
        BadRequest: bad learner options, bounds beyond the controller's box, θ0 outside.
        JournalError: `source`'s learner state cannot seed this learner
            (`services.learner.transfer.load_source` checks the rest first).
        RigError: the controller did not tell its box.
    """
    box = rig.theta_box()
    bounds = config.bounds or box
    if not (box.contains(bounds.low) and box.contains(bounds.high)):
        raise BadRequest(
            f"scenario.bounds low={bounds.low}, high={bounds.high} m exceed the controller's "
            f"θ box low={box.low}, high={box.high} m"
        )
    if not bounds.contains(config.theta0):
        raise BadRequest(bounds.outside("scenario.theta0", config.theta0))
    try:
        learner = make_learner(
            config.algorithm,
            np.array(config.theta0),
            rng=np.random.default_rng(config.seed),
            bounds=bounds,
            **config.learner_options(),
        )
    except LearnerError as exc:
        raise BadRequest(f"options for {config.algorithm!r}: {exc}") from None
    if source is not None:
        try:
            transferred_learner(learner, source.state)
        except LearnerError as exc:
            raise JournalError(f"--from {source.journal}: {exc}") from None
    session_id = session_id or new_session_id(config.algorithm, config.seed)
    header = HeaderRecord(
        session=session_id,
        algorithm=config.algorithm,
        seed=config.seed,
        rollouts=config.rollouts,
        options=learner.options(),
        config=config.to_dict() | {"bounds": msgspec.to_builtins(bounds)},
        controller_box=msgspec.to_builtins(box),
        learner_state=learner.state_dict(),
        from_=msgspec.UNSET if source is None else source.header(),
        rig=rig.setup(),
    )
    journal = Journal.create(runs / session_id, header)
    journal.state.forget_history()  # a running session keeps only what it needs next
    return journal, learner


def reopened_session(
    path: Path, session: str | None = None
) -> tuple[Journal, Learner, SessionConfig]:
    """The journal (`resumed` appended), restored learner and settings of the session
    journaled at `path` (a journal file or its directory).

    The learner is rebuilt from the latest checkpoint and the done rollouts after it
    (`services.learner.replay`), so asked again it proposes exactly what an uninterrupted
    session would have; checkpoints that did not restore are named in the `resumed` record.

    Raises:
        JournalError: unreadable journal, another session or version, an ended session, a
            journal changed by hand (a rollout the learner would not have proposed), or no
            room in the journal for the rollouts left.
    """
    path = Path(path)
    if path.is_dir():
        path = path / JOURNAL_NAME
    journal = Journal.resume(path, session)
    try:
        config = SessionConfig.from_header(journal.state.header)
        learner, skipped = rebuild_learner(journal.state)
        journal.room_for(config.rollouts - journal.state.n_done)
    except (KeyError, TypeError, ValueError) as exc:
        journal.close()
        if isinstance(exc, JournalError):
            raise
        raise JournalError(f"journal {path} cannot restore its session: {exc}") from None
    note: str | msgspec.UnsetType = msgspec.UNSET
    if skipped:
        note = "; ".join(skipped)
        log.warning("session %s: checkpoints skipped: %s", journal.state.session, note)
    journal.append(ResumedRecord(after=journal.state.last_index, skipped=note))
    return journal, learner, config
