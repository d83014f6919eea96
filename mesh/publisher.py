"""Publishing typed messages on one key: sequence numbers and wall stamps, latest-wins or
lossless (events), matching status and a count of what was sent.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Generic, TypeVar, cast

import msgspec
import zenoh

from archery.protocol.codec import encode_into
from archery.protocol.messages import (
    Image,
    Message,
)

__all__ = ["Publisher"]

M = TypeVar("M", bound=Message)


class Publisher(Generic[M]):
    """Publishes messages of one type on one key; stamps `seq` and wall time `stamp`.

    `lossless=True` (events) blocks rather than drops under congestion; state streams drop the
    oldest data instead (latest wins).
    """

    def __init__(self, session: zenoh.Session, key: str, message_type: type[M], lossless: bool):
        self.key = key
        self.message_type = message_type
        self._seq = 0
        self._closed = False
        self._lock = threading.Lock()
        self._buffer = bytearray()  # reused: Zenoh copies the payload out during `put`
        self._pub = session.declare_publisher(
            key,
            congestion_control=(
                zenoh.CongestionControl.BLOCK if lossless else zenoh.CongestionControl.DROP
            ),
            reliability=zenoh.Reliability.RELIABLE,
            # a frame is megabytes: on every link it queues behind state, events and RPC
            priority=zenoh.Priority.DATA_LOW if message_type is Image else zenoh.Priority.DATA,
        )

    def put(self, message: M) -> M:
        """Stamp and publish `message`; returns the stamped copy that was sent."""
        with self._lock:
            stamped = self._stamped(message)
            encode_into(stamped, self._buffer)
            self._pub.put(self._buffer)
        return stamped

    def stamp(self, message: M) -> M:
        """Stamp and count `message` as `put` does, without sending it: for a latest-wins
        message that no subscriber matches (a camera frame only a `grab` wants), which would
        be encoded, copied into Zenoh and dropped there; or one handed on before it is sent
        (`send`)."""
        with self._lock:
            return self._stamped(message)

    def send(self, stamped: M) -> None:
        """Publish a message this publisher stamped (`stamp`) as it is: its seq and stamp are
        kept (a camera frame a waiting `grab` got first, sent to the subscribers after)."""
        with self._lock:
            encode_into(stamped, self._buffer)
            self._pub.put(self._buffer)

    def _stamped(self, message: M) -> M:
        if not isinstance(message, self.message_type):
            raise TypeError(
                f"{self.key} carries {self.message_type.__name__}, got {type(message).__name__}"
            )
        self._seq += 1
        return msgspec.structs.replace(message, seq=self._seq, stamp=time.time())

    @property
    def count(self) -> int:
        """Messages published so far (the last `seq`)."""
        return self._seq

    def matching(self) -> bool:
        """Whether at least one subscriber matches the key now."""
        # zenoh's stub says bool; the property is a MatchingStatus
        status = cast(zenoh.MatchingStatus, self._pub.matching_status)
        return bool(status.matching)

    def on_matching(self, callback: Callable[[bool], None]) -> Callable[[], None]:
        """Call `callback(matching)` whenever subscribers appear or all go; returns the function
        that stops the calls (keep a reference while it should run)."""
        listener = self._pub.declare_matching_listener(lambda s: callback(bool(s.matching)))
        return listener.undeclare

    def wait_matched(self, timeout: float) -> bool:
        """Wait until at least one subscriber matches the key; False after `timeout` s."""
        if self.matching():
            return True
        matched = threading.Event()
        stop = self.on_matching(lambda matching: matched.set() if matching else None)
        try:
            return self.matching() or matched.wait(timeout)
        finally:
            stop()

    def close(self) -> None:
        """Undeclare the publisher (idempotent)."""
        if not self._closed:
            self._closed = True
            self._pub.undeclare()
