"""Following a session from outside the learner: its rollouts as they are published, its status
until it ends, and the JSON line `archery learn` prints of it.

Following outlives the faults the mesh lives through, every wait bounded by `gone_after` and
said the moment it begins (`apps.waits.waiting_for`); `follow` says what it waits for and how
it goes on.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from archery.apps.learn.client import learner_call, start_args
from archery.apps.waits import waiting_for
from archery.mesh.node import Node
from archery.protocol.errors import ArcheryError, RpcError, RpcTimeout
from archery.protocol.journal_records import StoppedRecord
from archery.protocol.messages import Rollout
from archery.services.learner.journal import JOURNAL_NAME, JournalError, JournalState, read_records
from archery.services.learner.session import FINAL_STATES

__all__ = ["SessionLost", "follow", "journal_status", "result_line"]

STATUS_TIMEOUT = 2.0  # s a status call may take
SILENT_NOTE = 2.0  # s of silence before a waiting line is shown


class SessionLost(ArcheryError):
    """Following a session could not go on (the learner or the router gone for too long, or the
    session no longer running); `status` is its last status seen. The message says how to go
    on."""

    code = "service_lost"

    def __init__(self, message: str, status: dict[str, Any] | None = None) -> None:
        super().__init__(message)
        self.status = status


def journal_status(journal: str | None) -> dict[str, Any] | None:
    """The final status a session's journal holds, read by this process: `finished` (its end
    record's reason as `cause`), `stopped` or `failed` (its last record a stopped record); None
    while the session is open, or when the journal cannot be read here."""
    if not journal:
        return None
    path = Path(journal)
    try:
        state = JournalState.from_records(read_records(path)[0], journal)
    except JournalError:
        return None
    last = state.records[-1]
    if state.ended is not None:
        state_, cause = "finished", state.ended.reason
    elif isinstance(last, StoppedRecord):
        state_ = "failed" if last.reason == "failed" else "stopped"
        cause = last.cause if isinstance(last.cause, str) else last.reason
    else:
        return None
    report, hit = path.parent / "report.png", path.parent / "hit.png"
    return state.summary() | {
        "state": state_,
        "cause": cause,
        "journal": journal,
        "directory": str(path.parent),
        "report": str(report) if report.is_file() else None,
        "hit_frame": str(hit) if hit.is_file() else None,
    }


def follow(
    node: Node,
    session: str,
    rollouts: Any,
    on_rollout: Callable[[Rollout], None],
    *,
    poll: float = 0.5,
    gone_after: float = 5.0,
    on_status: Callable[[dict[str, Any]], None] | None = None,
    journal: str | None = None,
    resume: bool = False,
    resume_timeout: float = 60.0,
    note: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """Hand each `Rollout` of `session` to `on_rollout` (and each status polled to `on_status`)
    until the session ends; its final status (the learner's, or its journal's when the
    learner no longer runs it and the journal says it ended).

    * the learner or the router not answering (a learner being restarted by `archery up`, a
      router outage) is waited for; on giving up, the message says which it was and how to go
      on: a vanished router or a silent learner may still run the session (`archery learn
      --attach`), a learner gone from the mesh does not (`archery learn --resume`);
    * a learner that answers without the session (restarted, it runs none): the session's
      journal, where this process can read it, says whether it had ended (its final status is
      then the journal's); else, with `resume`, the learner is asked once to `start {resume:
      JOURNAL, session: ID}` and the session is followed on.

    Each of these waits is one `note` line the moment it is seen to begin, with its limit,
    e.g. "  the learner does not answer; waiting up to 30 s for it (Ctrl-C to stop)".

    Args:
        poll: how long to wait for rollouts between two status calls (s).
        gone_after: how long the learner may stay silent (it or the router gone) before
            following gives up (s).
        journal: the session's journal path as the learner gave it (else taken from its
            status).
        resume: when the learner answers without the session (restarted: it runs none), ask
            it once to resume the session from its journal, and follow on.
        resume_timeout: how long that `start` may take (s; it waits for the services).
        note: called with a progress line (waiting for the learner, the session resumed).

    Raises:
        SessionLost: the learner stayed silent for `gone_after` s, or it no longer runs the
            session (another one, none and `resume` off, or it refused to resume it); the
            message says how to go on.
        RpcError: the learner refused the status call (e.g. access control).
    """
    say = note or (lambda line: None)
    silent_since: float | None = None
    noted = False  # the current silence has been shown
    last: dict[str, Any] | None = None
    asked = False  # asked the learner to resume the session since it last ran it
    while True:
        _drain(rollouts, session, on_rollout, poll)
        try:
            status = learner_call(node, "status", timeout=STATUS_TIMEOUT)
        except RpcTimeout:
            now = time.monotonic()
            if silent_since is None:
                silent_since = now
            silent = now - silent_since
            if silent > gone_after:
                raise SessionLost(_silence(node, session, journal, silent), last) from None
            if silent >= SILENT_NOTE and not noted:
                say(f"  the learner does not answer; {waiting_for('it', gone_after)}")
                noted = True
            continue
        if noted:
            say("  the learner answers again")
        silent_since, noted = None, False
        if status.get("session") == session:
            last, asked = status, False
            journal = status.get("journal") or journal
            if on_status is not None:
                on_status(status)
            if status.get("state") in FINAL_STATES:
                _drain(rollouts, session, on_rollout, 0.2)  # records published before it
                return status
            continue
        ended = journal_status(journal)
        if ended is not None:
            return ended
        running = status.get("session")
        if running is not None or not resume or asked or not journal:
            raise SessionLost(_not_running(session, journal, running, asked), last)
        asked = True
        say(
            f"  the learner runs no session (restarted?): asking it to resume session {session}; "
            f"{waiting_for('it', resume_timeout)}"
        )
        request = start_args({"resume": journal, "session": session})
        try:
            resumed = learner_call(node, "start", request, timeout=resume_timeout)
        except RpcTimeout:
            continue  # silent again: waited for above
        except RpcError as exc:
            if exc.code == "busy":
                continue  # someone else resumed it (then it is followed) or started another
            raise SessionLost(
                f"session {session} is not running and the learner refused to resume it: "
                f"{exc}; continue it with `archery learn --resume` {journal}",
                last,
            ) from None
        say(
            f"  session {session} resumed from its journal: {resumed.get('rollouts')} of "
            f"{resumed.get('budget')} rollouts done"
        )


def _drain(rollouts: Any, session: str, on_rollout: Callable[[Rollout], None], wait: float) -> None:
    """Hand on the rollouts of `session` that come within `wait` s of each other."""
    try:
        while True:
            message = rollouts.get(timeout=wait)
            if message.record.session == session:
                on_rollout(message)
    except RpcTimeout:
        pass


def _silence(node: Node, session: str, journal: str | None, silent: float) -> str:
    """Why the learner has not answered for `silent` s, and how to go on."""
    attach = f"follow it again with `archery learn --attach {session}`"
    if not list(node.session.info.routers_zid()):
        return (
            f"the router has been unreachable for {silent:.0f} s while following session "
            f"{session}; the session goes on if its learner still runs it: {attach} once the "
            f"router is back"
        )
    try:
        alive = "learner" in node.alive(timeout=1.0)
    except Exception:  # a failed query (the link going again) says nothing either way
        alive = True
    if alive:
        return (
            f"the learner is alive but has not answered for {silent:.0f} s during session "
            f"{session}; {attach}"
        )
    where = journal or f"JOURNAL (its runs/{session}/{JOURNAL_NAME})"
    return (
        f"the learner has been gone for {silent:.0f} s during session {session} (not "
        f"restarted); start it (`archery learner`, or `archery up`) and continue the session "
        f"with `archery learn --resume` {where}"
    )


def _not_running(session: str, journal: str | None, running: str | None, asked: bool) -> str:
    """The message when the learner answers without `session` (which then runs nowhere)."""
    where = journal or f"JOURNAL (its runs/{session}/{JOURNAL_NAME})"
    if running is not None:
        why, then = f"the learner runs session {running} now", " once that one ends"
    elif asked:
        why, then = "the restarted learner did not take it up when asked to resume it", ""
    else:
        why, then = "the learner runs no session (it was restarted)", ""
    return (
        f"session {session} is not running: {why}; continue it with `archery learn --resume` "
        f"{where}{then}"
    )


def result_line(status: dict[str, Any]) -> str:
    """The one JSON line `archery learn` prints."""
    keys = ("session", "rollouts", "hit_at", "final_distance_m", "journal")
    extra = ("status", "aborted", "report", "hit_frame", "video")
    line = {k: status.get(k) for k in keys} | {k: status.get(k) for k in extra}
    line["status"] = status.get("state")
    return json.dumps(line)
