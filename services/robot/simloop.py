"""The robot's simulation thread: owns the `ArcheryWorld`, runs queued jobs, paces time, streams.

MuJoCo is not thread-safe, so one thread owns the world. Every other thread (RPC workers,
Zenoh callbacks) hands it work as a *job*, a closure queued with a future; the thread runs jobs
between physics chunks, never in the middle of one.

Pacing (`pacing`): streams on a grid of simulated time, rtf × the wall clock when rtf > 0. At
rtf 0 (default) the world runs as fast as possible while something moves (a part not done, or
an arrow in flight), its streams' grid points going out at most at their rates in wall time
too, and not at all when everything is at rest: the thread then sleeps on its job queue and
repeats the unchanged state on the streams in wall time, at their rates for `rest_after` wall
seconds after the last activity (a command, positionMove, setRefSpeeds, nock, release, reset,
wind, the end of a motion), then at `rest_rate` (a heartbeat, 10 Hz by default); any activity
brings the full rates back at once. A command
that wakes the idle robot starts the motion at once, unless it announces a batch
(`JointCommand.batch` > 1: a controller's three part commands): then the loop waits for the
rest of the batch, at most `batch_window` wall seconds, and starts them at one simulated time,
which keeps same-seed runs identical; for the same reason a release replies only once the
robot also rests after the shot (the arms settle for a few simulated ms after the landing, and a
command arriving meanwhile would start at a simulated time of the wall clock's choosing). A move
of one simulated second then takes ~10-20 ms of wall time. A world state also goes out right
after each nock, release, landing and reset.

Watchdog (`watchdog`): a streaming part (commands overtaking unfinished moves) whose commands
stop for `config.watchdog` wall seconds (default 0.1) is held at its measured positions: the
loop wakes at that deadline, even in the middle of its wait for the next paced chunk, counts a
`watchdog_trips` and publishes a `watchdog` WorldEvent naming the part. At rtf 1 the hold comes
~1 ms after the deadline and the joints stop within the servos' settling time; at rtf 0 see
`watchdog` (the wall-clock timeout is then many simulated seconds). A command under another
lease than the part's previous command (another client, `gate`) continues no stream.

Ownership and rate (`gate`): the service screens every `command:i` payload before decoding it
(`screen`: the part's running lease, the rate limit), so a refused or excess command is counted
and dropped on the receiving thread and never becomes a job: a flood of them cannot make the
loop fall behind. positionMove and setRefSpeeds check the lease too.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import replace
from typing import Any, Literal, TypeVar

import numpy as np

from mesh.jobs import JobQueue
from protocol.errors import ArcheryError, BadRequest
from protocol.text import shown
from protocol.vectors import finite_vector
from protocol.verbs import robot as rv
from protocol.verbs.robot import MAX_WIND
from services.robot.commands import CommandRejected, PartCounters, PartLimits, check_command
from services.robot.config import RobotConfig
from services.robot.gate import NOT_OWNER, NotOwner, PartGate
from services.robot.pacing import MAX_IDLE_WAIT, Pacing
from services.robot.sink import Sink
from services.robot.watchdog import StreamWatchdog
from sim.arrow import Landing, Launch
from sim.errors import StateError
from sim.world import ArcheryWorld, ArrowState

__all__ = ["SimLoop", "SimUnavailable", "phase_of"]

_SHUTTING_DOWN = "the robot is shutting down"

log = logging.getLogger("archery.robot")

T = TypeVar("T")


class SimUnavailable(ArcheryError):
    """The simulation thread is not running or did not answer in time."""

    code = "unavailable"


Phase = Literal["idle", "nocked", "flying", "stuck", "missed"]


def phase_of(world: ArcheryWorld) -> Phase:
    """The shot phase for `WorldState`: idle, nocked, flying, stuck or missed."""
    state = world.arrow_state
    if state is ArrowState.LANDED:
        landing = world.landing
        return "stuck" if landing is not None and landing.hit else "missed"
    if state is ArrowState.STOWED:
        return "idle"
    return "nocked" if state is ArrowState.NOCKED else "flying"


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
        self._pacing = Pacing(
            self._dt,
            config.state_rate,
            config.world_rate,
            config.rtf,
            rest_rate=config.rest_rate,
            rest_after=config.rest_after,
        )
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
        self._gates = {
            part: PartGate(part, config.command_rate, config.command_burst) for part in world.parts
        }
        self._streams = StreamWatchdog(world.parts, config.watchdog)
        self._stream_lease = {part: "" for part in world.parts}  # of the last stream command
        self._jobs = JobQueue(SimUnavailable, "the simulation thread")
        self._shot = 0
        self._landing_future: Future[rv.ReleaseReply] | None = None
        self._launch: Launch | None = None
        self._idle = False
        # commands (and the largest batch they announced) since the loop last came to rest
        self._batch_seen = 0
        self._batch_size = 0
        # at rtf 0, a landing's reply kept until the robot rests (`_landed`)
        self._settling: tuple[Future[rv.ReleaseReply], rv.ReleaseReply] | None = None

    # -- jobs (any thread) -----------------------------------------------------------------
    def submit(self, func: Callable[[], T]) -> Future[T]:
        """Queue `func` to run on the simulation thread; its future holds the result."""
        return self._jobs.submit(func)

    def call(self, func: Callable[[], T], timeout: float | None = None) -> T:
        """Run `func` on the simulation thread and return its result (or raise its error).

        Raises:
            SimUnavailable: the thread did not run it within `timeout` (default: the config's
                job_timeout) wall seconds, or the loop is closed.
        """
        return self._jobs.call(func, self.config.job_timeout if timeout is None else timeout)

    def close(self) -> None:
        """Refuse new jobs, fail the pending ones and wake the loop, which then ends."""
        self._jobs.close(_SHUTTING_DOWN)

    # -- the public verbs (any thread) -------------------------------------------------------
    def screen(self, part: str, payload: bytes) -> bool:
        """Whether a raw `command:i` payload for `part` may go on to be decoded (any thread):
        the part's gate refuses one without the running lease and drops one over the rate limit,
        both counted (`not_owner`, `rate_limited`), before any decoding or job (see `gate`)."""
        refused = self._gates[part].screen(payload)
        if refused is None:
            return True
        self._refuse(part, *refused)
        return False

    def command(
        self,
        part: str,
        position: list[float],
        names: list[str] | None,
        said: str,
        batch: int = 1,
        lease: str = "",
    ) -> None:
        """A `command:i` message for `part` (`said`: the part the message names; `batch`: how
        many commands, this one included, start together; `lease`: the lease id it carries);
        not awaited. The service screens each payload first (`screen`: ownership, rate limit).

        A command without the running lease is refused here, on the calling thread; the others
        go to the simulation thread. Rejections are counted and logged, never applied."""
        refusal = self._gates[part].owner_refusal(lease)
        if refusal is not None:
            self._refuse(part, NOT_OWNER, refusal)
            return
        received = time.monotonic()
        self.submit(
            lambda: self._stream_command(part, position, names, said, received, batch, lease)
        )

    def position_move(
        self, part: str, position: Any, names: Any = None, lease: str = ""
    ) -> list[float]:
        """Validate and apply targets (rad) like a command; returns the part's targets.

        Raises:
            NotOwner: another client holds the part's lease (`lease` is not the running one).
            CommandRejected: the targets break a rule (see `commands`)."""
        return self.call(lambda: self._position_move(part, position, names, lease))

    def claim(self, part: str, owner: str, ttl: float, takeover: bool = False) -> rv.LeaseReply:
        """Give `owner` the lease of `part` for `ttl` wall s (see `gate`).

        Raises:
            NotOwner: another owner's lease runs and `takeover` is False."""
        lease, took_over = self._gates[part].claim(owner, ttl, takeover)
        return rv.LeaseReply(
            lease=lease.id,
            owner=lease.owner,
            ttl=lease.ttl,
            expires_in=lease.ttl,
            took_over=took_over,
        )

    def renew_claim(self, part: str, lease_id: str) -> rv.LeaseReply:
        """Extend `part`'s running lease `lease_id` by its ttl (wall s) from now.

        Raises:
            NotOwner: that lease ended, was dropped or was taken over."""
        lease = self._gates[part].renew(lease_id)
        return rv.LeaseReply(lease=lease.id, owner=lease.owner, ttl=lease.ttl, expires_in=lease.ttl)

    def drop_claim(self, part: str, lease_id: str) -> rv.ClaimReply:
        """End `part`'s lease `lease_id` (nothing if it had ended); who holds the part now.

        Raises:
            NotOwner: another client's lease runs."""
        self._gates[part].drop(lease_id)
        return self.claim_state(part)

    def claim_state(self, part: str) -> rv.ClaimReply:
        """Who holds `part` and for how long (wall s); never the lease id."""
        lease, left = self._gates[part].holder()
        if lease is None:
            return rv.ClaimReply(held=False, owner="", ttl=0.0, expires_in=0.0)
        return rv.ClaimReply(held=True, owner=lease.owner, ttl=lease.ttl, expires_in=left)

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

    def targets(self, part: str) -> list[float]:
        """Current (clamped) targets of `part` (rad)."""
        return self.call(lambda: self.world.joint_targets(part).tolist())

    def motion_done(self, part: str) -> bool:
        """True when `part` has reached its targets and settled."""
        return self.call(lambda: self.world.motion_done(part))

    def set_ref_speeds(self, part: str, speeds: Any, lease: str = "") -> list[float]:
        """Set `part`'s reference speeds (rad/s; one number for every joint, or one per joint).

        Raises:
            NotOwner: another client holds the part's lease (`lease` is not the running one)."""
        refusal = self._gates[part].owner_refusal(lease)
        if refusal is not None:
            raise NotOwner(refusal)
        n = len(self.limits[part].names)
        if isinstance(speeds, int | float) and not isinstance(speeds, bool):
            speeds = [speeds] * n
        return self.call(lambda: self._set_ref_speeds(part, speeds))

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

    def nock(self) -> rv.NockReply:
        """Put a fresh arrow on the bow."""
        return self.call(self._nock)

    def release(self, timeout: float | None = None) -> rv.ReleaseReply:
        """Release the nocked arrow and return once it has landed (see `_landed` for the reply;
        at rtf 0, once the robot also rests after the shot).

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

    def reset(self, seed: Any = None) -> rv.ResetReply:
        """Back to the home posture at sim time 0, the arrow stowed; reseed when `seed` is set.

        Raises:
            BadRequest: the seed is not an integer >= 0. StateError: an arrow is in flight.
        """
        if seed is not None and (isinstance(seed, bool) or not isinstance(seed, int) or seed < 0):
            raise BadRequest(f"seed must be an integer >= 0 or absent, got {shown(seed)}")
        return self.call(lambda: self._reset(seed))

    def set_wind(self, wind: Any) -> list[float]:
        """Set the constant wind (m/s, root frame) of the shots launched from now on.

        An arrow already flying keeps the wind drawn at its launch; on `archery/rpc:i` the call
        waits behind a pending release anyway, like `reset`. Returns the wind now in force.

        Raises:
            BadRequest: not 3 finite numbers, or a component beyond ±MAX_WIND m/s.
        """
        vector = tuple(finite_vector("wind", wind, BadRequest, unit="m/s").tolist())
        if any(abs(v) > MAX_WIND for v in vector):
            raise BadRequest(
                f"each wind component must be within ±{MAX_WIND:g} m/s, got {shown(wind)}"
            )
        return self.call(lambda: self._set_wind(vector))

    def status(self) -> rv.ArcheryStatusReply:
        """Arrow state, sim time, shot count, counters, and the scene and world configs."""
        return self.call(self._status)

    def _refuse(self, part: str, reason: str, message: str) -> None:
        """Count a command the gate refused (any thread); logged sparingly (a flood is many)."""
        n = self._counters[part].reject(reason, message)
        if n <= 10 or n % 1000 == 0:
            log.warning("refused command #%d on %s (%s): %s", n, part, reason, message)

    # -- jobs (simulation thread) ------------------------------------------------------------
    def _validate(
        self, part: str, position: Any, names: Any, said: str | None
    ) -> tuple[np.ndarray, bool]:
        try:
            return check_command(
                self.limits[part], self.world.joint_targets(part), position, names, said
            )
        except CommandRejected as exc:
            n = self._counters[part].reject(exc.reason, exc.message)
            if n <= 10 or n % 100 == 0:
                log.warning("rejected command #%d on %s (%s): %s", n, part, exc.reason, exc.message)
            raise

    def _apply(self, part: str, targets: np.ndarray, clamped: bool) -> list[float]:
        self._counters[part].accept(clamped)
        return self.world.set_joint_targets(part, targets).tolist()

    def _stream_command(
        self,
        part: str,
        position: list[float],
        names: list[str] | None,
        said: str,
        at: float,
        batch: int = 1,
        lease: str = "",
    ) -> None:
        self._pacing.wake()
        self._batch_seen += 1
        self._batch_size = max(self._batch_size, batch)
        refusal = self._gates[part].owner_refusal(lease)  # taken over while it was queued
        if refusal is not None:
            self._refuse(part, NOT_OWNER, refusal)
            return
        try:
            targets, clamped = self._validate(part, position, names, said)
        except CommandRejected:
            return
        overtakes = not self.world.motion_done(part)
        self._apply(part, targets, clamped)
        if lease != self._stream_lease[part]:  # another client's: it continues no stream
            self._stream_lease[part] = lease
            self._streams.forget(part)
        self._streams.command(part, at, overtakes)

    def _position_move(self, part: str, position: Any, names: Any, lease: str = "") -> list[float]:
        self._pacing.wake()
        refusal = self._gates[part].owner_refusal(lease)
        if refusal is not None:
            self._refuse(part, NOT_OWNER, refusal)
            raise NotOwner(refusal)
        if names is not None and not isinstance(names, list | tuple):
            raise BadRequest(f"names must be a list of joint names, got {shown(names)}")
        targets, clamped = self._validate(part, position, names, None)
        self._streams.forget(part)
        return self._apply(part, targets, clamped)

    def _set_ref_speeds(self, part: str, speeds: Any) -> list[float]:
        self._pacing.wake()
        return self.world.set_reference_speeds(part, speeds).tolist()

    def _nock(self) -> rv.NockReply:
        self._pacing.wake()
        self.world.nock()
        t = self.world.sim_time
        self._sink.event("nocked", self._shot + 1, t)
        self._publish_world()
        return rv.NockReply(shot=self._shot + 1, arrow=self.world.arrow_state.value, sim_time=t)

    def _release(self) -> Future[rv.ReleaseReply]:
        if self._landing_future is not None:
            raise StateError("a release is already waiting for its landing")
        self._launch = self.world.launch()
        self._pacing.wake()
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
        reply = rv.ReleaseReply(
            shot=self._shot,
            outcome=landing.outcome.value,
            hit=landing.hit,
            reason=landing.reason or "",
            sim_time=landing.sim_time,
            release_sim_time=launch.sim_time,
            flight_time=landing.flight_time,
            theta=launch.theta.tolist(),
        )
        future, self._landing_future = self._landing_future, None
        if future is None:
            return
        if self.config.rtf == 0:
            # the arms may still settle from the shot (the loop steps on until they rest), and
            # the states of the rest are not out yet: a reply now would let the next command
            # land at a simulated time, or start from a posture, of the wall clock's choosing,
            # so it goes out once the robot rests and has published that (`_rest`)
            self._settling = (future, reply)
        else:
            future.set_result(reply)

    def _reset(self, seed: int | None) -> rv.ResetReply:
        self._pacing.wake()
        self.world.reset(seed)
        if seed is not None:
            self._seed = seed
        self._streams.forget()
        self._pacing.schedule(self.world.sim_time)
        self._sink.event("reset", self._shot, self.world.sim_time)
        self._publish_joints()
        self._publish_world()
        return rv.ResetReply(sim_time=self.world.sim_time, seed=seed, shot=self._shot)

    def _set_wind(self, wind: tuple[float, float, float]) -> list[float]:
        self._pacing.wake()
        self.world.config = replace(self.world.config, wind=wind)
        log.info("wind set to %s m/s", list(wind))
        return list(self.world.config.wind)

    def _status(self) -> rv.ArcheryStatusReply:
        world = self.world
        cfg = self.config
        return rv.ArcheryStatusReply(
            sim_time=world.sim_time,
            arrow=world.arrow_state.value,
            phase=phase_of(world),
            shot=self._shot,
            motion_done=world.motion_done(),
            seed=self._seed,
            rtf=cfg.rtf,
            state_rate=cfg.state_rate,
            world_rate=cfg.world_rate,
            watchdog=cfg.watchdog,
            limit_tolerance=cfg.limit_tolerance,
            timestep=self._dt,
            counters={
                p: self._counters[p].to_dict()
                | {"streaming": self._streams.streaming(p), "owner": self._owner(p)}
                for p in world.parts
            },
            scene=world.config.scene.to_dict(),
            world=world.config.to_dict(),
        )

    def _owner(self, part: str) -> str:
        lease, _ = self._gates[part].holder()
        return lease.owner if lease is not None else ""

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
        self._pacing.sent_joints()

    def _publish_world(self) -> None:
        world = self.world
        self._sink.world_state(world.qpos(), phase_of(world), self._shot, world.sim_time)
        self._pacing.sent_world()

    def _watchdog(self, now: float) -> bool:
        """Hold the parts whose command stream went stale while they still move; True if any."""
        tripped = False
        for part, age in self._streams.stale(now):
            if not self.world.motion_done(part):
                held = self.world.hold(part)
                self._counters[part].tripped()
                tripped = True
                reason = f"{part}: no command for {age:.3f} s mid-motion, held where it is"
                log.warning("%s at %s", reason, np.round(held, 4).tolist())
                self._sink.event("watchdog", self._shot, self.world.sim_time, None, reason)
        return tripped

    def _moving(self) -> bool:
        return self._landing_future is not None or not self.world.motion_done()

    def _advance(self, steps: int) -> None:
        landing = self.world.step(steps * self._dt)
        joints, world = self._pacing.due(self.world.sim_time)
        if joints:
            self._publish_joints()
        if landing is not None:
            self._landed(landing)  # publishes the world state
        elif world:
            self._publish_world()

    # -- the loop (simulation thread) --------------------------------------------------------
    def run(self, stop: threading.Event) -> None:
        """Serve jobs and advance the world until `stop` is set or the loop is closed."""
        jobs = self._jobs
        try:
            self._pacing.schedule(self.world.sim_time)
            while not stop.is_set() and not jobs.closed:
                jobs.drain()
                self._watchdog(time.monotonic())
                if self.config.rtf == 0:
                    if self._moving():
                        if self._idle:  # at rest until now: start an announced batch whole
                            self._await_batch(stop)
                        self._idle = False
                        self._advance(self._pacing.chunk(self.world.sim_time))
                    else:
                        self._rest(stop)
                    continue
                steps = self._pacing.chunk(self.world.sim_time)
                if self._sleep_until(self._pacing.wall_due(self.world.sim_time, steps), stop):
                    continue  # jobs ran meanwhile: they may have changed the world
                self._advance(steps)
        finally:
            self.close()
            future, self._landing_future = self._landing_future, None
            if future is not None and not future.done():
                future.set_exception(SimUnavailable("the robot stopped before the arrow landed"))
            settling, self._settling = self._settling, None
            if settling is not None and not settling[0].done():
                settling[0].set_result(settling[1])  # landed; the robot stopped while settling

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
                ran = self._watchdog(now) or ran
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
        self._sleep_until(
            time.monotonic() + self.config.batch_window,
            stop,
            until=lambda: self._batch_seen >= self._batch_size,
        )
        if self._batch_seen < self._batch_size:
            log.warning(
                "a batch of %d commands started with %d of them after %g s (wall): the rest will "
                "start later, at a simulated time that depends on the wall clock (same-seed runs "
                "part here)",
                self._batch_size,
                self._batch_seen,
                self.config.batch_window,
            )

    def _rest(self, stop: threading.Event) -> None:
        """rtf 0 and nothing moves: sleep on the job queue, repeating the streams in wall time
        (at the full rates for `rest_after` s after the last activity, then at `rest_rate`)."""
        if not self._idle:
            self._idle = True
            self._batch_seen, self._batch_size = 0, 0
            self._pacing.wake()  # a motion just ended: full rates for a while yet
            self._publish_joints()  # the final state shows motion_done at once
            self._publish_world()
            settling, self._settling = self._settling, None
            if settling is not None:
                settling[0].set_result(settling[1])  # the release's reply, now at rest
        if self._jobs.wait(self._pacing.idle_wait()):
            self._jobs.drain()  # a command that starts a motion: `run` awaits its batch
            return
        joints, world = self._pacing.beats()
        if joints:
            self._publish_joints()
        if world:
            self._publish_world()
