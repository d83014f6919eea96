"""A KEEP_LAST queue of depth 1 per key, drained on one thread at a bounded rate: the ROS 2
node's commands, one waiting command per part. A newer command replaces the waiting one (the
stale one is dropped and counted), so a flood costs one slot per part and ends with its last
command; each key is sent at most once per `interval`, so the robot's command rate is kept."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import Any

from apps.ros2.endpoints import Counts

__all__ = ["LatestPerKey"]


class LatestPerKey:
    """The newest item of each key, handed to `send` on the thread that runs `run()`.

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
            self._cond.notify()

    def waiting(self) -> int:
        """How many keys have an item waiting."""
        with self._cond:
            return len(self._waiting)

    def _take(self) -> Any | None:
        """The next item whose key may go now, waiting for one; None once closed."""
        with self._cond:
            while not self._closed:
                now = time.monotonic()
                ready = [k for k in self._waiting if self._next.get(k, 0.0) <= now]
                if ready:
                    key = ready[0]
                    self._next[key] = now + self._interval
                    return self._waiting.pop(key)
                soonest = min((self._next[k] for k in self._waiting), default=None)
                self._cond.wait(None if soonest is None else max(0.0, soonest - now))
            return None

    def run(self) -> None:
        """Send the items as they may go, until `close()`."""
        while True:
            item = self._take()
            if item is None:
                return
            try:
                self._send(item)
            except Exception:
                self._log.exception("a command failed")

    def close(self) -> None:
        """Stop `run()`; what waits is dropped."""
        with self._cond:
            self._closed = True
            self._waiting.clear()
            self._cond.notify_all()
