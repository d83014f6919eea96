"""`YarpLoop`: a YARP robot's control boards (`yarp_parts.open_parts`) as the robot's handlers
see a loop (`handlers.RobotLoop`), for `archery robot --body yarp`.

Each part's joint states at `state_rate` per WALL second (`sim_time`: wall s since the start);
`positionMove`, `command:i` and trajectories (`yarp_play`: checked by `trajectory`, played on
a thread of their own in wall s) through `IPositionControl.positionMove` (degrees, the mapped
axes); reference speeds through `setRefSpeed` (deg/s). Motion done: the encoders within
`TOLERANCES["rest"]` (rad) of the last targets. The leases are the simulated robot's
(`leases`, `gate`). What needs the simulated world is refused (`Unsupported`), the archery
verbs unless the robot has its own archery port (`yarp_archery`). The body holds `yarp`.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future
from typing import Any

import numpy as np

from archery.protocol.errors import ArcheryError, BadRequest, Busy, PartLost
from archery.protocol.robotspec import MAX_REFERENCE_SPEED, REFERENCE_SPEED, TOLERANCES
from archery.protocol.text import shown
from archery.protocol.verbs import robot as rv
from archery.services.robot.commands import CommandRejected, PartCounters, PartLimits, check_command
from archery.services.robot.config import RobotConfig
from archery.services.robot.follow import PartSpec
from archery.services.robot.jobs import SimUnavailable
from archery.services.robot.leases import Leases
from archery.services.robot.sink import Sink
from archery.services.robot.yarp_archery import ArcheryLink
from archery.services.robot.yarp_parts import BodyError, YarpBody
from archery.services.robot.yarp_play import TrajectoryPlayer
from archery.services.robot.yarp_presence import BoardsLock, Presence
from archery.services.robot.yarp_shot import EventsIgnored, Shot, lab_shot
from archery.sim.scene_config import SceneConfig

__all__ = ["UNSUPPORTED", "Unsupported", "YarpLoop"]

log = logging.getLogger("archery.robot")

UNSUPPORTED = "unsupported"
RESYNC_WAIT = 2.0  # wall s a reset waits for the encoders to show the robot at its targets
_RESYNC_POLL = 0.01  # wall s between two readings meanwhile


class Unsupported(ArcheryError):
    """A verb a YARP body cannot do (yet): it needs the simulated world (arrow, bow, scene,
    simulated time), which a YARP robot's control boards do not have."""

    code = UNSUPPORTED

    def __init__(self, verb: str) -> None:
        super().__init__(
            f"a YARP body has no {verb} yet: `archery robot --body yarp` serves the parts' "
            "control boards only (joint states, limits, positionMove, trajectories, speeds, "
            "leases); the archery verbs need the simulated robot (--body mujoco)"
        )


class YarpLoop:
    """A YARP robot's parts, read at `config.state_rate` per wall second (`run`, on a thread
    of its own) and moved on request; every method may be called from any thread (the YARP
    calls are serialised by one lock).

    Args:
        body: the robot's control boards, opened by `yarp_parts.open_parts`; the loop closes
            them (`close`).
        config: state_rate (Hz, wall), limit_tolerance (rad), command_rate and command_burst.
        sink: receives the joint states (`Sink.joint_state`; no world state, no event).
        archery: the robot's own archery RPC port, which answers the archery verbs (None:
            they are refused); the loop closes it.

    Raises:
        BodyError: a part has no position control (`IPositionControl`), its first encoder
            reading is refused (`YarpBody.encoders`), or it refuses the start's reference
            speeds (`REFERENCE_SPEED`).
    """

    def __init__(
        self, body: YarpBody, config: RobotConfig, sink: Sink, archery: ArcheryLink | None = None
    ) -> None:
        self.body = body
        self.archery = archery  # the robot's own archery port: trajectories' actions need it
        #: who answers the archery verbs: the robot's own port (its landing ignored with
        #: `config.landing` "camera"), a finger release (`yarp_shot.LabShot`), or none
        self.shot: Shot | None = None
        self.config = config
        self.parts = tuple(body.parts)
        self.limits = {
            part: PartLimits(
                part=part,
                names=axes.joints,
                lower=axes.lower,
                upper=axes.upper,
                tolerance=config.limit_tolerance,
            )
            for part, axes in body.parts.items()
        }
        self._counters = {part: PartCounters() for part in self.parts}
        self.leases = Leases(self.parts, config.command_rate, config.command_burst, self._counters)
        self._sink = sink
        self._lock = BoardsLock()  # the YARP calls and the state below
        #: one publication at a time, its reading and its sending: the states leave in the order
        #: of their stamps (a reset's state is never followed by one read before it)
        self._publishing = threading.Lock()
        self._controls: dict[str, Any] = {}
        for part in self.parts:
            control = body.driver(part).viewIPositionControl()
            if control is None:
                raise BodyError(f"{body.parts[part].board} takes no position command")
            self._controls[part] = control
        self._start = time.monotonic()
        self._stamp = 0.0  # s of wall time since the start, of the reading below
        self._position = {p: np.asarray(v) for p, v in body.encoders().items()}
        self._velocity = {p: np.zeros(len(v)) for p, v in self._position.items()}
        self._targets = {p: v.copy() for p, v in self._position.items()}
        self._speeds: dict[str, list[float]] = {}
        for part in self.parts:
            self._send_speeds(part, [REFERENCE_SPEED] * len(self.limits[part].names))
        self._closed = threading.Event()
        self._player = TrajectoryPlayer(
            body,
            self._controls,
            self._lock,
            self.limits,
            self._targets,
            self.leases,
            archery,
            self._start,
            self._closed,
        )
        #: called with False when a part is lost, True when every part answers again (the
        #: service withdraws and declares its liveliness token)
        self.on_whole: Callable[[bool], None] = lambda whole: None
        self.presence = Presence(self.parts, body.timeout, lambda whole: self.on_whole(whole))
        if archery is not None:
            self.shot = EventsIgnored(archery) if config.landing == "camera" else archery
        else:
            self.shot = lab_shot(body, self._lock, self._stamp_now, config, self.lab_status)

    # -- the loop ------------------------------------------------------------------------------
    def run(self, stop: threading.Event) -> None:
        """Read every part and publish its joint state, `state_rate` times per wall second,
        until `stop` is set or the loop is closed. A reading refused (an encoder NaN, out of
        its limits) is logged once and not published; a part silent for the body's timeout is
        lost and its board opened again until it answers (`yarp_presence`)."""
        period = 1.0 / self.config.state_rate
        tick = time.monotonic()
        while not (stop.is_set() or self._closed.is_set()):
            try:
                self._publish()
                self._reopen()
            except SimUnavailable:  # closed meanwhile
                return
            tick = max(tick + period, time.monotonic())
            stop.wait(max(0.0, tick - time.monotonic()))

    def _publish(self) -> None:
        """Read every part's encoders and publish their joint states, all of one stamp."""
        with self._publishing:
            self._publish_now()

    def _publish_now(self) -> None:
        states = []
        with self._lock:
            now = time.monotonic()
            stamp = now - self._start
            for part in self.parts:
                if not self.presence.reads(part):
                    continue
                try:
                    values = self.body.read(part)
                except BodyError as exc:
                    self.presence.refused(part, str(exc))
                    continue
                if values is None:
                    self.presence.silent(part, self.body.parts[part].board, now)
                    continue
                position = np.asarray(values)
                dt = now - self.presence.read_at[part]
                if dt > 0:
                    self._velocity[part] = (position - self._position[part]) / dt
                if self.presence.read(part, now):  # back: it holds where it stands
                    self._targets[part] = position.copy()
                    self._velocity[part] = np.zeros(len(position))
                self._position[part] = position
                states.append(
                    (part, position.tolist(), self._velocity[part].tolist(), self._done(part))
                )
            self._stamp = stamp
        for part, position, velocity, done in states:  # one stamp: one time for all parts
            self._sink.joint_state(part, self.limits[part].names, position, velocity, done, stamp)

    def _reopen(self) -> None:
        """Open each lost part's board again, every `REOPEN_EVERY` s, until it answers."""
        for part in self.presence.due(time.monotonic()):
            with self._lock:
                try:
                    self.body.reopen(part)
                    control = self.body.driver(part).viewIPositionControl()
                    if control is None:
                        raise BodyError(f"{self.body.parts[part].board} takes no position command")
                    self._controls[part] = control
                    self._send_speeds(part, self._speeds[part])
                except BodyError as exc:
                    log.debug("%s not back yet: %s", part, exc)
                    continue
                self.presence.reopened(part, time.monotonic())

    def close(self) -> None:
        """End `run` and close the control boards (and YARP's network)."""
        self._closed.set()
        with self._lock.closing():
            if self.shot is not None:
                self.shot.close()
            self.body.close()

    # -- reading -------------------------------------------------------------------------------
    def _done(self, part: str) -> bool:
        """Every joint of `part` within `TOLERANCES["rest"]` rad of its target (lock held)."""
        gap = np.abs(self._position[part] - self._targets[part])
        return bool(np.all(gap <= TOLERANCES["rest"]))

    def positions(self, part: str) -> rv.PositionsReply:
        """`part`'s encoders now: positions (rad), velocities (rad/s, from the loop's last two
        readings), `sim_time`: wall s since the start.

        Raises:
            BodyError: the reading is refused (`YarpBody.encoders`).
        """
        with self._lock:
            self.presence.check(part)
            position = self.body.encoders([part])[part]
            return rv.PositionsReply(
                names=list(self.limits[part].names),
                position=list(position),
                velocity=self._velocity[part].tolist(),
                sim_time=time.monotonic() - self._start,
            )

    def targets(self, part: str) -> list[float]:
        """`part`'s last targets (rad; its encoders at the start before any move)."""
        with self._lock:
            out: list[float] = self._targets[part].tolist()
            return out

    def motion_done(self, part: str) -> bool:
        """Whether the loop's last reading of `part` lies within `TOLERANCES["rest"]` (rad) of
        its targets."""
        with self._lock:
            return self._done(part)

    def ref_speeds(self, part: str) -> list[float]:
        """`part`'s reference speeds (rad/s), as last sent."""
        with self._lock:
            return list(self._speeds[part])

    def counters(self, part: str, undecodable: int = 0) -> rv.CountersReply:
        """`part`'s command counters; never `streaming` (a YARP body keeps no stream
        watchdog); `undecodable`: counted by the service's subscription."""
        return rv.CountersReply(
            **self._counters[part].to_dict(), streaming=False, undecodable=undecodable
        )

    # -- moving --------------------------------------------------------------------------------
    def command(
        self,
        part: str,
        position: list[float],
        names: list[str] | None,
        said: str,
        batch: int = 1,
        lease: str = "",
    ) -> None:
        """A `command:i` message for `part` that passed `leases.screen`: moved at once (a
        YARP robot has no simulated time for a `batch` to start at). A command that breaks
        a rule (`commands`) or that the robot refuses is counted and logged, never applied."""
        try:
            self._move(part, position, names, said)
        except CommandRejected:
            return
        except ArcheryError as exc:
            log.warning("command on %s not sent: %s", part, exc)

    def position_move(self, part: str, position: Any, names: Any = None) -> list[float]:
        """Check the targets (rad) like a command, clamp them into the limits and send the
        named joints' (all, without names) to the robot; the part's targets. The caller
        checked the lease (`leases.check`).

        Raises:
            BadRequest: `names` is not a list; the robot refuses the move.
            CommandRejected: a command rule is broken (nothing sent).
        """
        if names is not None and not isinstance(names, list | tuple):
            raise BadRequest(f"names must be a list of joint names, got {shown(names)}")
        return self._move(part, position, names, None)

    def _move(self, part: str, position: Any, names: Any, said: str | None) -> list[float]:
        limits = self.limits[part]
        with self._lock:
            self.presence.check(part)
            if self._player.plays(part):
                raise Busy(f"{part} plays a trajectory; send the next move when it ends")
            try:
                targets, clamped = check_command(limits, self._targets[part], position, names, said)
            except CommandRejected as exc:
                n = self._counters[part].reject(exc.reason, exc.message)
                if n <= 10 or n % 100 == 0:
                    log.warning("rejected command #%d on %s (%s): %s", n, part, exc.reason, exc)
                raise
            moved = range(len(limits.names)) if names is None else map(limits.names.index, names)
            axes, control = self.body.parts[part], self._controls[part]
            for k in moved:
                if not control.positionMove(axes.index[k], math.degrees(float(targets[k]))):
                    raise self._refusal(
                        part,
                        f"{axes.board} refused positionMove of {limits.names[k]} "
                        f"(axis {axes.index[k]}) to {math.degrees(float(targets[k])):.2f}°",
                    )
                self._targets[part][k] = targets[k]
            self._counters[part].accept(clamped)
            out: list[float] = self._targets[part].tolist()
            return out

    def set_ref_speeds(self, part: str, speeds: Any) -> list[float]:
        """Set `part`'s reference speeds (rad/s: one for every joint, or one per joint), each
        in (0, MAX_REFERENCE_SPEED]; sent in deg/s. The caller checked the lease.

        Raises:
            BadRequest: the wrong number of speeds, one out of range, or the robot refuses.
        """
        n = len(self.limits[part].names)
        if isinstance(speeds, int | float) and not isinstance(speeds, bool):
            speeds = [speeds] * n
        values = [float(v) for v in speeds]
        if len(values) != n:
            raise BadRequest(f"{part} takes {n} reference speeds (rad/s), got {len(values)}")
        if not all(0 < v <= MAX_REFERENCE_SPEED for v in values):
            raise BadRequest(
                f"{part} reference speeds must be in (0, {MAX_REFERENCE_SPEED:g}] rad/s, "
                f"got {shown(values)}"
            )
        with self._lock:
            self.presence.check(part)
            try:
                self._send_speeds(part, values)
            except BodyError as exc:
                raise self._refusal(part, str(exc)) from None
            return list(self._speeds[part])

    def _refusal(self, part: str, said: str) -> ArcheryError:
        """What a refusal of `part`'s board is (lock held): `PartLost` when its encoders' stamps
        stopped too (the board is gone, not yet found lost by the loop), else `BadRequest`."""
        if self.body.stale(part):
            return PartLost(f"{part} does not answer: {said}; its encoders are silent")
        return BadRequest(said)

    def _send_speeds(self, part: str, speeds: list[float]) -> None:
        """`speeds` (rad/s) to `part`'s axes (deg/s), kept when the robot takes them all
        (lock held, or in the constructor).

        Raises:
            BodyError: the robot refuses one.
        """
        axes, control = self.body.parts[part], self._controls[part]
        for k, speed in enumerate(speeds):
            if not control.setRefSpeed(axes.index[k], math.degrees(speed)):
                raise BodyError(
                    f"{axes.board} refused the reference speed {math.degrees(speed):.1f}°/s of "
                    f"{axes.joints[k]} (axis {axes.index[k]})"
                )
        self._speeds[part] = list(speeds)

    # -- what needs the simulated world ----------------------------------------------------------
    def history(self, part: str, since: float) -> rv.HistoryReply:
        """Refused: no joint-state history is kept of a YARP body."""
        raise Unsupported("getHistory")

    def follow(
        self, parts: list[PartSpec], args: rv.PartTrajectoryArgs | rv.TrajectoryArgs
    ) -> Future[rv.TrajectoryReply]:
        """Check a trajectory by the simulated robot's rules (`trajectory.plan_path`: the
        times, the limits, `MAX_REFERENCE_SPEED`) from the joints' targets now, and play it on
        a thread of its own (`yarp_play.TrajectoryPlayer`) from now on, in wall s; its reply.
        The caller checked the leases.

        Raises:
            BadTrajectory: a rule of its form broken (nothing moves). Busy: a part plays
                another trajectory. Unsupported: archery actions without the robot's own
                archery port (`--archery-rpc`).
        """
        actions = sorted((a.t, a.verb) for a in getattr(args, "actions", ()))
        if actions and self.archery is None:
            raise ArcheryError(
                f"followTrajectory's actions ({', '.join(v for _, v in actions)}) need the "
                "robot's own archery port (`archery robot --body yarp --archery-rpc PORT`); a "
                "trajectory without actions plays on the control boards alone",
                code=UNSUPPORTED,
            )
        return self._player.follow(parts, args, actions)

    def _stamp_now(self) -> float:
        """Wall s since the loop's start."""
        return time.monotonic() - self._start

    def _shot(self, verb: str) -> Shot:
        if self.shot is None:
            raise Unsupported(verb)
        return self.shot

    def grasp(self) -> rv.GraspReply:
        """The shot's `grasp` (`yarp_shot` or the robot's own port); refused without one."""
        return self._shot("grasp").grasp()

    def nock(self) -> rv.NockReply:
        """The shot's `nock`; refused without one."""
        return self._shot("nock").nock()

    def release(self, timeout: float | None = None) -> rv.ReleaseReply:
        """The shot's `release` (the robot's own port answers once the arrow landed, within the
        link's timeout, not `timeout`; a finger release once the finger is open); refused
        without one."""
        return self._shot("release").release()

    def reset(self, seed: Any = None) -> rv.ResetReply:
        """The shot's `reset`, after which each part's targets are the robot's
        (`getTargetPositions`; its encoders where it tells none); refused without one: a real
        robot is not put back by a verb."""
        reply = self._shot("reset").reset(seed)
        self._resync_targets()
        self._publish()  # before the reply: no state of before the reset is the newest then
        return reply

    def _resync_targets(self) -> None:
        """Each part's targets from the robot's `getTargetPositions` (deg → rad), or from its
        encoders where the robot refuses; then, up to `RESYNC_WAIT` s, until the encoders show
        the robot within `TOLERANCES["passing"]` of them: a state stream lags its robot, and
        the states of before a reset would otherwise be taken for the robot's (a mover would
        plan its first move from where the robot no longer is)."""
        yarp = self.body.yarp
        with self._lock:
            answering = [part for part in self.parts if part not in self.presence.lost]
            targets = {}
            for part in answering:
                axes = self.body.parts[part]
                told = yarp.Vector(len(axes.axes))
                if self._controls[part].getTargetPositions(told.data()):
                    targets[part] = np.radians([told[k] for k in axes.index])
        deadline = time.monotonic() + RESYNC_WAIT
        while True:
            with self._lock:
                encoders = self.body.encoders(answering)
            there = all(
                np.all(np.abs(np.subtract(encoders[part], goal)) <= TOLERANCES["passing"])
                for part, goal in targets.items()
            )
            if there or time.monotonic() > deadline:
                break
            time.sleep(_RESYNC_POLL)
        with self._lock:
            for part in answering:
                self._targets[part] = np.asarray(targets.get(part, encoders[part]), dtype=float)
                self._position[part] = np.asarray(encoders[part])

    def set_wind(self, wind: Any) -> list[float]:
        """Refused: no simulated wind."""
        raise Unsupported("setWind")

    def status(self) -> rv.ArcheryStatusReply:
        """The shot's `status` (the robot's own port's: its scene, arrow, shot and simulated
        time; a finger release's: `lab_status`); refused without one."""
        return self._shot("status (its scene, arrow, shot and simulated time)").status()

    def lab_status(self, phase: str, shot: int, world: dict[str, Any]) -> rv.ArcheryStatusReply:
        """The robot's status as a body without a world tells it: wall s since the start, the
        shot's `phase` and count, the body's rates and counters, the project's scene
        (`SceneConfig`: the lab sets its target where the project's stands), `world`."""
        cfg = self.config
        with self._lock:
            done = all(self._done(part) for part in self.parts)
        return rv.ArcheryStatusReply(
            sim_time=self._stamp_now(),
            arrow="",
            phase=phase,  # type: ignore[arg-type]  # LabShot's phases: idle, nocked
            shot=shot,
            motion_done=done,
            seed=None,
            rtf=1.0,
            state_rate=cfg.state_rate,
            world_rate=0.0,
            watchdog=cfg.watchdog,
            limit_tolerance=cfg.limit_tolerance,
            timestep=0.0,
            counters={
                p: self._counters[p].to_dict() | {"streaming": False, "owner": self.leases.owner(p)}
                for p in self.parts
            },
            scene=SceneConfig().to_status(),
            world={"body": "yarp", "remote": self.body.remote} | world,
        )
