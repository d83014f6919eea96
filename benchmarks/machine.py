"""What every benchmark reports about the machine, and pinning a benchmark to one core."""

from __future__ import annotations

import multiprocessing
import os
import platform
import time
from pathlib import Path
from typing import Any

__all__ = ["core_scaling", "cpu_model", "pin_one_core"]


def cpu_model() -> str:
    """The CPU's model name (from /proc/cpuinfo where there is one)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def pin_one_core() -> str:
    """Pin this process to one core (where the OS allows it); says what was done."""
    try:
        core = min(os.sched_getaffinity(0))
        os.sched_setaffinity(0, {core})
        return f"pinned to core {core}"
    except (AttributeError, OSError):
        return "not pinned"


def _spin(start: Any, seconds: float, out: Any) -> None:
    """Pure-Python work for `seconds` of wall time once `start` is set; puts chunks per second."""
    start.wait()
    t0 = time.perf_counter()
    chunks = 0
    while time.perf_counter() - t0 < seconds:
        total = 0
        for i in range(20_000):
            total += i * i
        chunks += 1
    out.put(chunks / (time.perf_counter() - t0))


def core_scaling(processes: int = 2, seconds: float = 1.0) -> float:
    """What `processes` CPU-bound processes get done together, over what one gets done alone
    (pure-Python work, `seconds` each; one alone before and after, averaged): 2.0 on two idle
    cores of their own; less where the cores share a physical core or the host is busy. No
    set of processes on this machine can scale beyond it at that moment."""
    ctx = multiprocessing.get_context("spawn")

    def rate(k: int) -> float:
        start, out = ctx.Event(), ctx.Queue()
        procs = [ctx.Process(target=_spin, args=(start, seconds, out)) for _ in range(k)]
        for proc in procs:
            proc.start()
        start.set()
        total = sum(out.get(timeout=60 + seconds) for _ in procs)
        for proc in procs:
            proc.join()
        return total

    before = rate(1)
    together = rate(processes)
    return together / (0.5 * (before + rate(1)))
