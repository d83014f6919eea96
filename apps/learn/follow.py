"""Following a session from outside the learner: its rollouts as they are published, its status
until it ends, and the one JSON line `archery learn` prints of it."""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from typing import Any

from apps.learn.client import learner_call
from mesh.node import Node
from protocol.errors import ArcheryError, RpcTimeout
from protocol.messages import Rollout
from services.learner.session import FINAL_STATES

__all__ = ["SessionLost", "follow", "result_line"]


class SessionLost(ArcheryError):
    """The learner vanished while following a session; `status` is its last status seen."""

    code = "service_lost"

    def __init__(self, message: str, status: dict[str, Any] | None = None) -> None:
        super().__init__(message)
        self.status = status


def follow(
    node: Node,
    session: str,
    rollouts: Any,
    on_rollout: Callable[[Rollout], None],
    *,
    poll: float = 0.5,
    gone_after: float = 5.0,
    on_status: Callable[[dict[str, Any]], None] | None = None,
) -> dict[str, Any]:
    """Hand each `Rollout` of `session` to `on_rollout` (and each status polled to `on_status`)
    until the session ends; its final status.

    Raises:
        SessionLost: the learner stopped answering for `gone_after` s.
    """
    silent_since: float | None = None
    last: dict[str, Any] | None = None
    while True:
        try:
            while True:
                message = rollouts.get(timeout=poll)
                if message.record.session == session:
                    on_rollout(message)
        except RpcTimeout:
            pass
        try:
            status = learner_call(node, "status", timeout=2.0)
            silent_since = None
        except RpcTimeout:
            now = time.monotonic()
            silent_since = silent_since or now
            if now - silent_since > gone_after:
                raise SessionLost(
                    f"the learner stopped answering during session {session}; restart it "
                    f"(`archery learner`) and continue the session with `archery learn --resume`",
                    last,
                ) from None
            continue
        if status.get("session") == session:
            last = status
            if on_status is not None:
                on_status(status)
        if status.get("session") == session and status.get("state") in FINAL_STATES:
            try:  # records published before the final status
                while True:
                    message = rollouts.get(timeout=0.2)
                    if message.record.session == session:
                        on_rollout(message)
            except RpcTimeout:
                pass
            return status


def result_line(status: dict[str, Any]) -> str:
    """The one JSON line `archery learn` prints."""
    keys = ("session", "rollouts", "hit_at", "final_distance_m", "journal")
    extra = ("status", "aborted", "report", "hit_frame")
    line = {k: status.get(k) for k in keys} | {k: status.get(k) for k in extra}
    line["status"] = status.get("state")
    return json.dumps(line)
