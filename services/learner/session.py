"""One learning session, rollout by rollout, journaled: the closed loop, in order.

A rollout (attempt `index`): θ from the learner (or the retry θ an abort left) → journal
`proposed` → controller posture → robot nock and release → detector measure (a frame newer
than the landing) → `tell(θ, r)` → journal `done` (ARCHITECTURE.md, 'The life of one
rollout'). Each step of an attempt is the pure `services.learner.rollout_step`; this module
runs them (`Session.run` says what that takes). The services are reached through a `Rig`
(`services.learner.rig_protocol`; the mesh in `services.learner.rig`, fakes in tests), so this
module knows no Zenoh.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import msgspec
import numpy as np

from archery.protocol.journal_records import (
    CHECKPOINT_EVERY,
    CheckpointRecord,
    EndRecord,
    JournalRecord,
    ProposedRecord,
    StoppedRecord,
)
from archery.protocol.text import shown
from archery.protocol.verbs.learner import LearnerStatusReply
from archery.services.learner.abort_policy import SERVICE_LOST, streak_failure
from archery.services.learner.algorithms.base import Learner
from archery.services.learner.config import SessionConfig
from archery.services.learner.errors import RigError, ServiceLost, SessionFailed
from archery.services.learner.hit_frame import LatestHit
from archery.services.learner.journal import Journal, JournalError
from archery.services.learner.operator_desk import OperatorAbsent
from archery.services.learner.rig_protocol import Rig
from archery.services.learner.rollout_step import (
    Attempt,
    Failed,
    Measured,
    aborted_record,
    done_record,
    next_attempt,
    shoot,
)
from archery.services.learner.service_wait import ServiceWait
from archery.services.learner.session_setup import reopened_session, started_session
from archery.services.learner.transfer import TransferSource

__all__ = ["FINAL_STATES", "Session"]

log = logging.getLogger("archery.learner")
FINAL_STATES = ("finished", "stopped", "failed")  # a session's phases once `run` has returned


class Session:
    """A session over a `Rig`, journaled in `directory/journal.jsonl`. Build with `create` or
    `resume`; `run` it on one thread; `status` may be read from any thread.

    Args:
        on_record: called with each journal record right after it is durable (e.g. to publish
            it on `learner/rollout:o`); a done record with its `timing` completed.
        service_wait: how long to wait for a vanished service before failing (s).
    """

    def __init__(
        self,
        journal: Journal,
        learner: Learner,
        config: SessionConfig,
        rig: Rig,
        *,
        on_record: Callable[[JournalRecord], None] | None = None,
        service_wait: float = 120.0,
    ) -> None:
        self.journal = journal
        self.learner = learner
        self.config = config
        self.rig = rig
        self.directory = journal.path.parent
        self.on_record = on_record
        self.service_wait = service_wait
        self.latest_hit = LatestHit(rig, self.directory, self.session_id)
        self.waits = ServiceWait(rig, service_wait, self._show_waiting, self.session_id)
        self._lock = threading.Lock()
        self._phase = "starting"
        self._cause = ""
        self._waiting: list[str] = []

    @classmethod
    def create(
        cls,
        config: SessionConfig,
        rig: Rig,
        runs: Path,
        session_id: str | None = None,
        *,
        source: TransferSource | None = None,
        **kw: Any,
    ) -> Session:
        """A new session (`services.learner.session_setup.started_session`: its errors)."""
        journal, learner = started_session(config, rig, runs, session_id, source)
        return cls(journal, learner, config, rig, **kw)

    @classmethod
    def resume(cls, path: Path, rig: Rig, session: str | None = None, **kw: Any) -> Session:
        """Continue the session journaled at `path` (a journal file or its directory); an
        attempt left open is re-run with its θ (`session_setup.reopened_session`: its errors).
        """
        journal, learner, config = reopened_session(path, session)
        resumed = cls(journal, learner, config, rig, **kw)
        resumed.latest_hit.resumed(journal.state)
        journal.state.forget_history()  # the learner is rebuilt: keep only what comes next
        return resumed

    # -- status ---------------------------------------------------------------------------------
    @property
    def session_id(self) -> str:
        """The session id."""
        return self.journal.state.session

    def status(self) -> LearnerStatusReply:
        """Phase (starting, waiting, running, finished, stopped, failed), counts, results: the
        learner's `status` reply (its `report` and `hit_frame` are the service's to add)."""
        with self._lock:
            phase, cause, waiting = self._phase, self._cause, list(self._waiting)
        if phase == "waiting":
            cause = self.waits.note(waiting)
        state = self.journal.state
        last = state.done[-1] if state.done else None
        return LearnerStatusReply(
            **state.summary(),
            state=phase,
            cause=cause,
            waiting_for=waiting,
            journal=str(self.journal.path),
            directory=str(self.directory),
            last_theta=None if last is None else last.theta,
            last_r_m=None if last is None else last.r_m,
        )

    def _set(self, phase: str, cause: str = "", waiting: list[str] | None = None) -> None:
        with self._lock:
            self._phase, self._cause, self._waiting = phase, cause, waiting or []

    def _show_waiting(self, missing: list[str]) -> None:
        if missing:
            self._set("waiting", waiting=missing)
        else:
            self._set("running")

    # -- the loop -------------------------------------------------------------------------------
    @property
    def hit_frame_path(self) -> Path | None:
        """`hit.png` once the latest hit's frame is saved (at the latest when `run` ends)."""
        return self.latest_hit.path

    def _record(self, record: JournalRecord) -> JournalRecord:
        """Journal `record`, then hand it to `on_record`."""
        record = self.journal.append(record)
        self._published(record)
        return record

    def _published(self, record: JournalRecord) -> None:
        if self.on_record is not None:
            try:
                self.on_record(record)
            except Exception:
                log.exception("publishing the %s record failed", record.kind)

    def run(self, stop: threading.Event) -> LearnerStatusReply:
        """Run rollouts until the hit (with until_hit), the budget, `stop`, or a failure.

        It journals and publishes each record, waits for lost services
        (`services.learner.service_wait`), keeps the session's phase and status, keeps the
        latest hit for its frame (`hit_frame`: saved once, when the session ends) and loops
        until the session ends. Every `CHECKPOINT_EVERY` done rollouts, and before the session
        stops or ends, it journals a `checkpoint` of the learner's state (without its history:
        a record's size never grows with the session).

        Aborts (journal `aborted`; the learner is not told, attempts are not rollouts) are
        followed as the pure policy of `services.learner.abort_policy` says; after `max_aborts`
        aborts in a row (`service_lost` aside) the session fails with the last cause,
        resumably. A lost service is waited for within the session, in phase `waiting`, for at
        most `service_wait` s. The ground-truth impact (the robot's event) is logged beside
        each rollout for plots only.

        Returns:
            `status()` at the end.
        """
        try:
            self._run(stop)
        except SessionFailed as exc:
            self._set("failed", exc.message)
            log.error("session %s failed: %s", self.session_id, exc.message)
            self._record_failure(exc.message)
        except OperatorAbsent as exc:  # its attempt stays open: the resumed session runs it
            self._set("stopped", exc.message)
            log.error("session %s stopped: %s", self.session_id, exc.message)
            try:
                self._record(StoppedRecord(reason="operator absent", cause=exc.message))
            except JournalError as journal:
                log.error("session %s: the stop was not journaled: %s", self.session_id, journal)
        except JournalError as exc:
            self._set("failed", exc.message)
            log.error("session %s: journal failure: %s", self.session_id, exc.message)
        except RigError as exc:
            self._set("failed", exc.message)
            log.error("session %s failed to set up: %s", self.session_id, exc.message)
            self._record_failure(exc.message)
        except Exception as exc:  # a bug must not leave the session "running" forever
            log.exception("session %s failed", self.session_id)
            self._set("failed", f"internal error: {shown(exc)}")
        finally:
            self.latest_hit.save()
            self.journal.close()
        return self.status()

    def _record_failure(self, cause: str) -> None:
        """Journal the stopped record of a failure; a journal that cannot take it (e.g. a full
        disk) leaves the session failed with its first cause (the error is logged)."""
        try:
            self._checkpoint()
            self._record(StoppedRecord(reason="failed", cause=cause))
        except JournalError as exc:
            log.error("session %s: the failure was not journaled: %s", self.session_id, exc.message)

    def _run(self, stop: threading.Event) -> None:
        config, state = self.config, self.journal.state
        self.waits.until_alive(stop)
        if config.reset and state.last_index == 0 and not stop.is_set():
            # A new session starts from the home posture with the shot noise seeded; a resumed
            # one does not reset: a move the crashed learner left running may still be on.
            self._guard(lambda: self.rig.reset(config.seed), stop)
        while not stop.is_set():
            reason = self._finished()
            if reason is not None:
                self._checkpoint()
                self._record(EndRecord(reason=reason, summary=state.summary()))
                self._set("finished", reason)
                log.info("session %s finished: %s", self.session_id, reason)
                return
            self.waits.until_alive(stop)
            if stop.is_set():
                break
            last = state.aborted[-1] if state.aborted else None
            failure = streak_failure(state.aborts_in_row, config.max_aborts, last)
            if failure is not None:
                raise SessionFailed(failure)
            self._set("running")
            self._attempt(stop)
        self._checkpoint()
        self._record(StoppedRecord(reason="stop requested"))
        self._set("stopped", "stop requested")

    def _checkpoint(self) -> None:
        """Journal the learner's state (without its history) unless the latest checkpoint
        already follows the last done rollout."""
        state = self.journal.state
        if state.checkpointed < state.n_done and state.open is None:
            self._record(
                CheckpointRecord(
                    rollout=state.n_done, learner_state=self.learner.checkpoint_state()
                )
            )

    def _finished(self) -> str | None:
        state = self.journal.state
        if self.config.until_hit and state.hit_at() is not None:
            return "hit"
        if state.n_done >= self.config.rollouts:
            return "budget"
        return None

    def _guard(self, call: Callable[[], Any], stop: threading.Event) -> Any:
        """Run a set-up call, waiting for the services and retrying once if one was lost."""
        try:
            return call()
        except ServiceLost:
            self.waits.until_alive(stop)
            return call()

    def _attempt(self, stop: threading.Event) -> None:
        """One attempt: proposed (journaled unless a crash left it open), shot, then aborted
        or done (journaled), as `rollout_step` builds them."""
        self.latest_hit.attempt()
        attempt = next_attempt(self.learner, self.journal.state)
        before = time.perf_counter()
        if attempt.rerun:
            log.info("re-running open attempt %d at θ %s", attempt.index, attempt.theta.tolist())
        else:
            self._record(ProposedRecord(index=attempt.index, theta=attempt.theta.tolist()))
        attempt = attempt.timed(journal_proposed_s=time.perf_counter() - before)
        outcome = shoot(self.rig, attempt.theta)
        if isinstance(outcome, Failed):
            self._abort(stop, attempt, outcome)
        else:
            self._done(attempt, outcome)

    def _abort(self, stop: threading.Event, attempt: Attempt, failed: Failed) -> None:
        """Journal the aborted attempt with the θ the policy picks for the next one, then fail
        or wait for the services as the policy says."""
        state = self.journal.state
        record, decision = aborted_record(self.learner, state, self.config, attempt, failed)
        theta = attempt.theta.tolist()
        log.warning(
            "attempt %d at θ %s aborted [%s]: %s", record.index, theta, record.code, record.cause
        )
        if record.code == SERVICE_LOST:
            self.waits.lost()
        self._record(record)
        if decision.failure is not None:
            raise SessionFailed(decision.failure)
        if decision.await_services:
            self.waits.until_alive(stop)

    def _done(self, attempt: Attempt, measured: Measured) -> None:
        """Journal the done rollout (a hit becomes the latest, whose frame is saved later) and
        publish it with the journal's time."""
        record = done_record(self.learner, self.journal.state, self.config, attempt, measured)
        self.waits.recovered()
        timing = dict(record.timing or {})
        if record.hit:
            self.latest_hit.hit(measured.shot, measured.measurement, record)
        before = time.perf_counter()
        timing["rollout_s"] = before - attempt.started
        done = self.journal.append(msgspec.structs.replace(record, timing=timing))
        timing = timing | {"journal_s": time.perf_counter() - before}
        self._published(msgspec.structs.replace(done, timing=timing))
        if record.rollout % CHECKPOINT_EVERY == 0:
            self._checkpoint()
        log.info(
            "rollout %d (attempt %d): θ %s → r %s, %.1f cm%s",
            record.rollout,
            record.index,
            np.round(attempt.theta, 4).tolist(),
            np.round(record.r_m, 3).tolist(),
            100 * record.distance_m,
            " HIT" if record.hit else "",
        )
