"""`SimLoop`: the robot's simulation as the handlers and the service see it; every verb's work
on the world, queued for the thread that owns it.

Its parts, each in its own module: the job queue (`jobs`), the thread's loop (`simthread`),
physics stepping (`physics`), pacing (`pacing`), the lease gate (`leases`, `gate`), the shot
(`shot`), the archery verbs' work on the world (`world_jobs`), moving the joints (`joints`, by
the rules of `commands`) and the stream watchdog (`watchdog`). The ports and verbs are listed
in docs/names.md and `protocol.verbs.robot`.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from concurrent.futures import Future
from typing import Any, TypeVar

from archery.protocol.errors import BadRequest
from archery.protocol.text import shown
from archery.protocol.vectors import finite_vector
from archery.protocol.verbs import robot as rv
from archery.protocol.verbs.robot import MAX_WIND
from archery.services.robot.commands import PartCounters, PartLimits
from archery.services.robot.config import RobotConfig
from archery.services.robot.follow import Follower, PartSpec
from archery.services.robot.jobs import SimJobs, SimUnavailable
from archery.services.robot.joints import JointMover
from archery.services.robot.leases import Leases
from archery.services.robot.pacing import Pacing
from archery.services.robot.physics import Physics
from archery.services.robot.shot import Shots
from archery.services.robot.simthread import SimThread
from archery.services.robot.sink import Sink
from archery.services.robot.watchdog import StreamWatchdog
from archery.services.robot.world_jobs import WorldJobs
from archery.sim.world import ArcheryWorld

__all__ = ["SimLoop"]

T = TypeVar("T")


class SimLoop:
    """Runs the world on one thread (`run`); every other method may be called from any thread.

    Args:
        world: the simulated robot, owned by the loop from now on.
        config: rates, rtf, watchdog, limit tolerance, batch window, job timeout, rate limit.
        sink: receives the streams and events (called on the loop's thread).
        seed: the seed the world was last reset with (reported by `status`).
    """

    def __init__(
        self, world: ArcheryWorld, config: RobotConfig, sink: Sink, seed: int | None = None
    ) -> None:
        self.world = world
        self.config = config
        self.limits = {
            part: PartLimits(
                part=part,
                names=world.joint_names(part),
                lower=tuple(float(v) for v in world.joint_limits(part)[0]),
                upper=tuple(float(v) for v in world.joint_limits(part)[1]),
                tolerance=config.limit_tolerance,
            )
            for part in world.parts
        }
        self._counters = {part: PartCounters() for part in world.parts}
        self.leases = Leases(world.parts, config.command_rate, config.command_burst, self._counters)
        self._jobs = SimJobs(config.job_timeout)
        self._pacing = Pacing(
            world.timestep,
            config.state_rate,
            config.world_rate,
            config.rtf,
            rest_rate=config.rest_rate,
            rest_after=config.rest_after,
        )
        self._streams = StreamWatchdog(world.parts, config.watchdog)
        self._shots = Shots(sink, wait_for_rest=config.rtf == 0)
        self._sink = sink
        self._physics = Physics(
            world, sink, self._pacing, self._shots, self._streams, self._counters
        )
        self._thread = SimThread(
            self._physics, self._jobs, self._pacing, self._streams, self._shots, config
        )
        self._follower = Follower(
            world,
            self.limits,
            self.leases,
            self._shots,
            self._physics.publish_world,
            wait_for_rest=config.rtf == 0,
        )
        self._physics.follower = self._follower
        self._world = WorldJobs(
            world,
            config,
            sink,
            self._pacing,
            self._shots,
            self._physics,
            self._follower,
            self._streams,
            self._counters,
            self.leases,
            seed,
        )
        self._mover = JointMover(
            world,
            self.limits,
            self._counters,
            self._pacing,
            self._streams,
            self._thread,
            self._follower.plays,
        )

    # -- the thread and its jobs -------------------------------------------------------------
    def run(self, stop: threading.Event) -> None:
        """Serve jobs and advance the world until `stop` is set or the loop is closed."""
        try:
            self._thread.run(stop)
        finally:
            self._follower.abort_all("the robot stopped mid-trajectory", unavailable=True)

    def call(self, func: Callable[[], T], timeout: float | None = None) -> T:
        """Run `func` on the simulation thread and return its result (or raise its error).

        Raises:
            SimUnavailable: the thread did not run it within `timeout` (default: the config's
                job_timeout) wall seconds, or the loop is closed.
        """
        return self._jobs.call(func, timeout)

    def close(self) -> None:
        """Refuse new jobs, fail the pending ones and wake the loop, which then ends."""
        self._jobs.close()

    # -- moving the joints -------------------------------------------------------------------
    def command(
        self,
        part: str,
        position: list[float],
        names: list[str] | None,
        said: str,
        batch: int = 1,
        lease: str = "",
    ) -> None:
        """A `command:i` message for `part` whose payload passed `leases.screen` (`said`: the
        part it names; `batch`: how many commands, this one included, start together; `lease`:
        the lease id it carries, verified there: under another lease than the part's previous
        command it continues no stream). Queued, not awaited; a command that breaks a rule is
        counted and logged, never applied."""
        at = time.monotonic()
        self._jobs.submit(
            lambda: self._mover.command(part, position, names, said, at, batch, lease)
        )

    def position_move(self, part: str, position: Any, names: Any = None) -> list[float]:
        """Validate and apply targets (rad) like a command; returns the part's targets. The
        caller checked the lease (`leases.check`).

        Raises:
            CommandRejected: the targets break a rule (see `commands`)."""
        return self.call(lambda: self._mover.position_move(part, position, names))

    def set_ref_speeds(self, part: str, speeds: Any) -> list[float]:
        """Set `part`'s reference speeds (rad/s; one number for every joint, or one per joint).
        The caller checked the lease (`leases.check`)."""
        if isinstance(speeds, int | float) and not isinstance(speeds, bool):
            speeds = [speeds] * len(self.limits[part].names)
        return self.call(lambda: self._mover.set_ref_speeds(part, speeds))

    def follow(
        self, parts: list[PartSpec], args: rv.PartTrajectoryArgs | rv.TrajectoryArgs
    ) -> Future[rv.TrajectoryReply]:
        """Start a trajectory of `parts` (`follow`); its reply once it has ended. The caller
        checked the leases (`leases.check`).

        Raises:
            BadTrajectory, Busy, StateError: see `Follower.start` (nothing moved).
        """

        def start() -> Future[rv.TrajectoryReply]:
            self._pacing.wake()
            reply = self._follower.start(parts, args)
            for spec in parts:
                self._streams.forget(spec.part)  # no stream: the watchdog leaves it be
            return reply

        return self.call(start)

    # -- reading the joints ------------------------------------------------------------------
    def positions(self, part: str) -> rv.PositionsReply:
        """Encoders of `part`: positions (rad), velocities (rad/s), sim time (s)."""
        world = self.world
        return self.call(
            lambda: rv.PositionsReply(
                names=list(world.joint_names(part)),
                position=world.joint_positions(part).tolist(),
                velocity=world.joint_velocities(part).tolist(),
                sim_time=world.sim_time,
            )
        )

    def history(self, part: str, since: float) -> rv.HistoryReply:
        """`part`'s encoder positions (rad) at every joint-state grid point (s of sim time)
        from `since` on, of the last `HISTORY_SPAN` s (`history`)."""

        def read() -> rv.HistoryReply:
            times, positions = self._physics.history.since(part, since)
            names = list(self.world.joint_names(part))
            return rv.HistoryReply(names=names, times=times, positions=positions)

        return self.call(read)

    def targets(self, part: str) -> list[float]:
        """Current (clamped) targets of `part` (rad)."""
        return self.call(lambda: self.world.joint_targets(part).tolist())

    def motion_done(self, part: str) -> bool:
        """True when `part` has reached its targets and settled."""
        return self.call(lambda: self.world.motion_done(part))

    def ref_speeds(self, part: str) -> list[float]:
        """`part`'s reference speeds (rad/s)."""
        return self.call(lambda: self.world.reference_speeds(part).tolist())

    def counters(self, part: str, undecodable: int = 0) -> rv.CountersReply:
        """`part`'s command counters, whether it is streaming, and `undecodable`: the commands
        its port could not decode (counted by the service's subscription, not here)."""
        return self.call(
            lambda: rv.CountersReply(
                **self._counters[part].to_dict(),
                streaming=self._streams.streaming(part),
                undecodable=undecodable,
            )
        )

    # -- the shot and the world --------------------------------------------------------------
    def grasp(self) -> rv.GraspReply:
        """Whole shot: close the right hand on the arrow in its holder.

        Raises:
            GraspMissed: the hand is off the shaft by more than the tolerance (the arrow stays).
            StateError: not --shot whole, or an arrow is held, nocked or flying.
        """
        return self.call(self._world.grasp)

    def nock(self) -> rv.NockReply:
        """Put a fresh arrow on the bow (whole shot: the held arrow's nock on the string).

        Raises:
            NockMissed: whole shot, the nock is off the string by more than the tolerance.
            StateError: an arrow flies (whole shot: none is in the hand).
        """
        return self.call(self._world.nock)

    def release(self, timeout: float | None = None) -> rv.ReleaseReply:
        """Release the nocked arrow and return once it has landed (at rtf 0, once the robot
        also rests after the shot; see `shot`).

        Raises:
            StateError: no arrow is nocked. SimUnavailable: no landing within `timeout` wall s.
            ArrowDropped: whole shot, the arrow was in the hand but off the string: it falls.
        """
        cfg = self.config
        if timeout is None:
            flight = cfg.world.max_flight_time
            timeout = cfg.job_timeout + (flight / cfg.rtf if cfg.rtf > 0 else flight)
        landing = self.call(self._world.release)
        try:
            return landing.result(timeout)
        except TimeoutError:
            raise SimUnavailable(f"the arrow did not land within {timeout:g} wall s") from None

    def reset(self, seed: Any = None) -> rv.ResetReply:
        """Back to the home joint positions at sim time 0, the arrow stowed; reseed when `seed`
        is set.

        Raises:
            BadRequest: the seed is not an integer >= 0. StateError: an arrow is in flight.
        """
        if seed is not None and (isinstance(seed, bool) or not isinstance(seed, int) or seed < 0):
            raise BadRequest(f"seed must be an integer >= 0 or absent, got {shown(seed)}")
        return self.call(lambda: self._world.reset(seed))

    def set_wind(self, wind: Any) -> list[float]:
        """Set the constant wind (m/s, root frame) of the shots launched from now on; returns
        the wind now in force. An arrow already flying keeps the wind drawn at its launch.

        Raises:
            BadRequest: not 3 finite numbers, or a component beyond ±MAX_WIND m/s.
        """
        x, y, z = (float(v) for v in finite_vector("wind", wind, BadRequest, unit="m/s"))
        if any(abs(v) > MAX_WIND for v in (x, y, z)):
            raise BadRequest(
                f"each wind component must be within ±{MAX_WIND:g} m/s, got {shown(wind)}"
            )
        return self.call(lambda: self._world.set_wind((x, y, z)))

    def status(self) -> rv.ArcheryStatusReply:
        """Arrow state, sim time, shot count, counters, and the scene and world configs."""
        return self.call(self._world.status)
