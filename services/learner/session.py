"""One learning session, rollout by rollout, journaled: the closed loop of DESIGN.md in order.

A rollout (attempt `index`): θ from the learner (or the retry θ an abort left) → journal
`proposed` → controller posture → robot nock and release → detector measure (a frame newer
than the landing) → `tell(θ, r)` → journal `done` with the learner's state. The services are
reached through a `Rig` (the mesh in `services.learner.rig`, fakes in tests), so this module
knows no Zenoh.

Aborts (journal `aborted`, the learner is not told; attempts are not counted as rollouts)
`service_lost`, `rpc_error`, `not_reached`, `wrong_replier` (a reply from a session that is not
the live instance of the service asked: never used as data), `no_target`, `no_arrow`…: what
follows each (re-run the same θ, wait for the services, back off after a miss, fail) is decided
by the pure policy of `services.learner.abort_policy`. After a `no_arrow` back-off, the back-off
θ is what the learner is told about; its own pending proposal is dropped. After `max_aborts`
aborts in a row (`service_lost` aside) the session fails with the last cause; it can be resumed.

A lost service (any of them: crashed, frozen past its lease, cut off) is waited for, within the
same session: before each attempt, and again right before the shot (no arrow is released while
a service that must see it is missing), the session checks that every service is alive; if not,
it waits, in state `waiting` with `cause` saying for what ("waiting for camera (lost 3.2 s
ago)"), logged every few seconds. The wait is bounded: `service_wait` s after the loss began (the
first `service_lost` abort or wait since the last done rollout) the session fails, resumably.
The ground-truth impact (the robot's event) is logged beside each rollout for plots only.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import msgspec
import numpy as np

from protocol.errors import ArcheryError, BadRequest
from protocol.journal_records import (
    AbortedRecord,
    DoneRecord,
    EndRecord,
    HeaderRecord,
    JournalRecord,
    ProposedRecord,
    ResumedRecord,
    StoppedRecord,
)
from protocol.verbs.learner import LearnerStatusReply
from services.learner.abort_policy import NO_ARROW, SERVICE_LOST, after_abort, streak_failure
from services.learner.algorithms.base import Bounds, Learner, LearnerError
from services.learner.algorithms.registry import (
    make_learner,
    restore_learner,
    transferred_learner,
)
from services.learner.config import SessionConfig
from services.learner.journal import JOURNAL_NAME, Journal, JournalError
from services.learner.report import caption_png
from services.learner.transfer import TransferSource

__all__ = [
    "FINAL_STATES",
    "Measurement",
    "PostureResult",
    "Rig",
    "RigError",
    "ServiceLost",
    "Session",
    "SessionFailed",
    "Shot",
    "new_session_id",
]

log = logging.getLogger("archery.learner")
WAIT_SLICE = 1.0  # s between looks at the services while waiting for them
WAIT_LOG_EVERY = 5.0  # s between the log lines of a wait
FINAL_STATES = ("finished", "stopped", "failed")  # a session's phases once `run` has returned


class RigError(ArcheryError):
    """A service replied with an error, or its reply made no sense."""

    code = "rpc_error"


class ServiceLost(RigError):
    """A service did not reply in time or is no longer alive; `service` names it."""

    code = "service_lost"

    def __init__(self, service: str, message: str) -> None:
        super().__init__(message)
        self.service = service


class SessionFailed(ArcheryError):
    """The session cannot go on (too many aborts, a service gone for good); resumable."""

    code = "session_failed"


@dataclass(frozen=True)
class PostureResult:
    """The controller's answer: reached in time, why not, the θ measured (m), timings (s)."""

    reached: bool
    reason: str
    theta_measured: list[float]
    timing: dict[str, float] = field(default_factory=dict)


@dataclass(frozen=True)
class Shot:
    """A released arrow, landed: the robot's shot number, landing sim time (s), the wall time
    (s since the epoch) just before the arrow was nocked (a frame captured later and rendered
    at or after the landing shows this arrow), and what the robot says for the log."""

    shot: int
    sim_time: float
    stamp: float
    outcome: str
    timing: dict[str, float] = field(default_factory=dict)


@dataclass(frozen=True)
class Measurement:
    """The detector's answer: status ok / no_target / no_arrow, r (m) when ok, the reply."""

    status: str
    r_m: list[float] | None
    detection: dict[str, Any]
    timing: dict[str, float] = field(default_factory=dict)


class Rig(Protocol):
    """The other services as one session sees them (every call may raise `RigError` or
    `ServiceLost`)."""

    services: tuple[str, ...]

    def missing(self) -> list[str]:
        """Services not alive now."""

    def lost_ago(self, service: str) -> float | None:
        """Seconds since `service` was seen going (None if it was not)."""

    def wait_services(self, timeout: float, stop: threading.Event) -> bool:
        """Wait until every service is alive (True) or `stop` is set (False).

        Raises ServiceLost when some are still missing after `timeout` s."""

    def theta_box(self) -> Bounds:
        """The controller's θ box (m)."""

    def reset(self, seed: int) -> None:
        """Robot to its home posture, shot noise reseeded."""

    def posture(self, theta: np.ndarray) -> PostureResult:
        """Move to the archery posture for θ (m) and wait until the motion is done."""

    def shoot(self) -> Shot:
        """Nock an arrow and release it; returns once it has landed."""

    def measure(self, shot: Shot) -> Measurement:
        """Detect target centre and arrow tip in a frame newer than the landing."""

    def truth(self, shot: Shot) -> list[float] | None:
        """The robot's ground-truth r (m) of the shot, for the log only (None if unknown)."""

    def hit_frame(self, shot: Shot, measurement: Measurement) -> bytes | None:
        """The measured frame of the shot with the detection drawn on it (PNG), if available."""


def new_session_id(algorithm: str, seed: int) -> str:
    """A new session id: UTC time, algorithm, seed and 4 random hex digits."""
    stamp = time.strftime("%Y%m%d-%H%M%S", time.gmtime())
    return f"{stamp}-{algorithm}-s{seed}-{np.random.default_rng().integers(16**4):04x}"


def _distance(r: list[float]) -> float:
    return float(np.hypot(r[0], r[1]))


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
        self.hit_frame_path: Path | None = None
        self._lock = threading.Lock()
        self._phase = "starting"
        self._cause = ""
        self._waiting: list[str] = []
        self._lost_since: float | None = None  # monotonic start of the loss being waited out

    # -- construction ---------------------------------------------------------------------------
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
        """A new session: learner built (and seeded from `source`'s learned model, recorded as
        the header's `from`), bounds checked against the controller's box, header journaled.

        Raises:
            BadRequest: bad learner options, bounds beyond the controller's box, θ0 outside.
            JournalError: `source`'s learner state cannot seed this learner
                (`services.learner.transfer.load_source` checks the rest first).
            RigError: the controller did not tell its box.
        """
        box = rig.theta_box()
        bounds = config.bounds or box
        if not (box.contains(np.array(bounds.low)) and box.contains(np.array(bounds.high))):
            raise BadRequest(
                f"scenario.bounds low={list(bounds.low)}, high={list(bounds.high)} m exceed the "
                f"controller's θ box low={list(box.low)}, high={list(box.high)} m"
            )
        if not bounds.contains(np.array(config.theta0)):
            raise BadRequest(
                f"scenario.theta0 {list(config.theta0)} m lies outside the θ box "
                f"low={list(bounds.low)}, high={list(bounds.high)} m"
            )
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
            config=config.to_dict() | {"bounds": bounds.to_dict()},
            controller_box=box.to_dict(),
            learner_state=learner.state_dict(),
            from_=msgspec.UNSET if source is None else source.header(),
        )
        journal = Journal.create(runs / session_id, header)
        return cls(journal, learner, config, rig, **kw)

    @classmethod
    def resume(cls, path: Path, rig: Rig, session: str | None = None, **kw: Any) -> Session:
        """Continue the session journaled at `path` (a journal file or its directory).

        The learner is restored from the last done rollout's state and asked again, so it
        proposes exactly what it proposed before; an attempt left open is re-run with its θ.

        Raises:
            JournalError: unreadable journal, another session or version, an ended session.
        """
        path = Path(path)
        if path.is_dir():
            path = path / JOURNAL_NAME
        journal = Journal.resume(path, session)
        try:
            config = SessionConfig.from_header(journal.state.header)
            learner = restore_learner(journal.state.learner_state)
        except (KeyError, TypeError, ValueError) as exc:
            journal.close()
            raise JournalError(f"journal {path} cannot restore its session: {exc}") from None
        journal.append(ResumedRecord(after=journal.state.last_index))
        return cls(journal, learner, config, rig, **kw)

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
            cause = self.waiting_note(waiting)
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

    def waiting_note(self, missing: list[str]) -> str:
        """What a wait is for: "waiting for camera (lost 3.2 s ago), robot"."""
        names = []
        for name in missing:
            ago = self.rig.lost_ago(name)
            names.append(name if ago is None else f"{name} (lost {ago:.1f} s ago)")
        return "waiting for " + ", ".join(names)

    def _set(self, phase: str, cause: str = "", waiting: list[str] | None = None) -> None:
        with self._lock:
            self._phase, self._cause, self._waiting = phase, cause, waiting or []

    # -- the loop -------------------------------------------------------------------------------
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

        Returns:
            `status()` at the end.
        """
        try:
            self._run(stop)
        except SessionFailed as exc:
            self._set("failed", exc.message)
            log.error("session %s failed: %s", self.session_id, exc.message)
            self._record(StoppedRecord(reason="failed", cause=exc.message))
        except JournalError as exc:
            self._set("failed", exc.message)
            log.error("session %s: journal failure: %s", self.session_id, exc.message)
        except RigError as exc:
            self._set("failed", exc.message)
            log.error("session %s failed to set up: %s", self.session_id, exc.message)
            self._record(StoppedRecord(reason="failed", cause=exc.message))
        except Exception as exc:  # a bug must not leave the session "running" forever
            log.exception("session %s failed", self.session_id)
            self._set("failed", f"internal error: {exc!r}")
        finally:
            self.journal.close()
        return self.status()

    def _run(self, stop: threading.Event) -> None:
        config, state = self.config, self.journal.state
        self._await_services(stop)
        if config.reset and state.last_index == 0 and not stop.is_set():
            # A new session starts from the home posture with the shot noise seeded; a resumed
            # one does not reset: a move the crashed learner left running may still be on.
            self._guard(lambda: self.rig.reset(config.seed), stop)
        while not stop.is_set():
            reason = self._finished()
            if reason is not None:
                self._record(EndRecord(reason=reason, summary=state.summary()))
                self._set("finished", reason)
                log.info("session %s finished: %s", self.session_id, reason)
                return
            self._await_services(stop)
            if stop.is_set():
                break
            last = state.aborted[-1] if state.aborted else None
            failure = streak_failure(state.aborts_in_row, config.max_aborts, last)
            if failure is not None:
                raise SessionFailed(failure)
            self._set("running")
            self._attempt(stop)
        self._record(StoppedRecord(reason="stop requested"))
        self._set("stopped", "stop requested")

    def _finished(self) -> str | None:
        state = self.journal.state
        if self.config.until_hit and state.hit_at() is not None:
            return "hit"
        if len(state.done) >= self.config.rollouts:
            return "budget"
        return None

    def _await_services(self, stop: threading.Event) -> None:
        """Wait until every service is alive or `stop` is set, showing what for; SessionFailed
        once the loss has lasted `service_wait` s."""
        missing = self.rig.missing()
        if self._lost_since is not None or missing:
            self._lost_since = self._lost_since or time.monotonic()
            if time.monotonic() - self._lost_since > self.service_wait:
                raise SessionFailed(self._lost_for_good(missing))
        if not missing:
            self._set("running")
            return
        logged = None
        while not stop.is_set():
            self._set("waiting", waiting=missing)
            now = time.monotonic()
            if logged is None or now - logged >= WAIT_LOG_EVERY:
                log.warning("session %s: %s", self.session_id, self.waiting_note(missing))
                logged = now
            assert self._lost_since is not None  # set above: services are missing
            remaining = self._lost_since + self.service_wait - now
            if remaining <= 0:
                raise SessionFailed(self._lost_for_good(missing))
            try:
                if self.rig.wait_services(min(WAIT_SLICE, remaining), stop):
                    log.info("session %s: every service is alive again", self.session_id)
                    break
            except ServiceLost:
                missing = self.rig.missing() or missing
        self._set("running")

    def _lost_for_good(self, missing: list[str]) -> str:
        what = ", ".join(missing) + " still not alive" if missing else "services kept failing"
        return (
            f"{what} {self.service_wait:g} s after a service was lost; restart them and resume "
            f"the session"
        )

    def _guard(self, call: Callable[[], Any], stop: threading.Event) -> Any:
        """Run a set-up call, waiting for the services and retrying once if one was lost."""
        try:
            return call()
        except ServiceLost:
            self._await_services(stop)
            return call()

    def _next_theta(self) -> np.ndarray:
        state = self.journal.state
        if state.open is not None:
            # Left open by a crash: the learner was never told; run the same θ again.
            self.learner.ask()  # keeps the generator where the first run left it
            return np.array(state.open.theta)
        proposal = self.learner.ask()
        return proposal if state.retry_theta is None else np.array(state.retry_theta)

    def _attempt(self, stop: threading.Event) -> None:
        state = self.journal.state
        start = time.perf_counter()
        theta = self._next_theta()
        asked = time.perf_counter()
        if state.open is None:
            index = state.last_index + 1
            self._record(ProposedRecord(index=index, theta=theta.tolist()))
        else:
            index = state.open.index
            log.info("re-running open attempt %d at θ %s", index, theta.tolist())
        timing = {"ask_s": asked - start, "journal_proposed_s": time.perf_counter() - asked}
        try:
            posture = self.rig.posture(theta)
            if not posture.reached:
                reason = f"posture not reached: {posture.reason}"
                self._abort(stop, index, theta, "not_reached", reason)
                return
            missing = self.rig.missing()
            if missing:  # nobody could measure (or release) the arrow: do not shoot
                cause = f"{', '.join(missing)}: not alive before the shot; no arrow released"
                self._abort(stop, index, theta, SERVICE_LOST, cause)
                return
            shot = self.rig.shoot()
            measurement = self.rig.measure(shot)
        except ServiceLost as exc:
            self._abort(stop, index, theta, exc.code, f"{exc.service}: {exc.message}")
            return
        except RigError as exc:
            self._abort(stop, index, theta, exc.code, exc.message)
            return
        truth = self.rig.truth(shot)
        if measurement.status == "no_arrow":
            self._abort(
                stop,
                index,
                theta,
                "no_arrow",
                f"the detector saw no arrow on the target (robot: {shot.outcome})",
                truth_r_m=truth,
                detection=measurement.detection,
            )
            return
        if measurement.status != "ok" or measurement.r_m is None:
            self._abort(
                stop,
                index,
                theta,
                measurement.status,
                f"the detector says {measurement.status} "
                f"{measurement.detection.get('reason', '')}".strip(),
                truth_r_m=truth,
                detection=measurement.detection,
            )
            return
        self._done(index, theta, posture, shot, measurement, truth, start, timing)

    def _abort(
        self,
        stop: threading.Event,
        index: int,
        theta: np.ndarray,
        code: str,
        cause: str,
        **extra: Any,
    ) -> None:
        """Journal the aborted attempt with the θ the policy picks for the next one, then fail
        or wait for the services as the policy says."""
        state = self.journal.state
        best = min(state.done, key=lambda d: d.distance_m) if state.done else None
        redraw = self.learner.redraw((self.config.seed, index)) if code == NO_ARROW else None
        decision = after_abort(
            code,
            theta,
            best_theta=None if best is None else best.theta,
            theta0=self.config.theta0,
            bounds=self.learner.bounds,
            redraw=redraw,
        )
        if code == NO_ARROW:
            cause += (
                "; next θ drawn afresh"
                if redraw is not None
                else "; next θ backs off halfway towards the best θ"
            )
        log.warning("attempt %d at θ %s aborted [%s]: %s", index, theta.tolist(), code, cause)
        if code == SERVICE_LOST and self._lost_since is None:
            self._lost_since = time.monotonic()
        self._record(
            AbortedRecord(
                index=index,
                theta=theta.tolist(),
                code=code,
                cause=cause,
                retry_theta=list(decision.retry_theta),
                **extra,
            )
        )
        if decision.failure is not None:
            raise SessionFailed(decision.failure)
        if decision.await_services:
            self._await_services(stop)

    def _done(
        self,
        index: int,
        theta: np.ndarray,
        posture: PostureResult,
        shot: Shot,
        measurement: Measurement,
        truth: list[float] | None,
        start: float,
        timing: dict[str, float],
    ) -> None:
        r = [float(x) for x in measurement.r_m or ()]
        told = time.perf_counter()
        big_return = self.learner.tell(theta, np.array(r))
        distance = _distance(r)
        hit = distance < self.config.hit_radius
        rollout = len(self.journal.state.done) + 1
        self._lost_since = None
        timing = timing | posture.timing | shot.timing | measurement.timing
        timing["learner_s"] = time.perf_counter() - told
        if hit:  # the frame of the latest hit, taken before the next nock takes the arrow
            before = time.perf_counter()
            true = "" if truth is None else f" (true {100 * _distance(truth):.1f} cm)"
            caption = [
                f"session {self.session_id}, rollout {rollout}: hit, |r| = "
                f"{100 * distance:.1f} cm{true}",
                "theta = (" + ", ".join(f"{100 * v:.2f}" for v in theta) + ") cm. Left: the "
                "camera frame, right: the pixels of the colour models; red cross: target "
                "centre, blue circle: arrow tip",
            ]
            self._save_hit_frame(shot, measurement, caption)
            timing["hit_frame_s"] = time.perf_counter() - before
        before = time.perf_counter()
        timing["rollout_s"] = before - start
        record = DoneRecord(
            index=index,
            rollout=rollout,
            theta=theta.tolist(),
            theta_measured=posture.theta_measured,
            r_m=r,
            ret=float(big_return),
            distance_m=distance,
            hit=hit,
            shot=shot.shot,
            outcome=shot.outcome,
            truth_r_m=truth,
            truth_distance_m=None if truth is None else _distance(truth),
            detection=measurement.detection,
            timing=timing,
            learner_state=self.learner.state_dict(),
        )
        done = self.journal.append(record)
        timing = timing | {"journal_s": time.perf_counter() - before}
        # published with the journal's time
        self._published(msgspec.structs.replace(done, timing=timing))
        log.info(
            "rollout %d (attempt %d): θ %s → r %s, %.1f cm%s",
            rollout,
            index,
            np.round(theta, 4).tolist(),
            np.round(r, 3).tolist(),
            100 * distance,
            " HIT" if hit else "",
        )

    def _save_hit_frame(self, shot: Shot, measurement: Measurement, caption: list[str]) -> None:
        try:
            png = self.rig.hit_frame(shot, measurement)
        except RigError as exc:
            log.warning("no frame of the hit: %s", exc.message)
            return
        if png is None:
            return
        path = self.directory / "hit.png"
        try:
            path.write_bytes(caption_png(png, caption))
        except (OSError, ValueError) as exc:
            log.warning("could not save the hit frame: %s", exc)
            return
        self.hit_frame_path = path
