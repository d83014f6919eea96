"""The camera's newest frame and the requests waiting for a fresh one (thread-safe).

A request names what "fresh" means: rendered from a world state at or after a sim time (s),
and/or captured at or after a wall-clock stamp (s since the Unix epoch).
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass

from archery.protocol.errors import RpcTimeout
from archery.protocol.messages import Image

__all__ = ["FrameStore", "Freshness"]


@dataclass(frozen=True)
class Freshness:
    """What a waiting request accepts: `after_sim_time` (s), `after_stamp` (wall s); None = any."""

    after_sim_time: float | None = None
    after_stamp: float | None = None

    def accepts(self, image: Image, captured: float) -> bool:
        """True if `image`, whose capture started at wall time `captured`, is fresh enough."""
        if self.after_sim_time is not None and (
            image.sim_time is None or image.sim_time < self.after_sim_time
        ):
            return False
        return self.after_stamp is None or captured >= self.after_stamp


class FrameStore:
    """The newest published frame (with its capture start time) and who waits for one."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._latest: tuple[Image, float] | None = None
        self._waiting: list[Freshness] = []
        self.count = 0

    @property
    def latest(self) -> Image | None:
        """The newest frame, or None before the first."""
        latest = self._latest
        return None if latest is None else latest[0]

    def waiting(self) -> list[Freshness]:
        """The requests waiting now."""
        with self._cond:
            return list(self._waiting)

    def put(self, image: Image, captured: float) -> None:
        """Store a published frame whose capture started at wall time `captured` (s)."""
        with self._cond:
            self._latest = (image, captured)
            self.count += 1
            self._cond.notify_all()

    def wait(self, want: Freshness, timeout: float, on_wait: object = None) -> Image:
        """The newest frame if `want` accepts it, else the first such frame within `timeout` s.

        Raises:
            RpcTimeout: no acceptable frame in time; the message says what the newest was.
        """
        deadline = time.monotonic() + timeout
        with self._cond:
            self._waiting.append(want)
            try:
                if callable(on_wait):
                    on_wait()
                while self._latest is None or not want.accepts(*self._latest):
                    remaining = deadline - time.monotonic()
                    if remaining <= 0:
                        newest = self.latest
                        seen = (
                            "no frame yet"
                            if newest is None
                            else f"newest frame {newest.frame}: sim time {newest.sim_time}, "
                            f"stamp {newest.stamp:.3f}"
                        )
                        raise RpcTimeout(
                            f"no frame with sim time ≥ {want.after_sim_time} and capture ≥ "
                            f"{want.after_stamp} within {timeout:g} s ({seen})"
                        )
                    self._cond.wait(remaining)
                return self._latest[0]
            finally:
                self._waiting.remove(want)
