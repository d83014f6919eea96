"""Subscribing to typed messages on one key: latest-wins (state streams) or lossless FIFO
(events), freshness checks, malformed payloads counted and dropped.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable
from typing import Generic, TypeVar

import zenoh

from archery.mesh.memory import note_payload
from archery.protocol.codec import decode
from archery.protocol.errors import (
    DecodeError,
    RpcTimeout,
    StaleState,
)
from archery.protocol.messages import (
    Message,
)

__all__ = ["Subscription"]

M = TypeVar("M", bound=Message)
log = logging.getLogger("archery.node")


class Subscription(Generic[M]):
    """Receives one message type on one key.

    mode "latest": keeps only the newest message (`latest()`, `wait_newer()`); mode "fifo": keeps
    every message in arrival order (`get()`), never dropping one. An `Image` arrives as an
    `ImageView`: its pixels a read-only view of the received payload, not a copy. An optional
    callback runs on Zenoh's thread for each valid message, in order (keep it short); with a
    callback, a fifo subscription hands every message to it instead of queueing it for `get()`.
    Invalid payloads are counted in `dropped` and logged. An optional `admit` sees each raw
    payload first, on Zenoh's thread: a payload it refuses (False) is neither decoded nor
    counted here (`admit` keeps its own count), so a flood it screens out costs little.
    """

    def __init__(
        self,
        session: zenoh.Session,
        key: str,
        message_type: type[M],
        mode: str,
        callback: Callable[[M], None] | None,
        admit: Callable[[bytes], bool] | None = None,
    ) -> None:
        if mode not in ("latest", "fifo"):
            raise ValueError(f"subscription mode {mode!r} is not 'latest' or 'fifo'")
        self.key = key
        self.message_type = message_type
        self.mode = mode
        self.received = 0
        self.dropped = 0
        self.last_error = ""
        self._callback = callback
        self._admit = admit
        self._latest: M | None = None
        self._latest_time = 0.0
        self._cond = threading.Condition()
        self._closed = False  # closed: nothing newer will come
        self._queue: queue.Queue[M] = queue.Queue()
        self._sub: zenoh.Subscriber[None] | None = session.declare_subscriber(key, self._on_sample)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        payload = sample.payload.to_bytes()
        note_payload(len(payload))
        if self._admit is not None and not self._admit(payload):
            return
        try:
            message = decode(payload, self.message_type, view=True)
        except DecodeError as exc:
            self.dropped += 1
            self.last_error = str(exc)
            if self.dropped <= 10 or self.dropped % 100 == 0:
                log.warning("dropped message #%d on %s: %s", self.dropped, self.key, exc)
            return
        with self._cond:
            self.received += 1
            self._latest = message
            self._latest_time = time.monotonic()
            if self.mode == "fifo" and self._callback is None:
                self._queue.put(message)
            self._cond.notify_all()
        if self._callback is not None:
            try:
                self._callback(message)
            except Exception:
                log.exception("callback for %s failed on message seq %d", self.key, message.seq)

    def latest(self) -> M | None:
        """The newest valid message, or None if none arrived yet."""
        return self._latest

    def age(self) -> float:
        """Seconds since the newest valid message arrived (inf if none did)."""
        return time.monotonic() - self._latest_time if self._latest is not None else float("inf")

    def fresh(self, max_age: float, wait: float = 0.0) -> M:
        """The newest message if it arrived within the last `max_age` s, else the next one to
        arrive within `wait` s. The age is the arrival age on this host's monotonic clock (the
        sender's stamp is on another host's clock).

        Raises:
            StaleState: no message that fresh; names the key and the newest one's age.
        """
        with self._cond:
            old = self._latest
            if old is not None and time.monotonic() - self._latest_time <= max_age:
                return old
            deadline = time.monotonic() + wait
            while self._latest is old:  # identity: a restarted publisher's seq starts again
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise StaleState(self.key, self.age(), max_age)
                self._cond.wait(remaining)
            return self._latest  # type: ignore[return-value]  # not None: a message arrived

    def wait_newer(
        self,
        timeout: float,
        predicate: Callable[[M], bool] | None = None,
        after_seq: int | None = None,
        max_age: float | None = None,
    ) -> M:
        """Block until a message newer than `after_seq` (default: the current latest) arrives
        that satisfies `predicate`.

        With `max_age`, give up as soon as the stream is silent for longer than that (no message
        arrived for `max_age` s, counting from the call when none had arrived before).

        Raises:
            RpcTimeout: nothing suitable within `timeout` seconds; the message names the key.
            StaleState: the stream went silent for longer than `max_age` s.
        """
        start = time.monotonic()
        deadline = start + timeout
        with self._cond:
            if after_seq is None:
                after_seq = self._latest.seq if self._latest is not None else -1
            while True:
                msg = self._latest
                if (
                    msg is not None
                    and msg.seq > after_seq
                    and (predicate is None or predicate(msg))
                ):
                    return msg
                now = time.monotonic()
                remaining = deadline - now
                if remaining <= 0 or self._closed:
                    raise RpcTimeout(
                        f"no suitable message on {self.key} within {timeout:g} s "
                        f"(received {self.received}, dropped {self.dropped})"
                    )
                if max_age is not None:
                    heard = self._latest_time if msg is not None else start
                    if now - heard > max_age:
                        age = now - heard if msg is not None else float("inf")
                        raise StaleState(self.key, age, max_age)
                    remaining = min(remaining, heard + max_age - now + 1e-3)
                self._cond.wait(remaining)

    def get(self, timeout: float | None = None) -> M:
        """Next message in arrival order (fifo mode).

        Raises:
            RpcTimeout: nothing arrived within `timeout` seconds.
        """
        try:
            return self._queue.get(timeout=timeout)
        except queue.Empty:
            raise RpcTimeout(f"no message on {self.key} within {timeout:g} s") from None

    def close(self) -> None:
        """Undeclare the subscriber (idempotent); a `wait_newer` under way ends at once with
        `RpcTimeout` (nothing newer will come)."""
        if self._sub is not None:
            self._sub.undeclare()
            self._sub = None
        with self._cond:
            self._closed = True
            self._cond.notify_all()
