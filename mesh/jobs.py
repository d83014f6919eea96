"""One thread owns a resource; others hand it work as jobs: the queue between them.

A MuJoCo model and its renderer belong to the thread that made them (the robot's simulation
thread, the camera's capture thread). RPC handlers and Zenoh callbacks run on other threads,
so they *submit* a job (a callable) and wait on its future; the owning thread *drains* the
queue between its own steps, or *waits* on it when it has nothing else to do. Closing the
queue refuses new jobs and fails the pending ones with the caller's error, so no caller waits
for a thread that is gone.
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future
from concurrent.futures import TimeoutError as FutureTimeout
from typing import Any, TypeVar

__all__ = ["JobQueue"]

T = TypeVar("T")


class JobQueue:
    """Jobs for one owning thread.

    Args:
        unavailable: makes the exception that callers get when the owner cannot run their
            job (closed, or no answer in time); it receives a message saying which.
        owner: the owning thread's name, for those messages (e.g. "the simulation thread").
    """

    def __init__(self, unavailable: Callable[[str], Exception], owner: str) -> None:
        self._unavailable = unavailable
        self._owner = owner
        self._jobs: deque[tuple[Callable[[], Any], Future[Any]]] = deque()
        self._cond = threading.Condition()
        self._closed = ""
        self._woken = False  # a notify the owner has not waited for yet

    # -- any thread -------------------------------------------------------------------------
    def submit(self, func: Callable[[], T]) -> Future[T]:
        """Queue `func` for the owning thread; its future holds the result or the error."""
        future: Future[T] = Future()
        with self._cond:
            if self._closed:
                future.set_exception(self._unavailable(self._closed))
                return future
            self._jobs.append((func, future))
            self._cond.notify_all()
        return future

    def call(self, func: Callable[[], T], timeout: float) -> T:
        """Run `func` on the owning thread and return its result (or raise its error).

        Raises:
            the `unavailable` exception: the owner did not run it within `timeout` wall s, or
            the queue is closed.
        """
        future = self.submit(func)
        try:
            return future.result(timeout)
        except FutureTimeout:
            future.cancel()
            raise self._unavailable(f"{self._owner} did not answer within {timeout:g} s") from None

    def close(self, reason: str) -> None:
        """Refuse new jobs and fail the pending ones with `reason` (idempotent)."""
        with self._cond:
            if not self._closed:
                self._closed = reason
            jobs, self._jobs = list(self._jobs), deque()
            self._cond.notify_all()
        for _, future in jobs:
            if future.set_running_or_notify_cancel():
                future.set_exception(self._unavailable(reason))

    @property
    def closed(self) -> bool:
        """True once `close` was called."""
        return bool(self._closed)

    def notify(self) -> None:
        """Wake the owner (e.g. new sensor data arrived); if it is not waiting, its next `wait`
        returns at once, so no wake-up is lost."""
        with self._cond:
            self._woken = True
            self._cond.notify_all()

    # -- the owning thread ------------------------------------------------------------------
    def wait(self, timeout: float) -> bool:
        """Wait up to `timeout` s for a job (or `notify`/`close`); True if jobs are pending."""
        with self._cond:
            if not self._jobs and not self._closed and not self._woken and timeout > 0:
                self._cond.wait(timeout)
            self._woken = False
            return bool(self._jobs)

    def drain(self) -> bool:
        """Run every pending job in order; True if any ran. A job's exception goes to its
        caller, never to the owner."""
        ran = False
        while True:
            with self._cond:
                if not self._jobs:
                    return ran
                func, future = self._jobs.popleft()
            if not future.set_running_or_notify_cancel():
                continue  # its caller gave up waiting
            ran = True
            try:
                future.set_result(func())
            except BaseException as exc:
                future.set_exception(exc)
