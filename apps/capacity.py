"""What this machine can hold: the maxima of the scale flags (`up --robots`, `experiment
--sessions/--rollouts`), from its available memory and its cores.

A robot stack (robot, controller, camera, detector) is resident at 0.78 GiB once started
(measured with `archery up`, 2026-12-01) and grows while it renders and detects: counted as
`STACK_MEMORY`. At rtf 0 one stack keeps about 1.4 cores busy; at rtf 1 far less, so the
core bound allows `STACKS_PER_CORE` stacks per core. An experiment keeps, per rollout of every
session of every algorithm, θ, the observed and true r, its record and the learner's state:
0.9 KiB measured (peak resident size of 400 against 20 sessions of 60 rollouts), counted as
`ROLLOUT_MEMORY`. `--allow-overload` lifts these bounds for a user who knows better.
"""

from __future__ import annotations

import os
from pathlib import Path

from archery.protocol.errors import ConfigError

__all__ = [
    "MAX_SESSIONS",
    "ROLLOUT_MEMORY",
    "STACKS_PER_CORE",
    "STACK_MEMORY",
    "available_memory",
    "check_experiment",
    "check_robots",
    "cores",
    "max_robots",
]

GIB = 1024**3
STACK_MEMORY = 1.0 * GIB  # B per robot stack
BASE_MEMORY = 0.5 * GIB  # B: the router, the learner and `up` itself
STACKS_PER_CORE = 4
MAX_SESSIONS = 10_000  # per algorithm
ROLLOUT_MEMORY = 1024  # B kept per rollout of an experiment
OVERRIDE = "--allow-overload"


def available_memory(meminfo: Path = Path("/proc/meminfo")) -> int:
    """Memory the kernel can give without swapping (B): MemAvailable, or the physical memory
    where the kernel does not say."""
    try:
        for line in meminfo.read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")


def cores() -> int:
    """The cores this process may run on."""
    return len(os.sched_getaffinity(0))


def max_robots(memory: int | None = None, ncores: int | None = None) -> int:
    """The most robot stacks `archery up` starts on this machine (at least 1).

    Args:
        memory: available memory (B); None: this machine's.
        ncores: cores; None: this machine's.
    """
    memory = available_memory() if memory is None else memory
    ncores = cores() if ncores is None else ncores
    by_memory = int((memory - BASE_MEMORY) // STACK_MEMORY)
    return max(1, min(by_memory, STACKS_PER_CORE * ncores))


def check_robots(robots: int, allow_overload: bool, memory: int | None = None) -> None:
    """Refuse more robot stacks than the machine holds, unless `allow_overload`.

    Raises:
        ConfigError: one line naming the maximum, why, and the override.
    """
    limit = max_robots(memory)
    if robots > limit and not allow_overload:
        free = (available_memory() if memory is None else memory) / GIB
        raise ConfigError(
            f"--robots {robots}: this machine holds at most {limit} robot stacks "
            f"({free:.1f} GiB available at {STACK_MEMORY / GIB:.1f} GiB each, "
            f"{STACKS_PER_CORE} per core on {cores()} cores); give {OVERRIDE} to start them "
            "anyway"
        )


def check_experiment(
    algorithms: int, sessions: int, rollouts: int, allow_overload: bool, memory: int | None = None
) -> None:
    """Refuse an experiment above `MAX_SESSIONS` sessions per algorithm, or whose rollouts do
    not fit in half the available memory, unless `allow_overload`.

    Raises:
        ConfigError: one line naming the flag, the maximum and the override.
    """
    if allow_overload:
        return
    if sessions > MAX_SESSIONS:
        raise ConfigError(
            f"--sessions {sessions}: at most {MAX_SESSIONS} per algorithm; give {OVERRIDE} to "
            "run them anyway"
        )
    memory = available_memory() if memory is None else memory
    need = algorithms * sessions * rollouts * ROLLOUT_MEMORY
    if need > memory / 2:
        fits = int(memory / 2 // (algorithms * rollouts * ROLLOUT_MEMORY))
        raise ConfigError(
            f"--sessions {sessions} × --rollouts {rollouts} × {algorithms} algorithm(s) needs "
            f"{need / GIB:.1f} GiB, more than half of the {memory / GIB:.1f} GiB available: at "
            f"most {fits} sessions at this budget; give {OVERRIDE} to run it anyway"
        )
