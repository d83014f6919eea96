"""The operator's line on the `archery learn` terminal: what a session waits for the operator to
do by hand (the learner's status `operator`, e.g. a real robot's nock), said once per request,
and, where the terminal's input is a terminal, Enter to confirm it (the learner's `confirm`)."""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from typing import Any, TextIO

from archery.mesh.node import Node
from archery.protocol.errors import ArcheryError
from archery.protocol.verbs.learner import CONFIRM, ConfirmArgs

__all__ = ["OperatorPrompt"]

log = logging.getLogger("archery.learn")
CONFIRM_TIMEOUT = 5.0  # s the learner has to answer a confirmation


class OperatorPrompt:
    """Pass it as `follow(..., on_status=...)`: prints each new request of the operator as one
    line (`out`) and, with `keys` (the terminal's input; None: no keyboard), confirms the
    request shown last when a line (Enter) is read there.

    Args:
        node: calls the learner's `confirm`.
        out: prints one line.
        keys: the input to read Enter from (`sys.stdin` when it is a terminal), or None.
    """

    def __init__(self, node: Node, out: Callable[[str], None], keys: TextIO | None) -> None:
        self.node, self.out, self.keys = node, out, keys
        self._lock = threading.Lock()
        self._shown = 0  # the last request shown
        self._pending: int | None = None  # the request Enter confirms
        self._reader: threading.Thread | None = None

    def __call__(self, status: dict[str, Any]) -> None:
        request = status.get("operator")
        with self._lock:
            if not request:
                self._pending = None
                return
            number = int(request["request"])
            self._pending = number
            if number == self._shown:
                return
            self._shown = number
        how = (
            "press Enter here when done"
            if self.keys is not None
            else "confirm on the dashboard or with "
            f"`archery rpc {self.node.keys.learner_rpc()} confirm`"
        )
        self.out(
            f"  operator, please: {request['message']} — {how} "
            f"(request {number}; the session waits {request['limit']:g} s)"
        )
        if self.keys is not None and self._reader is None:
            self._reader = threading.Thread(target=self._read, name="operator keys", daemon=True)
            self._reader.start()

    def _read(self) -> None:
        """Confirm the pending request on each line read, until the input ends."""
        assert self.keys is not None
        for _ in self.keys:
            with self._lock:
                pending, self._pending = self._pending, None
            if pending is None:
                continue
            try:
                done = self.node.call_typed(
                    self.node.keys.learner_rpc(),
                    CONFIRM,
                    ConfirmArgs(request=pending),
                    timeout=CONFIRM_TIMEOUT,
                )
            except ArcheryError as exc:
                self.out(f"  not confirmed: {exc}")
                continue
            self.out(f"  confirmed: {done.verb} (request {done.request})")
