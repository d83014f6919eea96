"""The learner's RPC verbs on `ROBOT/learner/rpc:i` (`protocol.verbs.learner`): start, stop,
status, confirm (`operator_desk`); and the session thread they start. Each journal record of a
rollout also goes out on `ROBOT/learner/rollout:o`."""

from __future__ import annotations

import logging
import threading
from typing import Any

import msgspec
from msgspec import UnsetType

from archery.mesh.node import Node
from archery.mesh.publisher import Publisher
from archery.protocol.errors import ArcheryError, BadRequest
from archery.protocol.journal_records import (
    AbortedRecord,
    DoneRecord,
    JournalRecord,
    ProposedRecord,
)
from archery.protocol.messages import Rollout
from archery.protocol.text import shown
from archery.protocol.verbs import NoArgs, ServedVerbs
from archery.protocol.verbs.learner import (
    CONFIRM,
    LEARNER_VERBS,
    START,
    STATUS,
    STOP,
    ConfirmArgs,
    LearnerStatusReply,
    OperatorRequest,
    StartArgs,
)
from archery.services.learner.config import LearnerServiceConfig, SessionConfig
from archery.services.learner.operator_desk import OperatorDesk
from archery.services.learner.report import write_report
from archery.services.learner.rig import MeshRig
from archery.services.learner.runs_folder import journal_in_runs
from archery.services.learner.session import FINAL_STATES, Session
from archery.services.learner.transfer import load_source

__all__ = ["LearnerHandlers", "rollout_message"]

log = logging.getLogger("archery.learner")


def rollout_message(record: JournalRecord) -> Rollout | None:
    """The `Rollout` message of a proposed, done or aborted journal record (else None); a done
    record goes without its learner state."""
    if isinstance(record, DoneRecord):
        return Rollout(record=msgspec.structs.replace(record, learner_state=msgspec.UNSET))
    if isinstance(record, ProposedRecord | AbortedRecord):
        return Rollout(record=record)
    return None


class LearnerHandlers:
    """The learner's RPC verbs (one method each) and its one session thread."""

    def __init__(self, config: LearnerServiceConfig, node: Node) -> None:
        self.config = config
        self.node = node
        self.rig = MeshRig(node, config.rpc_timeout)
        # what a session asks of the operator
        self.desk = OperatorDesk(config.operator_wait, node.keys.learner_rpc())
        self.rig.desk = self.desk
        self.rollouts: Publisher[Rollout] = node.publisher(
            node.keys.learner_rollouts(), Rollout, lossless=True
        )
        self._lock = threading.Lock()
        self._session: Session | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._report: dict[str, str | None] = {}

    def verbs(self) -> ServedVerbs:
        """The verbs of `ROBOT/learner/rpc:i` (`protocol.verbs.learner`)."""
        return LEARNER_VERBS.bind(
            START.to(self.start),
            STOP.to(self.stop),
            STATUS.to(self.status),
            CONFIRM.to(self.confirm),
        )

    def _publish(self, record: JournalRecord) -> None:
        message = rollout_message(record)
        if message is not None:
            self.rollouts.put(message)

    def _check_services(self) -> None:
        missing = self.rig.missing()
        if missing and self.config.start_wait > 0:
            never = threading.Event()
            try:
                self.rig.wait_services(self.config.start_wait, never)
                missing = []
            except ArcheryError:
                missing = self.rig.missing()
        if missing:
            raise ArcheryError(
                f"services not alive: {', '.join(missing)} (robot {self.node.keys.robot!r}); "
                f"start them (`archery up` starts all) and retry",
                code="service_missing",
            )

    def start(self, request: StartArgs) -> LearnerStatusReply:
        """Start a new session (from another session's learned model with `from_journal`) or
        resume one; reply at once with the session's status (its id, journal path).

        `start {algo?, rollouts?, seed?, until_hit?, scenario?: {theta0, bounds, hit_radius,
        reset}, options?, from_journal?: SESSION}` starts a session (see
        `config.SessionConfig`); `start {resume: PATH, session?: ID}` continues the one
        journaled at PATH (a journal or its directory). Both paths must name journals inside
        the runs folder (a relative one is taken from there; `services.learner.runs_folder`):
        anything else is a bad request. Refused with code `service_missing` when the robot,
        camera, detector or controller is not alive, `busy` while a session runs (the message
        says how to follow it: `archery learn --attach ID`), `bad_request` or `bad_journal`
        for bad arguments; nothing journaled is touched then.
        """
        given = {
            f for f in request.__struct_fields__ if not isinstance(getattr(request, f), UnsetType)
        }
        with self._lock:
            if self._thread is not None and self._thread.is_alive():
                assert self._session is not None
                status = self._session.status()
                raise ArcheryError(
                    f"session {status.session} is running ({status.rollouts} of "
                    f"{status.budget} rollouts); follow it with `archery learn --attach "
                    f"{status.session}`, or stop it first (verb stop)",
                    code="busy",
                )
            kw: dict[str, Any] = {
                "on_record": self._publish,
                "service_wait": self.config.service_wait,
            }
            if isinstance(request.resume, str):
                unknown = sorted(given - {"resume", "session"})
                if unknown:
                    raise BadRequest(
                        f"start with resume takes only resume and session, not {shown(unknown[0])}"
                    )
                path = journal_in_runs(request.resume, self.config.runs, "resume")
                self._check_services()
                self._prepare_shot()
                wanted = request.session if isinstance(request.session, str) else None
                session = Session.resume(path, self.rig, wanted, **kw)
            else:
                config = SessionConfig.from_start(request)
                source = None
                if isinstance(request.from_journal, str):  # checked before any work
                    source = load_source(request.from_journal, config.algorithm, self.config.runs)
                self._check_services()
                self._prepare_shot()
                session = Session.create(config, self.rig, self.config.runs, source=source, **kw)
            self._session = session
            self._report = {}
            self._stop = threading.Event()
            self.rig.stop = self._stop  # a wait for the operator ends with the session
            self._thread = threading.Thread(
                target=self._run, args=(session, self._stop), name="session", daemon=True
            )
            self._thread.start()
            log.info("session %s started: journal %s", session.session_id, session.journal.path)
            return self._status_of(session)

    def _prepare_shot(self) -> None:
        """Follow the robot's shot (`MeshRig.follow_shot`: on a `--shot whole` robot every
        posture is the controller's whole movement)."""
        self.rig.follow_shot()

    def _run(self, session: Session, stop: threading.Event) -> None:
        status = session.run(stop)
        if self.config.report:
            try:
                report = write_report(session.journal.path)
                self._report = {
                    "report": str(report),
                    "hit_frame": None
                    if session.hit_frame_path is None
                    else str(session.hit_frame_path),
                }
            except Exception:
                log.exception("could not write the report of session %s", session.session_id)
        log.info("session %s: %s %s", session.session_id, status.state, status.cause)

    def _status_of(self, session: Session, **extra: Any) -> LearnerStatusReply:
        status = session.status()
        state = status.state
        if state in FINAL_STATES and self._thread is not None and self._thread.is_alive():
            state = "reporting"
        report = {"report": None, "hit_frame": None} | self._report
        operator = self.desk.pending
        return msgspec.structs.replace(status, state=state, operator=operator, **report, **extra)

    def stop(self, args: NoArgs) -> LearnerStatusReply:
        """Ask the running session to stop after its current rollout."""
        with self._lock:
            if self._session is None or self._thread is None or not self._thread.is_alive():
                if self._session is None:
                    return LearnerStatusReply(state="idle")
                return self._status_of(self._session)
            self._stop.set()
            return self._status_of(self._session, stopping=True)

    def status(self, args: NoArgs) -> LearnerStatusReply:
        """The running (or last) session's status (state starting, waiting, running,
        reporting, finished, stopped or failed), or {"state": "idle"}."""
        session = self._session
        return LearnerStatusReply(state="idle") if session is None else self._status_of(session)

    def confirm(self, args: ConfirmArgs) -> OperatorRequest:
        """The operator did what the running session waits for (`status`'s `operator`; with
        `request`, only if it is that one); the request confirmed.

        Raises:
            BadRequest: nothing waits, or another request does.
        """
        return self.desk.confirm(args.request)

    def close(self, timeout: float = 30.0) -> None:
        """Stop the running session (after its current rollout) and wait for it."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)
