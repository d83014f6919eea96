"""The simulation thread's loop: jobs run between physics chunks, paced, and the rest at rtf 0.

At rtf > 0 each chunk waits for its wall time (`pacing`), running the jobs that arrive and
holding stale streams meanwhile. At rtf 0 the world runs as fast as possible while something
moves and, when nothing does, the thread sleeps on its job queue and repeats the unchanged
state in wall time (see `pacing` and docs/names.md for the rates). A command that wakes the idle
robot starts its motion at once unless it announces a batch (`JointCommand.batch` > 1): the
loop then waits for the rest of the batch (at most `batch_window` wall s) and starts them at
one simulated time, so same-seed runs stay identical.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable

from archery.services.robot.config import RobotConfig
from archery.services.robot.jobs import SimJobs
from archery.services.robot.pacing import MAX_IDLE_WAIT, Pacing
from archery.services.robot.physics import Physics
from archery.services.robot.shot import Shots
from archery.services.robot.watchdog import StreamWatchdog

__all__ = ["SimThread"]

log = logging.getLogger("archery.robot")


class SimThread:
    """The loop of the thread that owns the world (`run`); `count_batch` is a job's to call.

    Args:
        physics: the world, stepped and streamed.
        jobs: the work other threads hand the thread.
        pacing: the chunks' grid, the rtf schedule and the beats at rest.
        streams: the command streams whose deadlines wake the thread.
        shots: the shot state (its held reply goes out at rest; it fails at the end).
        config: rtf and batch window.
    """

    def __init__(
        self,
        physics: Physics,
        jobs: SimJobs,
        pacing: Pacing,
        streams: StreamWatchdog,
        shots: Shots,
        config: RobotConfig,
    ) -> None:
        self._physics = physics
        self._jobs = jobs
        self._pacing = pacing
        self._streams = streams
        self._shots = shots
        self._config = config
        self._idle = False
        # commands (and the largest batch they announced) since the loop last came to rest
        self._batch_seen = 0
        self._batch_size = 0

    def count_batch(self, batch: int) -> None:
        """A command arrived that announced a batch of `batch` commands (itself included)."""
        self._batch_seen += 1
        self._batch_size = max(self._batch_size, batch)

    def run(self, stop: threading.Event) -> None:
        """Serve jobs and advance the world until `stop` is set or the jobs are closed."""
        jobs, physics, pacing = self._jobs, self._physics, self._pacing
        world = physics.world
        try:
            pacing.schedule(world.sim_time)
            physics.record()  # the grid's first point
            while not stop.is_set() and not jobs.closed:
                jobs.drain()
                physics.hold_stale(time.monotonic())
                if self._config.rtf == 0:
                    if physics.moving():
                        if self._idle:  # at rest until now: start an announced batch whole
                            self._await_batch(stop)
                        self._idle = False
                        physics.advance(physics.cap(pacing.chunk(world.sim_time)))
                    else:
                        self._rest(stop)
                    continue
                steps = physics.cap(pacing.chunk(world.sim_time))
                if self._sleep_until(pacing.wall_due(world.sim_time, steps), stop):
                    continue  # jobs ran meanwhile: they may have changed the world
                physics.advance(steps)
        finally:
            jobs.close()
            self._shots.abort()

    def _sleep_until(
        self, due: float, stop: threading.Event, until: Callable[[], bool] | None = None
    ) -> bool:
        """Wait until wall time `due` (or until `until()` holds), running jobs that arrive and
        holding the parts whose stream goes stale meanwhile (at its deadline); True if either
        changed the world."""
        ran = False
        while not stop.is_set() and not self._jobs.closed:
            if until is not None and until():
                break
            now = time.monotonic()
            stale_at = self._streams.deadline()
            if stale_at is not None and now >= stale_at:
                ran = self._physics.hold_stale(now) or ran
                stale_at = self._streams.deadline()
            remaining = due - now
            if remaining <= 0:
                break
            wake = remaining if stale_at is None else min(remaining, max(0.0, stale_at - now))
            if self._jobs.wait(min(wake, MAX_IDLE_WAIT)):
                ran = self._jobs.drain() or ran
        return ran

    def _await_batch(self, stop: threading.Event) -> None:
        """A motion starts at rest: let the rest of its announced batch arrive first (at most
        `batch_window` wall s), so that its commands start at one simulated time."""
        if self._batch_seen >= self._batch_size:
            return
        window = self._config.batch_window
        self._sleep_until(
            time.monotonic() + window, stop, until=lambda: self._batch_seen >= self._batch_size
        )
        if self._batch_seen < self._batch_size:
            log.warning(
                "a batch of %d commands started with %d of them after %g s (wall): the rest will "
                "start later, at a simulated time that depends on the wall clock (same-seed runs "
                "part here)",
                self._batch_size,
                self._batch_seen,
                window,
            )

    def _rest(self, stop: threading.Event) -> None:
        """rtf 0 and nothing moves: sleep on the job queue, repeating the streams in wall time
        (at the full rates for `rest_after` s after the last activity, then at `rest_rate`)."""
        if not self._idle:
            self._idle = True
            self._batch_seen, self._batch_size = 0, 0
            self._pacing.wake()  # a motion just ended: full rates for a while yet
            self._physics.publish_joints()  # the final state shows motion_done at once
            self._physics.publish_world()
            self._shots.at_rest()  # the release's reply, now at rest
            if self._physics.follower is not None:
                self._physics.follower.at_rest()  # an ended trajectory's, likewise
        if self._jobs.wait(self._pacing.idle_wait()):
            self._jobs.drain()  # a command that starts a motion: `run` awaits its batch
            return
        joints, world = self._pacing.beats()
        if joints:
            self._physics.publish_joints()
        if world:
            self._physics.publish_world()
