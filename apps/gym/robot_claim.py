"""Which robot of a fleet an `archery/AimRobot-v0` environment drives, when several may.

Given several robot prefixes (those `archery up --robots N` starts: `icubSim1` … `icubSimN`),
an environment claims the first one no other environment of this user on this machine holds:
an exclusive lock (`flock`) on `RUNTIME/PREFIX/gym.lock` (RUNTIME: `mesh.runtime.runtime_dir`),
held while the environment lives and released by the kernel when its process ends. So
`gymnasium.make_vec(..., vectorization_mode="async", robot=[...])` gives each worker process
its own robot.
"""

from __future__ import annotations

import fcntl
import os
from collections.abc import Sequence
from dataclasses import dataclass

from archery.mesh.runtime import runtime_dir
from archery.protocol.text import shown

__all__ = ["LOCK_NAME", "RobotClaim", "claim_robot", "robot_names"]

LOCK_NAME = "gym.lock"


@dataclass
class RobotClaim:
    """A robot prefix this process holds; `release()` lets another environment take it."""

    robot: str
    fd: int | None

    def release(self) -> None:
        """Give the robot back (closing the lock file releases the lock)."""
        if self.fd is not None:
            os.close(self.fd)
            self.fd = None


def robot_names(robot: str | Sequence[str]) -> list[str]:
    """The prefixes of a `robot` keyword: one name, names separated by commas, or a list.

    Raises:
        ValueError: not a string or a list of strings, no name, or an empty one.
    """
    listed = isinstance(robot, list | tuple) and all(isinstance(n, str) for n in robot)
    if not isinstance(robot, str) and not listed:
        raise ValueError(f"robot must name one robot prefix or several, got {shown(robot)}")
    names = robot.split(",") if isinstance(robot, str) else list(robot)
    names = [n.strip() for n in names]
    if not names or not all(names):
        raise ValueError(f"robot must name one robot prefix or several, got {shown(robot)}")
    return names


def claim_robot(names: Sequence[str]) -> RobotClaim:
    """The first of `names` free on this machine, claimed (one name: taken without a lock).

    Raises:
        ValueError: every one of several robots is held by another environment.
    """
    if len(names) == 1:
        return RobotClaim(names[0], None)
    for name in names:
        folder = runtime_dir() / name
        folder.mkdir(mode=0o700, parents=True, exist_ok=True)
        fd = os.open(folder / LOCK_NAME, os.O_RDWR | os.O_CREAT, 0o600)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            continue
        return RobotClaim(name, fd)
    raise ValueError(
        f"every robot of {', '.join(names)} is driven by another environment on this machine; "
        f"start more with `archery up --robots N` or make fewer environments"
    )
