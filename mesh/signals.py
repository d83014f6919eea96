"""Ending a process cleanly on SIGINT or SIGTERM."""

from __future__ import annotations

import logging
import signal
import threading

from archery.mesh import instances

__all__ = ["shutdown_on_signals"]

log = logging.getLogger("archery.node")


def shutdown_on_signals(stop: threading.Event | None = None) -> threading.Event:
    """An event set by SIGINT or SIGTERM from now on (`stop`, or a new one), so a service can
    end cleanly with exit status 0."""
    stop = threading.Event() if stop is None else stop
    instances.set_stop_event(stop)

    def handle(signum: int, frame: object) -> None:
        log.info("signal %d: shutting down", signum)
        stop.set()

    signal.signal(signal.SIGINT, handle)
    signal.signal(signal.SIGTERM, handle)
    return stop
