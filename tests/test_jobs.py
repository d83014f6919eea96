"""The job queue between a resource's owning thread and everyone else."""

from __future__ import annotations

import threading
import time

import pytest

from archery.mesh.jobs import JobQueue


class Unavailable(Exception):
    pass


def _owner(queue: JobQueue, stop: threading.Event) -> threading.Thread:
    """An owning thread that waits on the queue and drains it until `stop`."""

    def run() -> None:
        while not stop.is_set():
            if queue.wait(0.5):
                queue.drain()

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    return thread


def test_jobs_run_in_order_on_the_owning_thread() -> None:
    queue = JobQueue(Unavailable, "the owner")
    stop = threading.Event()
    thread = _owner(queue, stop)
    seen: list[tuple[int, str]] = []
    try:
        for i in range(20):
            queue.submit(lambda i=i: seen.append((i, threading.current_thread().name)))
        assert queue.call(lambda: 42, timeout=10) == 42
    finally:
        stop.set()
        queue.notify()
        thread.join(5)
    assert [i for i, _ in seen] == list(range(20))
    assert {name for _, name in seen} == {thread.name}


def test_a_job_error_reaches_its_caller_and_the_owner_goes_on() -> None:
    queue = JobQueue(Unavailable, "the owner")
    stop = threading.Event()
    thread = _owner(queue, stop)
    try:
        with pytest.raises(ZeroDivisionError):
            queue.call(lambda: 1 / 0, timeout=10)
        assert queue.call(lambda: "still serving", timeout=10) == "still serving"
    finally:
        stop.set()
        queue.notify()
        thread.join(5)


def test_no_owner_means_a_clear_timeout_and_the_job_never_runs_later() -> None:
    queue = JobQueue(Unavailable, "the capture thread")
    ran: list[int] = []
    with pytest.raises(Unavailable, match=r"the capture thread did not answer within 0\.05 s"):
        queue.call(lambda: ran.append(1), timeout=0.05)
    assert not queue.drain()  # the caller gave up: its job is skipped
    assert ran == []


def test_close_fails_pending_and_new_jobs() -> None:
    queue = JobQueue(Unavailable, "the owner")
    pending = queue.submit(lambda: 1)
    queue.close("shutting down")
    queue.close("again")  # idempotent: the first reason stays
    with pytest.raises(Unavailable, match="shutting down"):
        pending.result(1)
    with pytest.raises(Unavailable, match="shutting down"):
        queue.submit(lambda: 2).result(1)
    assert queue.closed and not queue.wait(0.0)


def test_a_notify_before_the_wait_is_not_lost() -> None:
    queue = JobQueue(Unavailable, "the owner")
    queue.notify()  # e.g. a frame arrived while the owner was busy
    started = time.monotonic()
    assert not queue.wait(5.0)
    assert time.monotonic() - started < 1.0
    started = time.monotonic()
    assert not queue.wait(0.2)  # consumed: the next wait waits
    assert time.monotonic() - started >= 0.15
