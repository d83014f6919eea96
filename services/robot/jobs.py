"""The simulation thread's job queue: how other threads hand it work, and the error they get
when it cannot do it.

MuJoCo is not thread-safe, so one thread owns the world; every other thread (RPC workers, Zenoh
callbacks) queues a *job*, a closure with a future, which the thread runs between physics
chunks (`simthread`), never in the middle of one.
"""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import Future
from typing import TypeVar

from archery.mesh.jobs import JobQueue
from archery.protocol.errors import ArcheryError

__all__ = ["SHUTTING_DOWN", "SimJobs", "SimUnavailable"]

SHUTTING_DOWN = "the robot is shutting down"

T = TypeVar("T")


class SimUnavailable(ArcheryError):
    """The simulation thread is not running or did not answer in time."""

    code = "unavailable"


class SimJobs:
    """The jobs queued for the simulation thread.

    Args:
        timeout: how long (wall s) `call` waits for a job by default (the config's job_timeout).
    """

    def __init__(self, timeout: float) -> None:
        self.timeout = timeout
        self._queue = JobQueue(SimUnavailable, "the simulation thread")

    # -- any thread ------------------------------------------------------------------------
    def submit(self, func: Callable[[], T]) -> Future[T]:
        """Queue `func` to run on the simulation thread; its future holds the result."""
        return self._queue.submit(func)

    def call(self, func: Callable[[], T], timeout: float | None = None) -> T:
        """Run `func` on the simulation thread and return its result (or raise its error).

        Raises:
            SimUnavailable: the thread did not run it within `timeout` (default: `timeout`)
                wall seconds, or the queue is closed.
        """
        return self._queue.call(func, self.timeout if timeout is None else timeout)

    def close(self) -> None:
        """Refuse new jobs, fail the pending ones and wake the thread, which then ends."""
        self._queue.close(SHUTTING_DOWN)

    @property
    def closed(self) -> bool:
        """True once `close` was called."""
        return self._queue.closed

    # -- the simulation thread -------------------------------------------------------------
    def wait(self, timeout: float) -> bool:
        """Wait up to `timeout` wall s for a job (or `close`); True if jobs are pending."""
        return self._queue.wait(timeout)

    def drain(self) -> bool:
        """Run every pending job in order; True if any ran."""
        return self._queue.drain()
