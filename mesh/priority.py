"""A lower CPU priority for the observers: `archery dashboard` by default (on a busy machine
it lags behind rather than slows the session it watches), `archery record --nice N` on request
(a starved recorder makes the router drop latest-wins frames meant for it, so it keeps its
priority unless told).

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

from mesh.cliargs import int_in

__all__ = ["OBSERVER_NICE", "add_nice_arg", "lower_priority"]

OBSERVER_NICE = 10


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
