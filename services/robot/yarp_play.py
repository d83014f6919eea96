"""`TrajectoryPlayer`: the trajectories of `archery robot --body yarp` (`yarp_loop.YarpLoop`),
checked by the simulated robot's rules (`trajectory.plan_path`) and played on a thread of their
own in wall s: every `PLAY_PERIOD` s the setpoints through `IPositionControl.positionMove`
(degrees, the mapped axes), the leases checked, the encoders compared with the path (rad), the
due actions run by the robot's own archery port (`yarp_archery`). An abort holds every joint
where its encoder reads.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Mapping
from concurrent.futures import Future
from typing import Any

import numpy as np

from archery.protocol.errors import ArcheryError, Busy
from archery.protocol.robotspec import MAX_REFERENCE_SPEED, TOLERANCES
from archery.protocol.verbs import robot as rv
from archery.services.robot.commands import PartLimits
from archery.services.robot.follow import (
    GOAL_TOLERANCE,
    PATH_TOLERANCE,
    PartSpec,
    TrajectoryAborted,
)
from archery.services.robot.gate import NotOwner
from archery.services.robot.jobs import SimUnavailable
from archery.services.robot.leases import Leases
from archery.services.robot.trajectory import BadTrajectory, JointPath, plan_path
from archery.services.robot.yarp_archery import ArcheryLink
from archery.services.robot.yarp_parts import BodyError, YarpBody
from archery.services.robot.yarp_presence import BoardsLock

__all__ = ["PLAY_PERIOD", "TrajectoryPlayer"]

log = logging.getLogger("archery.robot")

PLAY_PERIOD = 0.01  # wall s between a trajectory's setpoints (`TrajectoryPlayer._play`)


class TrajectoryPlayer:
    """A YARP robot's trajectories, each played on a thread of its own (`follow`); the
    pieces it is given are the loop's (`yarp_loop.YarpLoop`), shared with it.

    Args:
        body: the robot's control boards: their encoders (rad) and axes.
        controls: each part's `IPositionControl` (a board opened again replaces its entry).
        lock: serialises the YARP calls and `targets` (the loop's lock).
        limits: each part's joint names and limits (rad), with the clamp tolerance (rad).
        targets: each part's targets (rad), updated as the setpoints go.
        leases: the parts' leases, checked at every setpoint.
        archery: the robot's own archery port, which runs a trajectory's actions (None: the
            loop refuses actions).
        start: `time.monotonic()` at the loop's start (s): the replies' times are wall s
            since then.
        closed: set once the loop closes; a trajectory playing then fails.
    """

    def __init__(
        self,
        body: YarpBody,
        controls: Mapping[str, Any],
        lock: BoardsLock,
        limits: Mapping[str, PartLimits],
        targets: Mapping[str, np.ndarray],
        leases: Leases,
        archery: ArcheryLink | None,
        start: float,
        closed: threading.Event,
    ) -> None:
        self.body = body
        self.archery = archery
        self.limits = limits
        self.leases = leases
        self._controls = controls
        self._lock = lock
        self._targets = targets
        self._start = start
        self._closed = closed
        self._playing: set[str] = set()  # the parts a trajectory moves (`follow`)

    def plays(self, part: str) -> bool:
        """Whether a trajectory moves `part` (lock held)."""
        return part in self._playing

    def follow(
        self,
        parts: list[PartSpec],
        args: rv.PartTrajectoryArgs | rv.TrajectoryArgs,
        actions: list[tuple[float, str]],
    ) -> Future[rv.TrajectoryReply]:
        """Check a trajectory by the simulated robot's rules (`trajectory.plan_path`: the
        times, the limits, `MAX_REFERENCE_SPEED`) from the joints' targets now, and play it on
        a thread of its own (`_play`) from now on, in wall s; its reply. `actions`: its
        actions' (time in s, verb), by time; the loop refused them without its archery port.
        The caller checked the leases.

        Raises:
            BadTrajectory: a rule of its form broken (nothing moves). Busy: a part plays
                another trajectory.
        """
        seen = [spec.part for spec in parts]
        if len(set(seen)) != len(seen):
            raise BadTrajectory(f"a part is named twice: {seen}")
        last = float(args.times[-1])
        for t, verb in actions:
            if not 0.0 <= t <= last:
                raise BadTrajectory(f"{verb} at {t:g} s is outside the times (0 to {last:g} s)")
        joints, lower, upper, names = self._joints(parts)
        with self._lock:
            for spec in parts:
                if spec.part in self._playing:
                    raise Busy(f"{spec.part} plays a trajectory; send the next one when it ends")
            start = np.array([self._targets[part][k] for part, k in joints])
            path = plan_path(
                start,
                args.times,
                args.positions,
                args.velocities,
                lower,
                upper,
                names,
                rv.MAX_TRAJECTORY_DURATION,
                MAX_REFERENCE_SPEED,
            )
            reply: Future[rv.TrajectoryReply] = Future()
            self._playing.update(seen)
        thread = threading.Thread(
            target=self._play,
            args=(tuple(parts), joints, path, actions, args, reply),
            name="robot yarp trajectory",
            daemon=True,
        )
        thread.start()
        return reply

    def _joints(
        self, parts: list[PartSpec]
    ) -> tuple[list[tuple[str, int]], np.ndarray, np.ndarray, list[str]]:
        """The trajectory's joints as (part, index in the part), their limits with the clamp
        tolerance (rad) and names `part.joint`.

        Raises:
            BadTrajectory: an unknown part or joint, or a joint named twice.
        """
        joints: list[tuple[str, int]] = []
        lower: list[float] = []
        upper: list[float] = []
        names: list[str] = []
        for spec in parts:
            limits = self.limits.get(spec.part)
            if limits is None:
                raise BadTrajectory(f"unknown part {spec.part!r}; parts: {', '.join(self.limits)}")
            chosen = limits.names if spec.names is None else spec.names
            if len(set(chosen)) != len(chosen):
                raise BadTrajectory(f"{spec.part}: a joint is named twice")
            unknown = [n for n in chosen if n not in limits.names]
            if unknown:
                raise BadTrajectory(
                    f"{spec.part} has no joint {unknown[0]!r}; joints: {', '.join(limits.names)}"
                )
            for name in chosen:
                k = limits.names.index(name)
                joints.append((spec.part, k))
                lower.append(limits.lower[k] - limits.tolerance)
                upper.append(limits.upper[k] + limits.tolerance)
                names.append(f"{spec.part}.{name}")
        return joints, np.array(lower), np.array(upper), names

    def _play(
        self,
        parts: tuple[PartSpec, ...],
        joints: list[tuple[str, int]],
        path: JointPath,
        actions: list[tuple[float, str]],
        args: rv.PartTrajectoryArgs | rv.TrajectoryArgs,
        reply: Future[rv.TrajectoryReply],
    ) -> None:
        """Play `path` from now (wall s): every `PLAY_PERIOD` s the setpoints `path.at(t)`
        go to the robot through `positionMove` (deg), the leases are checked (an ended or
        taken lease aborts with its code), the encoders compared with the path (more than
        `path_tolerance` rad behind: `path_tolerance`) and the due actions run (the robot's
        archery port). Once the last waypoint's time passed, the reply comes when every
        encoder lies within `TOLERANCES["rest"]` rad of the goal, else `goal_tolerance`
        `goal_time` s after it. An abort holds every joint where its encoder is."""
        started = time.monotonic()
        ran: dict[str, float] = {}
        path_error = 0.0
        pending = list(actions)
        moved = sorted({part for part, _ in joints})
        try:
            while True:
                if self._closed.is_set():
                    raise SimUnavailable("the robot stopped mid-trajectory")
                for spec in parts:
                    try:
                        self.leases.check(spec.part, spec.lease, counted=False)
                    except NotOwner as exc:
                        raise TrajectoryAborted(
                            f"{spec.part}: the lease ended mid-trajectory ({exc.message})",
                            code=exc.code,
                        ) from None
                since = time.monotonic() - started
                with self._lock:
                    read = self.body.encoders(moved)
                positions = np.array([read[part][k] for part, k in joints])
                if since <= path.duration:
                    error = float(np.max(np.abs(positions - path.at(since))))
                    path_error = max(path_error, error)
                    if error > args.path_tolerance:
                        raise TrajectoryAborted(
                            f"a joint fell {error:.3f} rad behind the trajectory at "
                            f"{since:.3f} s (path tolerance {args.path_tolerance:g} rad)",
                            code=PATH_TOLERANCE,
                        )
                while pending and pending[0][0] <= since:
                    _, verb = pending.pop(0)
                    assert self.archery is not None  # `YarpLoop.follow` refused actions without it
                    self.archery.grasp() if verb == "grasp" else self.archery.nock()
                    ran[verb] = time.monotonic() - self._start
                if since >= path.duration:
                    goal_error = float(np.max(np.abs(positions - path.goal)))
                    if goal_error <= TOLERANCES["rest"]:
                        reply.set_result(
                            rv.TrajectoryReply(
                                parts=[spec.part for spec in parts],
                                started=started - self._start,
                                ended=time.monotonic() - self._start,
                                path_error=path_error,
                                goal_error=goal_error,
                                actions=ran,
                            )
                        )
                        return
                    if since > path.duration + args.goal_time:
                        raise TrajectoryAborted(
                            f"a joint ended {goal_error:.3f} rad from the goal {args.goal_time:g} "
                            f"s after the last waypoint (rest tolerance {TOLERANCES['rest']:g} "
                            "rad)",
                            code=GOAL_TOLERANCE,
                        )
                self._setpoints(joints, path.at(since + PLAY_PERIOD))
                time.sleep(PLAY_PERIOD)
        except ArcheryError as exc:
            log.warning(
                "trajectory of %s aborted (%s): %s", ", ".join(p.part for p in parts), exc.code, exc
            )
            self._hold(joints)
            reply.set_exception(exc)
        except BaseException as exc:  # a YARP failure: the caller hears of it
            self._hold(joints)
            reply.set_exception(exc)
        finally:
            with self._lock:
                self._playing.difference_update(spec.part for spec in parts)

    def _setpoints(self, joints: list[tuple[str, int]], values: np.ndarray) -> None:
        """`values` (rad) to the joints through `positionMove` (deg); they are the targets.

        Raises:
            BodyError: the robot refuses one.
        """
        with self._lock:
            for (part, k), value in zip(joints, values, strict=True):
                axes = self.body.parts[part]
                if not self._controls[part].positionMove(axes.index[k], math.degrees(value)):
                    raise BodyError(
                        f"{axes.board} refused positionMove of {axes.joints[k]} (axis "
                        f"{axes.index[k]}) to {math.degrees(value):.2f}° mid-trajectory"
                    )
                self._targets[part][k] = value

    def _hold(self, joints: list[tuple[str, int]]) -> None:
        """Every joint of an aborted trajectory held where its encoder reads (best effort)."""
        try:
            with self._lock:
                read = self.body.encoders(sorted({part for part, _ in joints}))
            self._setpoints(joints, np.array([read[part][k] for part, k in joints]))
        except (BodyError, ArcheryError) as exc:
            log.error("the aborted trajectory's joints not held: %s", exc)
