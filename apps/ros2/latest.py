"""A KEEP_LAST queue of depth 1 per key, drained by a few threads at a bounded rate: the ROS 2
node's commands, one waiting command per part. A newer command replaces the waiting one (the
stale one is dropped and counted), so a flood costs one slot per part and ends with its last
command; each key is sent at most once per `interval`, and by one thread at a time: while a
key's send runs (a trajectory, until the robot replies at its end) the key's newest item waits
and goes once that send returns, and the other keys go on the other threads."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import Any

from archery.apps.ros2.endpoints import Counts

__all__ = ["LatestPerKey"]


class LatestPerKey:
    """The newest item of each key, handed to `send` on the threads that run `run()`.

    Args:
        send: called with each item taken (a failure is logged on `log`, the queue goes on).
        interval: the least time between two items of the same key (s).
        counts: where each replaced item is counted (`dropped stale`).
        log: where a failure of `send` is logged.
    """

    def __init__(
        self, send: Callable[[Any], None], interval: float, counts: Counts, log: logging.Logger
    ) -> None:
        self._send = send
        self._interval = interval
        self._counts = counts
        self._log = log
        self._waiting: dict[str, Any] = {}
        self._next: dict[str, float] = {}  # key -> monotonic time its next item may go
        self._sending: set[str] = set()  # keys whose item a thread is sending now
        self._closed = False
        self._cond = threading.Condition()

    def offer(self, key: str, item: Any) -> None:
        """Put `item` as `key`'s waiting item (replacing, and counting, a waiting one)."""
        with self._cond:
            if self._closed:
                return
            if key in self._waiting:
                self._counts.add("dropped stale")
            self._waiting[key] = item
            self._cond.notify_all()

    def waiting(self) -> int:
        """How many keys have an item waiting."""
        with self._cond:
            return len(self._waiting)

    def _take(self) -> tuple[str, Any] | None:
        """The next (key, item) whose key may go now (not being sent, its interval passed),
        waiting for one; None once closed."""
        with self._cond:
            while not self._closed:
                now = time.monotonic()
                free = [k for k in self._waiting if k not in self._sending]
                ready = [k for k in free if self._next.get(k, 0.0) <= now]
                if ready:
                    key = ready[0]
                    self._next[key] = now + self._interval
                    self._sending.add(key)
                    return key, self._waiting.pop(key)
                soonest = min((self._next[k] for k in free), default=None)
                self._cond.wait(None if soonest is None else max(0.0, soonest - now))
            return None

    def run(self) -> None:
        """Send the items as they may go, until `close()` (several threads may run it: a key
        is sent by one of them at a time)."""
        while True:
            taken = self._take()
            if taken is None:
                return
            key, item = taken
            try:
                self._send(item)
            except Exception:
                self._log.exception("a command failed")
            finally:
                with self._cond:
                    self._sending.discard(key)
                    self._cond.notify_all()

    def close(self) -> None:
        """Stop `run()`; what waits is dropped (a send under way ends on its own)."""
        with self._cond:
            self._closed = True
            self._waiting.clear()
            self._cond.notify_all()
