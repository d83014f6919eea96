"""A lower CPU priority for the observers (`archery record`, `archery dashboard`): on a busy
machine they lag behind (their queues buffer) rather than slow the session they watch.

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

from protocol.cliargs import int_in

__all__ = ["OBSERVER_NICE", "add_nice_arg", "lower_priority"]

OBSERVER_NICE = 10


def add_nice_arg(parser: argparse.ArgumentParser) -> None:
    """Add --nice N (default `OBSERVER_NICE`; 0 keeps the priority)."""
    parser.add_argument(
        "--nice",
        type=int_in(0, 19, "a niceness increment"),
        default=OBSERVER_NICE,
        help=f"lower this process's CPU priority by N (0..19, default {OBSERVER_NICE}; 0: "
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
