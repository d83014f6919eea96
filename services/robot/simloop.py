"""The robot's simulation thread: owns the `ArcheryWorld`, runs queued jobs, paces time, streams.

MuJoCo is not thread-safe, so one thread owns the world. Every other thread (RPC workers,
Zenoh callbacks) hands it work as a *job*, a closure queued with a future; the thread runs jobs
between physics chunks, never in the middle of one.

Timing model:

* Streams are scheduled in simulated time: joint states every 1/state_rate s, the world state
  every 1/world_rate s, plus a world state right after each nock, release, landing and reset.
  Physics advances in chunks that end on the next publication (at most 20 ms of sim time).
* rtf > 0: simulated time advances continuously, at rtf × the wall clock, idle or not (a
  falling-behind simulation re-anchors rather than racing to catch up).
* rtf = 0 (default): as fast as possible while something moves (a part not done, or an arrow
  in flight) and not at all when everything is at rest: the thread then sleeps on its job
  queue and repeats the unchanged state on the streams at their rates in wall time, so
  subscribers still see a live robot. A command that wakes the idle robot starts the motion
  after `batch_window` wall seconds, together with the commands that arrived meanwhile (a
  controller's three part commands start at the same simulated time, which keeps same-seed
  runs identical). A move of one simulated second then takes ~10-20 ms of wall time.

Watchdog (wall clock, command streams only): a command on `command:i` that arrives within
`watchdog` s of the part's previous one, while the part is still moving toward that one, makes
the part *streaming* (new targets overtake the old: interpolated or teleoperated targets). A
streaming part whose next command does not arrive within `watchdog` s is stale: if it is still
moving, its targets freeze at the measured positions (counted in `watchdog_trips`); either way
the stream ends. Any other command (the first after a silence, or one sent after the previous
move was done, as a cartesian controller does) and every `positionMove` is a move, followed to
its end however long it takes.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass
from typing import Any, Protocol, TypeVar

import numpy as np

from protocol.errors import ArcheryError, BadRequest
from services.robot.commands import CommandRejected, PartCounters, PartLimits, check_command
from services.robot.config import RobotConfig
from sim.arrow import Landing, Launch
from sim.errors import StateError
from sim.world import ArcheryWorld, ArrowState

__all__ = ["MAX_CHUNK", "SimLoop", "SimUnavailable", "Sink", "phase_of"]

MAX_CHUNK = 0.02  # s of simulated time per physics chunk at most (bounds the jobs' latency)
_MAX_IDLE_WAIT = 0.1  # s of wall time between idle checks of the stop flag and the watchdog
_MAX_LAG = 0.25  # s of wall time behind the rtf schedule before re-anchoring

log = logging.getLogger("archery.robot")

T = TypeVar("T")


class SimUnavailable(ArcheryError):
    """The simulation thread is not running or did not answer in time."""

    code = "unavailable"


class Sink(Protocol):
    """Where the loop's streams go (Zenoh publishers in the service; a list in tests)."""

    def joint_state(
        self,
        part: str,
        names: tuple[str, ...],
        position: list[float],
        velocity: list[float],
        motion_done: bool,
        sim_time: float,
    ) -> None:
        """One part's joint state: positions (rad), velocities (rad/s), sim time (s)."""

    def world_state(self, qpos: np.ndarray, phase: str, shot: int, sim_time: float) -> None:
        """The scene's generalized positions, the shot phase and number, sim time (s)."""

    def event(
        self,
        kind: str,
        shot: int,
        sim_time: float,
        impact_m: list[float] | None = None,
        reason: str = "",
    ) -> None:
        """A shot event (nocked, released, landed, missed, reset); impact_m is ground truth."""


def phase_of(world: ArcheryWorld) -> str:
    """The shot phase for `WorldState`: idle, nocked, flying, stuck or missed."""
    state = world.arrow_state
    if state is ArrowState.LANDED:
        landing = world.landing
        return "stuck" if landing is not None and landing.hit else "missed"
    return {ArrowState.STOWED: "idle", ArrowState.NOCKED: "nocked"}.get(state, "flying")


@dataclass
class _Job:
    func: Callable[[], Any]
    future: Future[Any]


@dataclass
class _Stream:
    last: float | None = None  # wall time of the last accepted stream command
    streaming: bool = False


class SimLoop:
    """Runs the world on one thread (`run`); every other method may be called from any thread.

    Args:
        world: the simulated robot, owned by the loop from now on.
        config: rates, rtf, watchdog, limit tolerance, batch window, job timeout.
        sink: receives the streams and events (called on the loop's thread).
        seed: the seed the world was last reset with (reported by `status`).
    """

    def __init__(
        self, world: ArcheryWorld, config: RobotConfig, sink: Sink, seed: int | None = None
    ) -> None:
        self.world = world
        self.config = config
        self._sink = sink
        self._seed = seed
        self._dt = world.timestep
        self._max_chunk = max(1, round(MAX_CHUNK / self._dt))
        self._state_period = 1.0 / config.state_rate
        self._world_period = 1.0 / config.world_rate
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
        self._streams = {part: _Stream() for part in world.parts}
        self._jobs: deque[_Job] = deque()
        self._cond = threading.Condition()
        self._running = False
        self._closed = False
        self._shot = 0
        self._landing_future: Future[dict[str, Any]] | None = None
        self._launch: Launch | None = None
        self._next_state = 0.0  # sim time of the next joint state publication
        self._next_world = 0.0
        self._beat_state = 0.0  # wall time of the next idle repetition
        self._beat_world = 0.0
        self._idle = False

    # -- jobs (any thread) -----------------------------------------------------------------
    def submit(self, func: Callable[[], T]) -> Future[T]:
        """Queue `func` to run on the simulation thread; its future holds the result."""
        future: Future[T] = Future()
        with self._cond:
            if self._closed:
                future.set_exception(SimUnavailable("the robot is shutting down"))
                return future
            self._jobs.append(_Job(func, future))
            self._cond.notify_all()
        return future

    def call(self, func: Callable[[], T], timeout: float | None = None) -> T:
        """Run `func` on the simulation thread and return its result (or raise its error).

        Raises:
            SimUnavailable: the thread did not run it within `timeout` (default: the config's
                job_timeout) wall seconds.
        """
        wait = self.config.job_timeout if timeout is None else timeout
        future = self.submit(func)
        try:
            return future.result(wait)
        except TimeoutError:
            future.cancel()
            raise SimUnavailable(
                f"the simulation thread did not answer within {wait:g} s (running: {self._running})"
            ) from None

    def close(self) -> None:
        """Refuse new jobs and wake the loop (it ends once its `stop` event is set)."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()

    def _wait_jobs(self, timeout: float) -> bool:
        with self._cond:
            if not self._jobs and timeout > 0:
                self._cond.wait(timeout)
            return bool(self._jobs)

    def _drain(self) -> bool:
        ran = False
        while True:
            with self._cond:
                if not self._jobs:
                    return ran
                job = self._jobs.popleft()
            ran = True
            if not job.future.set_running_or_notify_cancel():
                continue
            try:
                job.future.set_result(job.func())
            except BaseException as exc:
                job.future.set_exception(exc)

    # -- the public verbs (any thread) -------------------------------------------------------
    def command(self, part: str, position: list[float], names: list[str] | None, said: str) -> None:
        """A `command:i` message for `part` (`said`: the part the message names); not awaited.

        Rejections are counted and logged, never applied."""
        received = time.monotonic()
        self.submit(lambda: self._stream_command(part, position, names, said, received))

    def position_move(self, part: str, position: Any, names: Any = None) -> list[float]:
        """Validate and apply targets (rad) like a command; returns the part's targets."""
        return self.call(lambda: self._position_move(part, position, names))

    def positions(self, part: str) -> dict[str, Any]:
        """Encoders of `part`: positions (rad), velocities (rad/s), sim time (s)."""
        world = self.world
        return self.call(
            lambda: {
                "names": list(world.joint_names(part)),
                "position": world.joint_positions(part).tolist(),
                "velocity": world.joint_velocities(part).tolist(),
                "sim_time": world.sim_time,
            }
        )

    def targets(self, part: str) -> list[float]:
        """Current (clamped) targets of `part` (rad)."""
        return self.call(lambda: self.world.joint_targets(part).tolist())

    def motion_done(self, part: str) -> bool:
        """True when `part` has reached its targets and settled."""
        return self.call(lambda: self.world.motion_done(part))

    def set_ref_speeds(self, part: str, speeds: Any) -> list[float]:
        """Set `part`'s reference speeds (rad/s; one number for every joint, or one per joint)."""
        n = len(self.limits[part].names)
        if isinstance(speeds, int | float) and not isinstance(speeds, bool):
            speeds = [speeds] * n
        return self.call(lambda: self.world.set_reference_speeds(part, speeds).tolist())

    def ref_speeds(self, part: str) -> list[float]:
        """`part`'s reference speeds (rad/s)."""
        return self.call(lambda: self.world.reference_speeds(part).tolist())

    def counters(self, part: str) -> dict[str, Any]:
        """`part`'s command counters and whether it is streaming."""
        return self.call(
            lambda: self._counters[part].to_dict() | {"streaming": self._streams[part].streaming}
        )

    def nock(self) -> dict[str, Any]:
        """Put a fresh arrow on the bow."""
        return self.call(self._nock)

    def release(self, timeout: float | None = None) -> dict[str, Any]:
        """Release the nocked arrow and return once it has landed (see `_landed` for the reply).

        Raises:
            StateError: no arrow is nocked. SimUnavailable: no landing within `timeout` wall s.
        """
        cfg = self.config
        if timeout is None:
            flight = cfg.world.max_flight_time
            timeout = cfg.job_timeout + (flight / cfg.rtf if cfg.rtf > 0 else flight)
        landing = self.call(self._release)
        try:
            return landing.result(timeout)
        except TimeoutError:
            raise SimUnavailable(f"the arrow did not land within {timeout:g} wall s") from None

    def reset(self, seed: Any = None) -> dict[str, Any]:
        """Back to the home posture at sim time 0, the arrow stowed; reseed when `seed` is set.

        Raises:
            BadRequest: the seed is not an integer >= 0. StateError: an arrow is in flight.
        """
        if seed is not None and (isinstance(seed, bool) or not isinstance(seed, int) or seed < 0):
            raise BadRequest(f"seed must be an integer >= 0 or absent, got {seed!r}")
        return self.call(lambda: self._reset(seed))

    def status(self) -> dict[str, Any]:
        """Arrow state, sim time, shot count, counters, and the scene and world configs."""
        return self.call(self._status)

    # -- jobs (simulation thread) ------------------------------------------------------------
    def _validate(
        self, part: str, position: Any, names: Any, said: str | None
    ) -> tuple[np.ndarray, bool]:
        counters = self._counters[part]
        try:
            return check_command(
                self.limits[part], self.world.joint_targets(part), position, names, said
            )
        except CommandRejected as exc:
            counters.rejected[exc.reason] += 1
            counters.last_rejection = exc.message
            total = sum(counters.rejected.values())
            if total <= 10 or total % 100 == 0:
                log.warning("rejected command #%d on %s: %s", total, part, exc.message)
            raise

    def _apply(self, part: str, targets: np.ndarray, clamped: bool) -> list[float]:
        counters = self._counters[part]
        counters.accepted += 1
        counters.clamped += int(clamped)
        return self.world.set_joint_targets(part, targets).tolist()

    def _stream_command(
        self, part: str, position: list[float], names: list[str] | None, said: str, at: float
    ) -> None:
        try:
            targets, clamped = self._validate(part, position, names, said)
        except CommandRejected:
            return
        overtakes = not self.world.motion_done(part)
        self._apply(part, targets, clamped)
        stream = self._streams[part]
        wd = self.config.watchdog
        recent = stream.last is not None and wd > 0 and at - stream.last <= wd
        stream.streaming = recent and overtakes
        stream.last = at

    def _position_move(self, part: str, position: Any, names: Any) -> list[float]:
        if names is not None and not isinstance(names, list | tuple):
            raise BadRequest(f"names must be a list of joint names, got {names!r}")
        targets, clamped = self._validate(part, position, names, None)
        self._streams[part] = _Stream()
        return self._apply(part, targets, clamped)

    def _nock(self) -> dict[str, Any]:
        self.world.nock()
        t = self.world.sim_time
        self._sink.event("nocked", self._shot + 1, t)
        self._publish_world()
        return {"shot": self._shot + 1, "arrow": self.world.arrow_state.value, "sim_time": t}

    def _release(self) -> Future[dict[str, Any]]:
        if self._landing_future is not None:
            raise StateError("a release is already waiting for its landing")
        self._launch = self.world.launch()
        self._shot += 1
        self._landing_future = Future()
        self._sink.event("released", self._shot, self.world.sim_time)
        self._publish_world()
        return self._landing_future

    def _landed(self, landing: Landing) -> None:
        """Publish the landing (ground truth only in the event) and answer the release."""
        launch = landing.launch
        self._publish_world()
        r = None if landing.r is None else landing.r.tolist()
        kind = "landed" if landing.hit else "missed"
        self._sink.event(kind, self._shot, landing.sim_time, r, landing.reason or "")
        reply = {
            "shot": self._shot,
            "outcome": landing.outcome.value,
            "hit": landing.hit,
            "reason": landing.reason or "",
            "sim_time": landing.sim_time,
            "release_sim_time": launch.sim_time,
            "flight_time": landing.flight_time,
            "theta": launch.theta.tolist(),
        }
        future, self._landing_future = self._landing_future, None
        if future is not None:
            future.set_result(reply)

    def _reset(self, seed: int | None) -> dict[str, Any]:
        self.world.reset(seed)
        if seed is not None:
            self._seed = seed
        self._streams = {part: _Stream() for part in self.world.parts}
        self._schedule()
        self._sink.event("reset", self._shot, self.world.sim_time)
        self._publish_joints()
        self._publish_world()
        return {"sim_time": self.world.sim_time, "seed": seed, "shot": self._shot}

    def _status(self) -> dict[str, Any]:
        world = self.world
        cfg = self.config
        return {
            "sim_time": world.sim_time,
            "arrow": world.arrow_state.value,
            "phase": phase_of(world),
            "shot": self._shot,
            "motion_done": world.motion_done(),
            "seed": self._seed,
            "rtf": cfg.rtf,
            "state_rate": cfg.state_rate,
            "world_rate": cfg.world_rate,
            "watchdog": cfg.watchdog,
            "limit_tolerance": cfg.limit_tolerance,
            "timestep": self._dt,
            "counters": {
                p: self._counters[p].to_dict() | {"streaming": self._streams[p].streaming}
                for p in world.parts
            },
            "scene": world.config.scene.to_dict(),
            "world": world.config.to_dict(),
        }

    # -- streams (simulation thread) ---------------------------------------------------------
    def _publish_joints(self) -> None:
        world = self.world
        t = world.sim_time
        for part in world.parts:
            self._sink.joint_state(
                part,
                self.limits[part].names,
                world.joint_positions(part).tolist(),
                world.joint_velocities(part).tolist(),
                world.motion_done(part),
                t,
            )
        self._beat_state = time.monotonic() + self._state_period

    def _publish_world(self) -> None:
        world = self.world
        self._sink.world_state(world.qpos(), phase_of(world), self._shot, world.sim_time)
        self._beat_world = time.monotonic() + self._world_period

    def _watchdog(self, now: float) -> None:
        wd = self.config.watchdog
        if wd <= 0:
            return
        for part, stream in self._streams.items():
            if stream.streaming and stream.last is not None and now - stream.last > wd:
                stream.streaming = False
                if not self.world.motion_done(part):
                    held = self.world.set_joint_targets(part, self.world.joint_positions(part))
                    self._counters[part].watchdog_trips += 1
                    log.warning(
                        "%s command stream stale for %.2f s: holding at %s",
                        part,
                        now - stream.last,
                        np.round(held, 4).tolist(),
                    )

    def _schedule(self) -> None:
        """Publications on a grid of the periods from now (the current state goes out now)."""
        t = self.world.sim_time
        self._next_state = t + self._state_period
        self._next_world = t + self._world_period

    def _moving(self) -> bool:
        return self._landing_future is not None or not self.world.motion_done()

    def _chunk(self) -> int:
        """Steps up to the next scheduled publication (at least 1, at most MAX_CHUNK)."""
        t = self.world.sim_time
        ahead = min(self._next_state, self._next_world) - t
        return min(self._max_chunk, max(1, math.ceil(ahead / self._dt - 1e-6)))

    def _advance(self, steps: int) -> None:
        world = self.world
        landing = world.step(steps * self._dt)
        t = world.sim_time
        half = 0.5 * self._dt
        if t >= self._next_state - half:
            self._publish_joints()
            self._next_state = max(self._next_state + self._state_period, t + half)
        if landing is not None:
            self._landed(landing)
        if t >= self._next_world - half:
            if landing is None:
                self._publish_world()
            self._next_world = max(self._next_world + self._world_period, t + half)

    # -- the loop (simulation thread) --------------------------------------------------------
    def run(self, stop: threading.Event) -> None:
        """Serve jobs and advance the world until `stop` is set (see the module docstring)."""
        self._running = True
        rtf = self.config.rtf
        anchor: tuple[float, float] | None = None  # (wall, sim) time pair of the rtf schedule
        try:
            self._schedule()
            while not stop.is_set():
                self._drain()
                self._watchdog(time.monotonic())
                if rtf == 0:
                    if self._moving():
                        self._idle = False
                        self._advance(self._chunk())
                    else:
                        self._rest(stop)
                    continue
                steps = self._chunk()
                sim = self.world.sim_time
                now = time.monotonic()
                if anchor is None or sim < anchor[1] or now - self._due(anchor, sim) > _MAX_LAG:
                    anchor = (now, sim)
                due = self._due(anchor, sim + steps * self._dt)
                if self._sleep_until(due, stop):
                    continue  # jobs ran meanwhile: they may have changed the world
                self._advance(steps)
        finally:
            self._running = False
            self.close()
            self._fail_pending()

    def _due(self, anchor: tuple[float, float], sim: float) -> float:
        return anchor[0] + (sim - anchor[1]) / self.config.rtf

    def _sleep_until(self, due: float, stop: threading.Event) -> bool:
        """Wait until wall time `due`, running jobs that arrive; True if any ran."""
        ran = False
        while not stop.is_set():
            remaining = due - time.monotonic()
            if remaining <= 0:
                break
            if self._wait_jobs(min(remaining, _MAX_IDLE_WAIT)):
                ran = self._drain() or ran
        return ran

    def _rest(self, stop: threading.Event) -> None:
        """rtf 0 and nothing moves: sleep on the job queue, repeating the streams in wall time."""
        if not self._idle:
            self._idle = True
            self._publish_joints()  # the final state shows motion_done at once
            self._publish_world()
        now = time.monotonic()
        wait = min(_MAX_IDLE_WAIT, self._beat_state - now, self._beat_world - now)
        if self._wait_jobs(wait):
            self._drain()
            if self._moving() and self.config.batch_window > 0:
                # Let the rest of a batch of commands arrive, to start them together.
                self._sleep_until(time.monotonic() + self.config.batch_window, stop)
            return
        now = time.monotonic()
        if now >= self._beat_state:
            self._publish_joints()
        if now >= self._beat_world:
            self._publish_world()

    def _fail_pending(self) -> None:
        with self._cond:
            jobs, self._jobs = list(self._jobs), deque()
        for job in jobs:
            if job.future.set_running_or_notify_cancel():
                job.future.set_exception(SimUnavailable("the robot is shutting down"))
        future, self._landing_future = self._landing_future, None
        if future is not None and not future.done():
            future.set_exception(SimUnavailable("the robot stopped before the arrow landed"))
