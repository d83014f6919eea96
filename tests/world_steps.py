"""Stepping a world until its motion is done, for tests and benchmarks that drive the simulator
without a robot service."""

from __future__ import annotations

import math

from archery.sim.errors import CommandError
from archery.sim.world import ArcheryWorld

__all__ = ["move_until_done"]


def move_until_done(world: ArcheryWorld, timeout: float = 10.0, check_every: float = 0.01) -> bool:
    """Step until `world.motion_done()` or `timeout` simulated seconds; True if done.

    Motion is checked every `check_every` simulated seconds. An arrow in flight keeps flying.
    """
    if not math.isfinite(timeout) or timeout < 0:
        raise CommandError(f"timeout must be a finite number of seconds >= 0, got {timeout!r}")
    end = world.physics.time + timeout
    while not world.motion_done():
        if world.physics.time >= end - 0.5 * world.timestep:
            return False
        world.step(min(check_every, end - world.physics.time))
    return True
