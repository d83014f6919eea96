"""`OperatorDesk`: what a session waits for the operator to do by hand on a real robot (put an
arrow on the string, ready the robot), one request at a time, until the operator confirms it
(the learner's `confirm`: the `archery learn` terminal's Enter, or the dashboard's button).

A request is said once, as one line on the learner's log, and shown in its `status`
(`operator`); it waits at most `limit` s, or until the session is stopped: then the session
stops, resumably (`OperatorAbsent`), its attempt left open for the resumed session to run
again."""

from __future__ import annotations

import logging
import threading
import time

from archery.protocol.errors import ArcheryError, BadRequest
from archery.protocol.verbs.learner import OperatorRequest

__all__ = ["OPERATOR_LIMIT", "OperatorAbsent", "OperatorDesk"]

log = logging.getLogger("archery.learner")

OPERATOR_LIMIT = 600.0  # s a session waits for the operator's confirmation by default
_SLICE = 0.25  # s between two looks at the session's stop while waiting


class OperatorAbsent(ArcheryError):
    """No confirmation came within the limit, or the session was stopped while waiting: the
    session stops (resumable), the attempt open."""

    code = "operator_absent"


class OperatorDesk:
    """The operator's requests of one learner, its sessions' one after another.

    Args:
        limit: s a request waits for its confirmation (`ask`).
        key: the learner's RPC key, named in the line that asks (ROBOT/learner/rpc:i).
    """

    def __init__(self, limit: float = OPERATOR_LIMIT, key: str = "ROBOT/learner/rpc:i") -> None:
        self.limit, self.key = limit, key
        self._cond = threading.Condition()
        self._count = 0
        self._pending: OperatorRequest | None = None
        self._confirmed = 0  # the last request confirmed

    @property
    def pending(self) -> OperatorRequest | None:
        """The request waiting now (None: none)."""
        with self._cond:
            return self._pending

    def ask(self, verb: str, message: str, stop: threading.Event) -> float:
        """Ask the operator to do `verb` by hand (`message`: what, as the robot said it) and wait
        for `confirm`; returns the wall s waited.

        Raises:
            OperatorAbsent: no confirmation within `limit` s, or `stop` set while waiting.
        """
        with self._cond:
            self._count += 1
            request = OperatorRequest(
                request=self._count, verb=verb, message=message, since=time.time(), limit=self.limit
            )
            self._pending = request
        log.warning(
            "operator, please: %s — then confirm (Enter on `archery learn`, the dashboard's "
            "Confirm, or `archery rpc %s confirm`); request %d, waiting up to %g s",
            message,
            self.key,
            request.request,
            self.limit,
        )
        start = time.monotonic()
        deadline = start + self.limit
        try:
            with self._cond:
                while self._confirmed < request.request:
                    left = deadline - time.monotonic()
                    if stop.is_set():
                        raise OperatorAbsent(f"stopped while waiting for the operator's {verb}")
                    if left <= 0:
                        raise OperatorAbsent(
                            f"the operator did not confirm the {verb} within {self.limit:g} s "
                            f"({message}); resume the session once the robot is ready"
                        )
                    self._cond.wait(min(_SLICE, left))
        finally:
            with self._cond:
                if self._pending is request:
                    self._pending = None
        waited = time.monotonic() - start
        log.info("operator confirmed the %s after %.1f s", verb, waited)
        return waited

    def confirm(self, request: int | None = None) -> OperatorRequest:
        """Confirm the waiting request (`request`: only if it is that one).

        Raises:
            BadRequest: nothing waits, or another request does.
        """
        with self._cond:
            pending = self._pending
            if pending is None:
                raise BadRequest("no request of the operator is waiting: nothing to confirm")
            if request is not None and request != pending.request:
                raise BadRequest(
                    f"request {request} is not the one waiting: request {pending.request} "
                    f"({pending.verb}: {pending.message})"
                )
            self._confirmed = pending.request
            self._pending = None  # no longer shown as waiting, even before the session wakes
            self._cond.notify_all()
            return pending
