"""Giving memory back to the system after a burst of big payloads.

glibc keeps what a process frees in its heaps (one per thread that allocated it) for later use,
and a request refused with an exception may sit in a reference cycle (exception, traceback,
frame) until the cycle collector happens to run: after a flood of 10 MB messages, each copied
out of Zenoh, decoded and refused on one thread or another, a service kept hundreds of MB it no
longer used (the robot: 298 → 627 MB after 50 bad 10 MB requests, for good). `note_payload`
collects the cycles and trims the heaps after big payloads; where there is no glibc it does
nothing.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import gc
import threading
import time
from collections.abc import Callable

__all__ = ["BIG_PAYLOAD", "TRIM_DELAY", "TRIM_EVERY", "note_payload", "trims"]

BIG_PAYLOAD = 1024 * 1024  # bytes: freeing a payload this big is worth a trim
TRIM_DELAY = 0.5  # s without a big payload before the trim
TRIM_EVERY = 5.0  # s at most between the first big payload and the trim


def _malloc_trim() -> Callable[[], object] | None:
    """glibc's `malloc_trim(0)`, or None where there is none."""
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        trim = libc.malloc_trim
    except (OSError, AttributeError):
        return None
    trim.argtypes = [ctypes.c_size_t]
    trim.restype = ctypes.c_int
    return lambda: trim(0)


_trim = _malloc_trim()
_cond = threading.Condition()
_first: float | None = None  # monotonic s of the first big payload not trimmed after yet
_last = 0.0  # monotonic s of the latest big payload
_count = 0
_worker: threading.Thread | None = None


def trims() -> int:
    """How many times memory was given back in this process."""
    return _count


def _run() -> None:
    global _first, _count
    while True:
        with _cond:
            while _first is None:
                _cond.wait()
            while (due := min(_last + TRIM_DELAY, _first + TRIM_EVERY)) > time.monotonic():
                _cond.wait(due - time.monotonic())
            quiet = time.monotonic() >= _last + TRIM_DELAY
            _first = None
        if quiet:  # the burst is over: free what only the cycle collector would
            gc.collect()
        if _trim is not None:
            _trim()
        _count += 1


def note_payload(size: int) -> None:
    """A payload of `size` bytes arrived (any thread; cheap): after big ones, give the freed
    memory back to the system.

    It is told the size of every payload received (by subscriptions and RPC servers); after big
    ones (≥ `BIG_PAYLOAD` bytes), once none came for `TRIM_DELAY` s, it collects garbage cycles
    (`gc.collect()`, some 30 ms in the robot) and asks glibc to return the free pages of every
    heap (`malloc_trim(0)`, well under a millisecond); while they keep coming (a camera's
    stream of frames) it only trims, `TRIM_EVERY` s after the first.
    """
    global _first, _last, _worker
    if size < BIG_PAYLOAD or _trim is None:
        return
    with _cond:
        _last = time.monotonic()
        if _first is None:
            _first = _last
            _cond.notify()
        if _worker is None:
            _worker = threading.Thread(target=_run, name="memory trim", daemon=True)
            _worker.start()
