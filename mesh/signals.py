"""Ending a process cleanly on SIGINT or SIGTERM."""

from __future__ import annotations

import logging
import signal
import threading

from archery.mesh import instances

__all__ = ["STOP_SLICE", "shutdown_on_signals", "wait_for_stop"]

log = logging.getLogger("archery.node")

#: s: the main thread waits for a stop in slices this long (see `wait_for_stop`)
STOP_SLICE = 0.25


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


def wait_for_stop(stop: threading.Event) -> None:
    """Wait on the main thread until `stop` is set, in slices of `STOP_SLICE` s.

    The kernel may deliver SIGTERM to any thread that does not block it (the native libraries'
    threads among them); Python then runs its handler only once the main thread is back in the
    interpreter, which an untimed wait never is: it would wait forever, the signal noted and
    never handled."""
    while not stop.wait(STOP_SLICE):
        pass
