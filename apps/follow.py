"""Following a mesh stream for a live viewer (the Foxglove bridge, the ROS 2 node): the newest
state on a thread of its own, or every event on arrival; each returns the function that stops it,
so a topic nobody watches costs the mesh nothing."""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from typing import Any

import zenoh

from mesh.subscription import Subscription

__all__ = ["Stop", "follow_events", "follow_latest"]

WAIT = 0.5  # s: how long a worker waits for a newer message before it looks at its stop flag

Stop = Callable[[], None]


def follow_latest(
    session: zenoh.Session,
    key: str,
    kind: type[Any],
    name: str,
    each: Callable[[Any], None],
    log: logging.Logger,
) -> Stop:
    """Follow a state stream on a thread of its own: `each(message)` with the newest message
    only, so a slow viewer skips states instead of queueing them; a failure of `each` is logged
    on `log` (naming `name`) and the stream goes on."""
    sub: Subscription[Any] = Subscription(session, key, kind, "latest", None)
    stop = threading.Event()

    def work() -> None:
        seq = -1
        while not stop.is_set():
            message = sub.latest()
            if message is None or message.seq == seq:
                try:
                    message = sub.wait_newer(WAIT, after_seq=seq)
                except Exception:  # nothing newer yet: look at the stop flag again
                    continue
            seq = message.seq
            try:
                each(message)
            except Exception:
                log.exception("%s: could not send message seq %d", name, seq)

    thread = threading.Thread(target=work, name=f"follow {name}", daemon=True)
    thread.start()

    def close() -> None:
        stop.set()
        sub.close()
        thread.join(5 * WAIT)

    return close


def follow_events(
    session: zenoh.Session, key: str, kind: type[Any], each: Callable[[Any], None]
) -> Stop:
    """Follow an event stream: `each(message)` with every message, on arrival (they are
    small)."""
    sub: Subscription[Any] = Subscription(session, key, kind, "fifo", each)
    return sub.close
