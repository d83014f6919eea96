"""Physics stepping on the simulation thread: the world advanced chunk by chunk, its joint and
world states streamed when due, and the parts whose command stream went stale held.

Which chunk and which states are due is `pacing`'s to say; when a stream is stale, the
`watchdog`'s. Simulation thread only.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from typing import TYPE_CHECKING

import numpy as np

from archery.services.robot.commands import PartCounters
from archery.services.robot.history import StateHistory
from archery.services.robot.pacing import Pacing
from archery.services.robot.shot import Shots, phase_of
from archery.services.robot.sink import Sink
from archery.services.robot.watchdog import StreamWatchdog
from archery.sim.world import ArcheryWorld

if TYPE_CHECKING:
    from archery.services.robot.follow import Follower

__all__ = ["Physics"]

log = logging.getLogger("archery.robot")


class Physics:
    """The world, stepped and streamed.

    Args:
        world: the simulated robot, owned by the simulation thread.
        sink: receives the joint states, world states and watchdog events.
        pacing: the publication grid the chunks end on.
        shots: the shot state (its number goes out with the world state; a landing answers it).
        streams: the parts' command streams (the watchdog).
        counters: each part's command counters (a watchdog hold is counted there).
    """

    def __init__(
        self,
        world: ArcheryWorld,
        sink: Sink,
        pacing: Pacing,
        shots: Shots,
        streams: StreamWatchdog,
        counters: Mapping[str, PartCounters],
    ) -> None:
        self.world = world
        self.dt = world.timestep  # s of sim time per step
        self._sink = sink
        self._pacing = pacing
        self._shots = shots
        self._streams = streams
        self._counters = counters
        self._names = {part: tuple(world.joint_names(part)) for part in world.parts}
        #: every part's positions at each joint-state grid point, whatever the rtf
        self.history = StateHistory(
            {part: len(names) for part, names in self._names.items()}, pacing.state_period
        )
        self.follower: Follower | None = None  # the trajectories, once the loop attaches them

    def cap(self, steps: int) -> int:
        """`steps` cut so that a chunk ends at a playing trajectory's next action or end."""
        if self.follower is None:
            return steps
        return self.follower.cap(steps, self.world.sim_time, self.dt)

    def moving(self) -> bool:
        """True while a part has not reached its targets or an arrow flies or falls."""
        return self._shots.flying or self.world.arrow_falling or not self.world.motion_done()

    def advance(self, steps: int) -> None:
        """Step the world `steps` time steps; publish the states then due and a landing."""
        world = self.world
        landing = world.step(steps * self.dt)
        if self.follower is not None:
            self.follower.check()
        joints, world_due = self._pacing.due(world.sim_time)
        if self._pacing.on_state_grid:
            self.record()
        if joints:
            self.publish_joints()
        if landing is not None:
            self.publish_world()
            self._shots.landed(landing)
        elif world_due:
            self.publish_world()

    def record(self) -> None:
        """Keep every part's positions now in the history (a grid point of the joint states)."""
        world = self.world
        row = np.concatenate([world.joint_positions(part) for part in world.parts])
        self.history.add(world.sim_time, row)

    def publish_joints(self) -> None:
        """Every part's joint state: positions (rad), velocities (rad/s), motion done."""
        world = self.world
        t = world.sim_time
        for part in world.parts:
            self._sink.joint_state(
                part,
                self._names[part],
                world.joint_positions(part).tolist(),
                world.joint_velocities(part).tolist(),
                world.motion_done(part),
                t,
            )
        self._pacing.sent_joints()

    def publish_world(self) -> None:
        """The world state: the scene's generalized positions, the shot phase and number."""
        world = self.world
        self._sink.world_state(world.qpos(), phase_of(world), self._shots.number, world.sim_time)
        self._pacing.sent_world()

    def hold_stale(self, now: float) -> bool:
        """Hold the parts whose command stream went stale by wall time `now` (monotonic s)
        while they still move, each counted and announced; True if any."""
        tripped = False
        for part, age in self._streams.stale(now):
            if not self.world.motion_done(part):
                held = self.world.hold(part)
                self._counters[part].tripped()
                tripped = True
                reason = f"{part}: no command for {age:.3f} s mid-motion, held where it is"
                log.warning("%s at %s", reason, np.round(held, 4).tolist())
                self._sink.event("watchdog", self._shots.number, self.world.sim_time, None, reason)
        return tripped
