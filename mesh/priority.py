"""A lower CPU priority for the observers: `archery dashboard` by default (on a busy machine
it lags behind rather than slows the session it watches), `archery record --nice N` on request
(a starved recorder makes the router drop latest-wins frames meant for it, so its receiving
threads keep their priority unless told; its writer thread, which decodes, compresses and writes
what they queue, runs at `WRITER_NICE` and in the SCHED_IDLE class on its own:
`lower_thread_priority`).

Linux keeps a niceness per thread: it is raised for every thread running (numpy's, say) and
before the Zenoh session starts, so the threads started later inherit it. Raising it needs no
privilege.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import threading
from pathlib import Path

from archery.mesh.cliargs import int_in

__all__ = [
    "OBSERVER_NICE",
    "WRITER_NICE",
    "add_nice_arg",
    "lower_priority",
    "lower_thread_priority",
]

OBSERVER_NICE = 10
WRITER_NICE = 10  # a recorder's writer thread, on top of its process's niceness


def add_nice_arg(parser: argparse.ArgumentParser, default: int) -> None:
    """Add --nice N (0 keeps the priority)."""
    parser.add_argument(
        "--nice",
        type=int_in(0, 19, "a niceness increment"),
        default=default,
        help=f"lower this process's CPU priority by N (0..19, default {default}; 0: "
        "unchanged), so a busy machine serves the session first",
    )


def lower_priority(increment: int) -> int:
    """Raise the niceness of this process's threads by `increment` (call before opening the
    Zenoh session); returns the calling thread's niceness now."""
    if increment == 0:
        return os.getpriority(os.PRIO_PROCESS, 0)
    tasks = Path("/proc/self/task")
    if not tasks.is_dir():  # not Linux: the process's niceness
        return os.nice(increment)
    me = threading.get_native_id()
    for task in tasks.iterdir():
        tid = int(task.name)
        with contextlib.suppress(ProcessLookupError):  # a thread that just ended
            os.setpriority(os.PRIO_PROCESS, tid, os.getpriority(os.PRIO_PROCESS, tid) + increment)
    return os.getpriority(os.PRIO_PROCESS, me)


def lower_thread_priority(
    increment: int, native_id: int | None = None, idle: bool = False
) -> int | None:
    """Raise the niceness of one thread only by `increment` (Linux keeps one per thread): the
    calling thread, or the thread of `native_id` (`threading.Thread.native_id`) of this
    process; with `idle`, also put it in Linux's SCHED_IDLE class, where it runs only on a core
    nothing else wants (a worker behind a queue: the queue holds what arrives meanwhile).
    Returns its niceness now, or None where that cannot be done (not Linux)."""
    tid = threading.get_native_id() if native_id is None else native_id
    try:
        os.setpriority(os.PRIO_PROCESS, tid, os.getpriority(os.PRIO_PROCESS, tid) + increment)
        if idle and hasattr(os, "SCHED_IDLE"):
            os.sched_setscheduler(tid, os.SCHED_IDLE, os.sched_param(0))
        return os.getpriority(os.PRIO_PROCESS, tid)
    except OSError:
        return None
