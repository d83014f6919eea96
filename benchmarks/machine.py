"""What every benchmark reports about the machine, and pinning a benchmark to one core."""

from __future__ import annotations

import os
import platform
from pathlib import Path

__all__ = ["cpu_model", "pin_one_core"]


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
