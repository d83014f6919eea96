"""Trajectories played in the robot's own loop: a `followTrajectory` request checked and
started (`start`), its joints' setpoints set at every physics step by the world
(`ArcheryWorld.play`), the chunks cut at its actions' times and its end (`cap`), and after each
chunk its tolerances, leases and actions checked (`check`). A trajectory ends with a reply
(its goal reached) or an abort that holds every part of it where it is. Simulation thread
only; times in s of simulated time, angles in rad. The rules are those of the comment above
`TrajTimes` in `protocol.verbs.robot`.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import Future
from dataclasses import dataclass, field

import numpy as np

from archery.protocol.errors import ArcheryError, Busy
from archery.protocol.robotspec import MAX_REFERENCE_SPEED
from archery.protocol.verbs import robot as rv
from archery.services.robot.commands import PartLimits
from archery.services.robot.gate import NotOwner
from archery.services.robot.jobs import SimUnavailable
from archery.services.robot.leases import Leases
from archery.services.robot.shot import Shots
from archery.services.robot.trajectory import BadTrajectory, JointPath, plan_path
from archery.sim.errors import StateError
from archery.sim.world import ArcheryWorld

__all__ = ["GOAL_TOLERANCE", "PATH_TOLERANCE", "Follower", "PartSpec", "TrajectoryAborted"]

log = logging.getLogger("archery.robot")

PATH_TOLERANCE = "path_tolerance"  # a joint fell behind the trajectory by more than allowed
GOAL_TOLERANCE = "goal_tolerance"  # the goal not reached within the goal time


class TrajectoryAborted(ArcheryError):
    """A trajectory stopped before its end; its code says why (`path_tolerance`,
    `goal_tolerance`, `not_owner`, or a failed action's)."""


@dataclass(frozen=True)
class PartSpec:
    """One part of a trajectory: its joints (None: all, YARP order) and the lease it moves
    under ("" for none)."""

    part: str
    names: tuple[str, ...] | None
    lease: str


@dataclass
class Playing:
    """A trajectory that plays: the world follows its `setpoints`."""

    parts: tuple[PartSpec, ...]
    joints: np.ndarray  # indices of the world's joint vector
    path: JointPath
    start: float  # sim s
    actions: list[tuple[float, str]]  # (s from the start, verb), those still to run, in order
    path_tolerance: float
    goal_tolerance: float
    goal_time: float
    reply: Future[rv.TrajectoryReply] = field(default_factory=Future)
    ran: dict[str, float] = field(default_factory=dict)  # verb: sim s it ran at
    path_error: float = 0.0

    def setpoints(self, sim_time: float) -> np.ndarray:
        """The joints' setpoints (rad) at `sim_time` (s)."""
        return self.path.at(sim_time - self.start)

    @property
    def names(self) -> tuple[str, ...]:
        """The parts' names."""
        return tuple(spec.part for spec in self.parts)


class Follower:
    """The trajectories the world plays.

    Args:
        world: the simulated robot.
        limits: each part's joint names, limits and clamp tolerance.
        leases: the parts' leases (a lease that ends or changes owner aborts a trajectory).
        shots: runs the actions (grasp, nock).
        published: called after an action changed the world (publishes its state).
        wait_for_rest: hold an ended trajectory's reply until the robot rests (rtf 0), as a
            landing's: the next command then finds the joints settled, not wall-clock timed.
    """

    def __init__(
        self,
        world: ArcheryWorld,
        limits: Mapping[str, PartLimits],
        leases: Leases,
        shots: Shots,
        published: Callable[[], None],
        wait_for_rest: bool = False,
    ) -> None:
        self._world = world
        self._limits = limits
        self._leases = leases
        self._shots = shots
        self._published = published
        self._wait_for_rest = wait_for_rest
        self._playing: list[Playing] = []
        self._settling: list[Playing] = []  # ended; their replies go out at rest

    def plays(self, part: str) -> bool:
        """True while a trajectory moves `part` (it then refuses other moves: `busy`)."""
        return any(part in p.names for p in self._playing)

    def start(
        self,
        parts: Sequence[PartSpec],
        args: rv.PartTrajectoryArgs | rv.TrajectoryArgs,
    ) -> Future[rv.TrajectoryReply]:
        """Check a trajectory and start it at the world's simulated time now; its reply.

        Raises:
            BadTrajectory: a rule of its form broken (nothing moves). Busy: a part plays
                another trajectory. StateError: an action the world's shot does not run.
            CommandError: an unknown part or joint.
        """
        world = self._world
        names_seen = [spec.part for spec in parts]
        if len(set(names_seen)) != len(names_seen):
            raise BadTrajectory(f"a part is named twice: {names_seen}")
        for spec in parts:
            if spec.part not in self._limits:
                raise BadTrajectory(f"unknown part {spec.part!r}; parts: {', '.join(self._limits)}")
            if self.plays(spec.part):
                raise Busy(f"{spec.part} plays a trajectory; send the next one when it ends")
        joints, lower, upper, names = self._joints(parts)
        actions = sorted((a.t, a.verb) for a in getattr(args, "actions", ()))
        if actions and world.whole is None:
            raise StateError(
                "the robot's shot is 'posture': a trajectory's grasp and nock need --shot whole"
            )
        last = float(args.times[-1])
        for t, verb in actions:
            if not 0.0 <= t <= last:
                raise BadTrajectory(f"{verb} at {t:g} s is outside the times (0 to {last:g} s)")
        path = plan_path(
            world.setpoints_of(joints),
            args.times,
            args.positions,
            args.velocities,
            lower,
            upper,
            names,
            rv.MAX_TRAJECTORY_DURATION,
            MAX_REFERENCE_SPEED,
        )
        playing = Playing(
            parts=tuple(parts),
            joints=joints,
            path=path,
            start=world.sim_time,
            actions=list(actions),
            path_tolerance=args.path_tolerance,
            goal_tolerance=args.goal_tolerance,
            goal_time=args.goal_time,
        )
        self._playing.append(playing)
        world.play(playing)
        return playing.reply

    def _joints(
        self, parts: Sequence[PartSpec]
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[str]]:
        indices: list[np.ndarray] = []
        lower: list[float] = []
        upper: list[float] = []
        names: list[str] = []
        for spec in parts:
            limits = self._limits[spec.part]
            chosen = limits.names if spec.names is None else spec.names
            if len(set(chosen)) != len(chosen):
                raise BadTrajectory(f"{spec.part}: a joint is named twice")
            unknown = [n for n in chosen if n not in limits.names]
            if unknown:
                raise BadTrajectory(
                    f"{spec.part} has no joint {unknown[0]!r}; joints: {', '.join(limits.names)}"
                )
            at = [limits.names.index(n) for n in chosen]
            indices.append(self._world.joint_indices(spec.part, list(chosen)))
            lower.extend(limits.lower[i] - limits.tolerance for i in at)
            upper.extend(limits.upper[i] + limits.tolerance for i in at)
            names.extend(f"{spec.part}.{n}" for n in chosen)
        return np.concatenate(indices), np.array(lower), np.array(upper), names

    def cap(self, steps: int, sim_time: float, dt: float) -> int:
        """`steps` (≥ 1) cut so that the chunk ends at the next action's or end's time."""
        for p in self._playing:
            for due in (*(p.start + t for t, _ in p.actions), p.start + p.path.duration):
                ahead = due - sim_time
                if ahead > 0.5 * dt:
                    steps = min(steps, max(1, math.ceil(ahead / dt - 1e-6)))
        return steps

    def check(self) -> None:
        """After a chunk: each trajectory's leases, path, due actions and goal."""
        for p in list(self._playing):
            try:
                self._check(p)
            except ArcheryError as exc:
                self._abort(p, exc)

    def _check(self, p: Playing) -> None:
        world = self._world
        for spec in p.parts:
            try:
                self._leases.check(spec.part, spec.lease, counted=False)
            except NotOwner as exc:
                raise TrajectoryAborted(
                    f"{spec.part}: the lease ended mid-trajectory ({exc.message})",
                    code=exc.code,
                ) from None
        now = world.sim_time
        since = now - p.start
        positions = world.positions_of(p.joints)
        if since <= p.path.duration:
            error = float(np.max(np.abs(positions - p.path.at(since))))
            p.path_error = max(p.path_error, error)
            if error > p.path_tolerance:
                raise TrajectoryAborted(
                    f"a joint fell {error:.3f} rad behind the trajectory at {since:.3f} s "
                    f"(path tolerance {p.path_tolerance:g} rad)",
                    code=PATH_TOLERANCE,
                )
        half = 0.5 * world.timestep
        while p.actions and p.actions[0][0] <= since + half:
            _, verb = p.actions.pop(0)
            if verb == "grasp":
                self._shots.grasp(world)
            else:
                self._shots.nock(world)
            p.ran[verb] = now
            self._published()
        if since + half < p.path.duration:
            return
        goal_error = float(np.max(np.abs(positions - p.path.goal)))
        if goal_error <= p.goal_tolerance:
            self._finish(p)
        elif since > p.path.duration + p.goal_time:
            raise TrajectoryAborted(
                f"a joint ended {goal_error:.3f} rad from the goal {p.goal_time:g} s after the "
                f"last waypoint (goal tolerance {p.goal_tolerance:g} rad)",
                code=GOAL_TOLERANCE,
            )

    def _finish(self, p: Playing) -> None:
        self._playing.remove(p)
        self._world.unplay(p)
        if self._wait_for_rest:
            self._settling.append(p)
        else:
            self._reply(p)

    def _reply(self, p: Playing) -> None:
        positions = self._world.positions_of(p.joints)
        p.reply.set_result(
            rv.TrajectoryReply(
                parts=list(p.names),
                started=p.start,
                ended=self._world.sim_time,
                path_error=p.path_error,
                goal_error=float(np.max(np.abs(positions - p.path.goal))),
                actions=p.ran,
            )
        )

    def at_rest(self) -> None:
        """The robot rests and has published so: the held replies of ended trajectories go
        out (their `ended` the simulated time of the rest)."""
        settling, self._settling = self._settling, []
        for p in settling:
            self._reply(p)

    def _abort(self, p: Playing, exc: ArcheryError) -> None:
        """Stop `p` with `exc`, every part of it held where it is."""
        if p in self._playing:
            self._playing.remove(p)
        self._world.unplay(p)
        for part in p.names:
            self._world.hold(part)
        log.warning("trajectory of %s aborted (%s): %s", ", ".join(p.names), exc.code, exc)
        if not p.reply.done():
            p.reply.set_exception(exc)

    def abort_all(self, why: str, unavailable: bool = False) -> None:
        """Abort every trajectory (a reset, `bad_state`; the loop's end, `unavailable`); those
        that ended and wait for the rest are answered now."""
        self.at_rest()
        for p in list(self._playing):
            exc: ArcheryError = SimUnavailable(why) if unavailable else StateError(why)
            self._abort(p, exc)
