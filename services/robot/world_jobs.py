"""The archery verbs' work on the world (grasp, nock, release, reset, wind, status), run on
the simulation thread by `SimLoop`; each wakes the pacing and publishes what it changed.
"""

from __future__ import annotations

import logging
from concurrent.futures import Future
from dataclasses import replace

from archery.protocol.verbs import robot as rv
from archery.services.robot.commands import PartCounters
from archery.services.robot.config import RobotConfig
from archery.services.robot.follow import Follower
from archery.services.robot.leases import Leases
from archery.services.robot.pacing import Pacing
from archery.services.robot.physics import Physics
from archery.services.robot.shot import Shots, phase_of
from archery.services.robot.sink import Sink
from archery.services.robot.watchdog import StreamWatchdog
from archery.sim.whole_shot import NOCK_IN_STRING_HAND
from archery.sim.world import ArcheryWorld

__all__ = ["WorldJobs"]

log = logging.getLogger("archery.robot")


class WorldJobs:
    """The archery verbs' jobs; call them on the simulation thread only (`SimLoop.call`).
    `seed` is the seed the world was last reset with (reported by `status`)."""

    def __init__(
        self,
        world: ArcheryWorld,
        config: RobotConfig,
        sink: Sink,
        pacing: Pacing,
        shots: Shots,
        physics: Physics,
        follower: Follower,
        streams: StreamWatchdog,
        counters: dict[str, PartCounters],
        leases: Leases,
        seed: int | None,
    ) -> None:
        self.world = world
        self.config = config
        self.seed = seed
        self._sink = sink
        self._pacing = pacing
        self._shots = shots
        self._physics = physics
        self._follower = follower
        self._streams = streams
        self._counters = counters
        self.leases = leases

    def grasp(self) -> rv.GraspReply:
        self._pacing.wake()
        reply = self._shots.grasp(self.world)
        self._physics.publish_world()
        return reply

    def nock(self) -> rv.NockReply:
        self._pacing.wake()
        reply = self._shots.nock(self.world)
        self._physics.publish_world()
        return reply

    def release(self) -> Future[rv.ReleaseReply]:
        self._pacing.wake()
        try:
            landing = self._shots.release(self.world)
        finally:
            self._physics.publish_world()  # also a dropped arrow's
        return landing

    def reset(self, seed: int | None) -> rv.ResetReply:
        self._pacing.wake()
        self._follower.abort_all("the robot was reset mid-trajectory")
        self.world.reset(seed)
        if seed is not None:
            self.seed = seed
        self._streams.forget()
        self._pacing.schedule(self.world.sim_time)
        self._physics.history.clear()  # simulated time starts again
        self._physics.record()
        shot = self._shots.number
        self._sink.event("reset", shot, self.world.sim_time)
        self._physics.publish_joints()
        self._physics.publish_world()
        return rv.ResetReply(sim_time=self.world.sim_time, seed=seed, shot=shot)

    def set_wind(self, wind: tuple[float, float, float]) -> list[float]:
        self._pacing.wake()
        self.world.config = replace(self.world.config, wind=wind)
        log.info("wind set to %s m/s", list(wind))
        return list(self.world.config.wind)

    def status(self) -> rv.ArcheryStatusReply:
        world = self.world
        cfg = self.config
        return rv.ArcheryStatusReply(
            sim_time=world.sim_time,
            arrow=world.arrow_state.value,
            phase=phase_of(world),
            shot=self._shots.number,
            motion_done=world.motion_done(),
            seed=self.seed,
            rtf=cfg.rtf,
            state_rate=cfg.state_rate,
            world_rate=cfg.world_rate,
            watchdog=cfg.watchdog,
            limit_tolerance=cfg.limit_tolerance,
            timestep=world.timestep,
            counters={
                p: self._counters[p].to_dict()
                | {"streaming": self._streams.streaming(p), "owner": self.leases.owner(p)}
                for p in world.parts
            },
            scene=world.config.scene.to_status(),
            world=world.config.to_dict(),
            nock_in_hand=None if world.whole is None else list(NOCK_IN_STRING_HAND),
        )
