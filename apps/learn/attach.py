"""`archery learn --attach SESSION`: follow a session the learner runs now, from where it is.

SESSION is a session id or its journal (the file or its directory). The client asks the learner
for its `status`; if that is SESSION, it prints where the session stands, then each rollout as
`archery learn` does, and the same final JSON line. A session that has ended already gets its
final line at once (from the learner's status, or from the journal when the learner runs another
session). Once attached, it follows the session across a restarted learner or router as
`archery learn` does (`apps.learn.follow`). The counts of every final line (rollouts, aborted,
hit_at, final distance) are the journal's (`journal_counts`), never the client's own count, so a
client that attached late, or that outlived its learner, reports the truth. Exit status as
`archery learn`: 0 finished, 1 failed, stopped, lost or not running, 2 for a bad SESSION.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from archery.apps.learn.client import learner_call
from archery.apps.learn.follow import SessionLost, follow, result_line
from archery.mesh.node import Node
from archery.mesh.subscription import Subscription
from archery.protocol.errors import ArcheryError, RpcError
from archery.protocol.exit_status import INTERRUPTED, for_error
from archery.protocol.journal_records import HeaderRecord
from archery.protocol.messages import Rollout
from archery.services.learner.journal import (
    JOURNAL_NAME,
    JournalError,
    JournalState,
    read_records,
)
from archery.services.learner.session import FINAL_STATES

__all__ = ["WaitingLines", "attach", "journal_counts", "session_of", "stderr_line"]

COUNTS = ("rollouts", "aborted", "hit_at", "final_distance_m")
WAIT_REPEAT = 5.0  # s between two lines of the same wait


def session_of(target: str) -> tuple[str, Path | None]:
    """(session id, journal path or None) of an `--attach` argument: a journal file, its
    directory, or a bare session id.

    Raises:
        JournalError: the path exists but is no journal.
    """
    path = Path(target)
    if path.is_dir():
        path = path / JOURNAL_NAME
    if not path.is_file():
        return target, None
    records, _ = read_records(path)
    if not records or not isinstance(records[0], HeaderRecord):
        raise JournalError(f"{path} does not start with a journal header")
    return records[0].session, path


def journal_counts(status: dict[str, Any]) -> dict[str, Any]:
    """`status` with its counts (rollouts, aborted, hit_at, final_distance_m) and `ended` read
    from its journal file when this process can read it; else as the learner gave them (which
    it also takes from the journal)."""
    path = status.get("journal")
    if not path:
        return status
    try:
        records, _ = read_records(Path(path))
        summary = JournalState.from_records(records, str(path)).summary()
    except JournalError:
        return status
    return status | {k: summary[k] for k in (*COUNTS, "ended")}


class WaitingLines:
    """Prints what a waiting session waits for (its status `cause`, e.g. "waiting for camera
    (lost 3.2 s ago)"): on entering the wait, when the services waited for change, and every
    `repeat` s; and a line when the wait is over. Pass it as `follow(..., on_status=...)`."""

    def __init__(self, out: Callable[[str], None], repeat: float = WAIT_REPEAT) -> None:
        self.out = out
        self.repeat = repeat
        self._waiting: list[str] | None = None
        self._shown = 0.0

    def __call__(self, status: dict[str, Any]) -> None:
        now = time.monotonic()
        if status.get("state") == "waiting":
            waiting = list(status.get("waiting_for") or [])
            if waiting != self._waiting or now - self._shown >= self.repeat:
                self.out(f"  {status.get('cause') or 'waiting for the services'}…")
                self._waiting, self._shown = waiting, now
        elif self._waiting is not None:
            self.out("  every service is alive again: the session goes on")
            self._waiting = None


def stderr_line(line: str) -> None:
    """Print one progress line on stderr."""
    print(line, file=sys.stderr, flush=True)


def attach(
    node: Node,
    rollouts: Subscription[Rollout],
    target: str,
    show: Callable[[Rollout], None],
    *,
    quiet: bool = False,
    gone_after: float = 5.0,
    resume_timeout: float = 60.0,
    note: Callable[[str], None] | None = None,
) -> int:
    """Follow the session `target` names (see the module docstring); prints the progress on
    stderr and the final JSON line on stdout; returns the exit status.

    Args:
        gone_after, resume_timeout, note: as `follow`'s (s, s, progress lines): once attached,
            a vanished learner or router is waited for `gone_after` s, and a learner restarted
            without the session is asked to resume it.
    """
    try:
        session, path = session_of(target)
    except JournalError as exc:
        stderr_line(f"archery learn: --attach {target}: {exc}")
        return 2
    try:
        status = learner_call(node, "status", timeout=10.0)
    except RpcError as exc:
        stderr_line(f"archery learn: --attach: the learner does not answer: {exc}")
        return for_error(exc.code)
    if status.get("session") != session:
        return _not_running(session, path, status, result_line)
    if not quiet:
        stderr_line(
            f"attached to session {session} ({status.get('state')}): {status.get('rollouts')} "
            f"of {status.get('budget')} rollouts done, {status.get('aborted')} attempts aborted; "
            f"journal {status.get('journal')}"
        )
    if status.get("state") not in FINAL_STATES:
        waiting = (lambda s: None) if quiet else WaitingLines(stderr_line)
        try:
            status = follow(
                node,
                session,
                rollouts,
                show,
                on_status=waiting,
                journal=status.get("journal"),
                resume=True,
                gone_after=gone_after,
                resume_timeout=resume_timeout,
                note=note,
            )
        except SessionLost as exc:
            stderr_line(f"archery learn: {exc}")
            print(result_line(journal_counts(exc.status or status) | {"state": "lost"}))
            return 1
        except RpcError as exc:  # the learner refused its status (e.g. access control)
            stderr_line(f"archery learn: {exc}")
            return for_error(exc.code)
        except KeyboardInterrupt:  # detaching leaves the session running
            stderr_line(f"archery learn: detached; session {session} goes on")
            print(result_line(journal_counts(status)))
            return INTERRUPTED
    print(result_line(journal_counts(status)))
    if status.get("state") != "finished":
        stderr_line(f"archery learn: session {status.get('state')}: {status.get('cause', '')}")
        return 1
    return 0


def _not_running(
    session: str,
    path: Path | None,
    status: dict[str, Any],
    result_line: Callable[[dict[str, Any]], str],
) -> int:
    """The answer when the learner's session is not `session`: the journal's final line if it
    ended, else how to continue it."""
    running = status.get("session")
    now = "is idle" if running is None else f"has session {running} ({status.get('state')})"
    if path is not None:
        try:
            state = JournalState.from_records(read_records(path)[0], str(path))
        except ArcheryError as exc:
            stderr_line(f"archery learn: --attach: {exc}")
            return 2
        if state.ended is not None:
            final = {"journal": str(path), "state": "finished"} | state.summary()
            print(result_line(final))
            return 0
        stderr_line(
            f"archery learn: session {session} is not running (the learner {now}); continue it "
            f"with `archery learn --resume {path}`"
        )
        return 1
    stderr_line(
        f"archery learn: session {session} is not running (the learner {now}); continue it with "
        f"`archery learn --resume JOURNAL` (its runs/{session}/{JOURNAL_NAME})"
    )
    return 1
