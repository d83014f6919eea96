"""Following a mesh stream for a live viewer (the Foxglove bridge, the ROS 2 node): the newest
state on a thread of its own, or every event on arrival, each a subscription of the viewer's
`Node` (so `describe` lists it while it lasts); each returns the function that stops it and
unsubscribes, so a topic nobody watches costs the mesh nothing."""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from typing import Any

from archery.mesh.node import Node
from archery.mesh.subscription import Subscription
from archery.protocol.streams import Stream

__all__ = ["Stop", "follow_events", "follow_latest", "follow_stream"]

WAIT = 0.5  # s: how long a worker waits for a newer message before it looks at its stop flag

Stop = Callable[[], None]


def follow_latest(
    node: Node,
    key: str,
    kind: type[Any],
    name: str,
    each: Callable[[Any], None],
    log: logging.Logger,
) -> Stop:
    """Follow a state stream on a thread of its own: `each(message)` with the newest message
    only, so a slow viewer skips states instead of queueing them; a failure of `each` is logged
    on `log` (naming `name`) and the stream goes on."""
    sub: Subscription[Any] = node.subscribe(key, kind, mode="latest")
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
        node.unsubscribe(sub)
        thread.join(5 * WAIT)

    return close


def follow_events(node: Node, key: str, kind: type[Any], each: Callable[[Any], None]) -> Stop:
    """Follow an event stream: `each(message)` with every message, on arrival (they are
    small)."""
    sub: Subscription[Any] = node.subscribe(key, kind, mode="fifo", callback=each)
    return lambda: node.unsubscribe(sub)


def follow_stream(
    node: Node, stream: Stream, each: Callable[[Any], None], log: logging.Logger, name: str = ""
) -> Stop:
    """Follow a row of the declared stream table (`protocol/streams.py`) on `node`'s robot, as
    the row says (the newest state on a thread of its own, or every event), each of its keys
    (one per part for a part's port); `each(message)`; one function stops them all."""
    stops = [
        follow_latest(node, key, stream.message, name or key, each, log)
        if stream.follow == "latest"
        else follow_events(node, key, stream.message, each)
        for key in stream.keys(node.keys)
    ]

    def close() -> None:
        for stop in stops:
            stop()

    return close
