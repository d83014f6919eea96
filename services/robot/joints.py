"""Moving the joints on the simulation thread: a command or positionMove checked against the
part's rules (`commands`), counted and applied as the part's targets; reference speeds set.

The lease was checked before the job was queued (`leases`); here nothing checks it again.
Simulation thread only.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from archery.protocol.errors import BadRequest, Busy
from archery.protocol.text import shown
from archery.services.robot.commands import CommandRejected, PartCounters, PartLimits, check_command
from archery.services.robot.pacing import Pacing
from archery.services.robot.simthread import SimThread
from archery.services.robot.watchdog import StreamWatchdog
from archery.sim.world import ArcheryWorld

__all__ = ["JointMover"]

log = logging.getLogger("archery.robot")


class JointMover:
    """Sets the parts' joint targets (rad) and reference speeds (rad/s).

    Args:
        world: the simulated robot.
        limits: each part's joint names, software limits and clamp tolerance.
        counters: each part's command counters.
        pacing: woken by every move (the streams keep their full rates a while).
        streams: the command streams a `command:i` command continues (the watchdog).
        thread: the loop a command's announced batch is counted for.
        plays: whether a trajectory moves a part now (it refuses commands meanwhile: `busy`).
    """

    def __init__(
        self,
        world: ArcheryWorld,
        limits: Mapping[str, PartLimits],
        counters: Mapping[str, PartCounters],
        pacing: Pacing,
        streams: StreamWatchdog,
        thread: SimThread,
        plays: Callable[[str], bool],
    ) -> None:
        self._world = world
        self._limits = limits
        self._counters = counters
        self._pacing = pacing
        self._streams = streams
        self._thread = thread
        self._plays = plays
        self._stream_lease = {part: "" for part in world.parts}  # of the last stream command

    def command(
        self,
        part: str,
        position: list[float],
        names: list[str] | None,
        said: str,
        at: float,
        batch: int,
        lease: str,
    ) -> None:
        """A `command:i` command received at wall time `at` (monotonic s) under `lease`; one
        under another lease than the part's previous command continues no stream."""
        self._pacing.wake()
        self._thread.count_batch(batch)
        try:
            targets, clamped = self._check(part, position, names, said)
        except (CommandRejected, Busy):
            return
        overtakes = not self._world.motion_done(part)
        self._apply(part, targets, clamped)
        if lease != self._stream_lease[part]:  # another client's: it continues no stream
            self._stream_lease[part] = lease
            self._streams.forget(part)
        self._streams.command(part, at, overtakes)

    def position_move(self, part: str, position: Any, names: Any) -> list[float]:
        """A positionMove: a move followed to its end (it ends a stream); the part's targets.

        Raises:
            BadRequest: `names` is not a list. CommandRejected: a command rule is broken.
        """
        self._pacing.wake()
        if names is not None and not isinstance(names, list | tuple):
            raise BadRequest(f"names must be a list of joint names, got {shown(names)}")
        targets, clamped = self._check(part, position, names, None)
        self._streams.forget(part)
        return self._apply(part, targets, clamped)

    def set_ref_speeds(self, part: str, speeds: Any) -> list[float]:
        """Set `part`'s reference speeds (rad/s, one per joint); the speeds now in force."""
        self._pacing.wake()
        in_force: list[float] = self._world.set_reference_speeds(part, speeds).tolist()
        return in_force

    def _check(
        self, part: str, position: Any, names: Any, said: str | None
    ) -> tuple[np.ndarray, bool]:
        if self._plays(part):
            message = f"{part} plays a trajectory: its moves wait until it ends"
            self._counters[part].reject("busy", message)
            raise Busy(message)
        try:
            return check_command(
                self._limits[part], self._world.joint_targets(part), position, names, said
            )
        except CommandRejected as exc:
            n = self._counters[part].reject(exc.reason, exc.message)
            if n <= 10 or n % 100 == 0:
                log.warning("rejected command #%d on %s (%s): %s", n, part, exc.reason, exc.message)
            raise

    def _apply(self, part: str, targets: np.ndarray, clamped: bool) -> list[float]:
        self._counters[part].accept(clamped)
        applied: list[float] = self._world.set_joint_targets(part, targets).tolist()
        return applied
