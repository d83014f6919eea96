"""The robot's RPC handlers: one method per verb of `protocol.verbs.robot` (the tables, with
docs/names.md's), served from a `RobotLoop` (the simulated robot's `SimLoop`, or a YARP body's
`yarp_loop.YarpLoop`, which refuses what needs the world) and its lease gate (`leases`).

Part verbs take the part first (bound per `ROBOT/{part}/rpc:i` key by `part_verbs`); joint
vectors are in YARP order (rad, rad/s), times in s of simulated time.
"""

from __future__ import annotations

from collections.abc import Mapping
from concurrent.futures import Future
from typing import Any, Protocol

from archery.mesh.acl import OPERATOR
from archery.mesh.rpc_server import caller, caller_left
from archery.mesh.subscription import Subscription
from archery.protocol.errors import BadRequest
from archery.protocol.messages import JointCommand
from archery.protocol.verbs import NoArgs, ServedVerbs
from archery.protocol.verbs import robot as rv
from archery.services.robot.commands import PartLimits
from archery.services.robot.config import RobotConfig
from archery.services.robot.follow import PartSpec
from archery.services.robot.gate import NotOwner
from archery.services.robot.jobs import SimUnavailable
from archery.services.robot.leases import Leases
from archery.services.robot.trajectory import BadTrajectory

__all__ = ["RobotHandlers", "RobotLoop"]


class RobotLoop(Protocol):
    """What the handlers need of a robot's loop (`simloop.SimLoop`, `yarp_loop.YarpLoop`):
    angles in rad, speeds in rad/s, times in s (each loop's docstrings say of which clock)."""

    @property
    def config(self) -> RobotConfig: ...
    @property
    def limits(self) -> Mapping[str, PartLimits]: ...
    @property
    def leases(self) -> Leases: ...
    def positions(self, part: str) -> rv.PositionsReply: ...
    def history(self, part: str, since: float) -> rv.HistoryReply: ...
    def targets(self, part: str) -> list[float]: ...
    def motion_done(self, part: str) -> bool: ...
    def set_ref_speeds(self, part: str, speeds: Any) -> list[float]: ...
    def ref_speeds(self, part: str) -> list[float]: ...
    def position_move(self, part: str, position: Any, names: Any = None) -> list[float]: ...
    def follow(
        self, parts: list[PartSpec], args: rv.PartTrajectoryArgs | rv.TrajectoryArgs
    ) -> Future[rv.TrajectoryReply]: ...
    def counters(self, part: str, undecodable: int = 0) -> rv.CountersReply: ...
    def grasp(self) -> rv.GraspReply: ...
    def nock(self) -> rv.NockReply: ...
    def release(self, timeout: float | None = None) -> rv.ReleaseReply: ...
    def reset(self, seed: Any = None) -> rv.ResetReply: ...
    def set_wind(self, wind: Any) -> list[float]: ...
    def status(self) -> rv.ArcheryStatusReply: ...


class RobotHandlers:
    """The controlboard verbs of every part and the archery verbs.

    Args:
        loop: the loop the verbs run on (the simulation's, or a YARP body's).
        commands: each part's `command:i` subscription (its undecodable count is a counter).
        secure: the mesh runs in secure mode: a lease's owner is the identity its claim names
            (`mesh.rpc_server.caller`, vouched for by the router), and only the operator takes
            a part over.
    """

    def __init__(
        self,
        loop: RobotLoop,
        commands: Mapping[str, Subscription[JointCommand]],
        secure: bool = False,
    ) -> None:
        self._loop = loop
        self._commands = commands
        self._secure = secure

    def _owner(self, claim: rv.ClaimArgs) -> str:
        """Who a claim's lease belongs to: in secure mode the caller's identity, else the
        `owner` it gives.

        Raises:
            BadRequest: secure mode, and the call names no caller.
            NotOwner: secure mode, and a takeover by another identity than the operator.
        """
        if not self._secure:
            return claim.owner
        who = caller()
        if who is None:
            raise BadRequest(
                "a claim must name its caller in secure mode (sent to PORT/VERB~IDENTITY)"
            )
        if claim.takeover and who != OPERATOR:
            raise NotOwner(f"only the {OPERATOR} takes a part over, not {who!r}")
        return who

    def part_verbs(self, part: str) -> ServedVerbs:
        """The verbs of `ROBOT/{part}/rpc:i`."""
        return rv.PART_VERBS.bind(
            rv.GET_JOINT_NAMES.to(lambda a: self.get_joint_names(part, a)),
            rv.GET_LIMITS.to(lambda a: self.get_limits(part, a)),
            rv.GET_POSITIONS.to(lambda a: self.get_positions(part, a)),
            rv.GET_HISTORY.to(lambda a: self.get_history(part, a)),
            rv.GET_TARGETS.to(lambda a: self.get_targets(part, a)),
            rv.CHECK_MOTION_DONE.to(lambda a: self.check_motion_done(part, a)),
            rv.SET_REF_SPEEDS.to(lambda a: self.set_ref_speeds(part, a)),
            rv.GET_REF_SPEEDS.to(lambda a: self.get_ref_speeds(part, a)),
            rv.POSITION_MOVE.to(lambda a: self.position_move(part, a)),
            rv.FOLLOW_PART_TRAJECTORY.to(lambda a: self.follow_part_trajectory(part, a)),
            rv.COUNTERS.to(lambda a: self.counters(part, a)),
            rv.PART_STATUS.to(lambda a: self.part_status(part, a)),
            rv.CLAIM.to(lambda a: self.claim(part, a)),
            rv.RENEW_CLAIM.to(lambda a: self.renew_claim(part, a)),
            rv.DROP_CLAIM.to(lambda a: self.drop_claim(part, a)),
            rv.GET_CLAIM.to(lambda a: self.get_claim(part, a)),
        )

    def archery_verbs(self) -> ServedVerbs:
        """The verbs of `ROBOT/archery/rpc:i`."""
        return rv.ARCHERY_VERBS.bind(
            rv.GRASP.to(self.grasp),
            rv.NOCK.to(self.nock),
            rv.RELEASE.to(self.release),
            rv.FOLLOW_TRAJECTORY.to(self.follow_trajectory),
            rv.RESET.to(self.reset),
            rv.SET_WIND.to(self.set_wind),
            rv.ARCHERY_STATUS.to(self.archery_status),
        )

    def _names(self, part: str) -> list[str]:
        return list(self._loop.limits[part].names)

    # -- controlboard verbs ------------------------------------------------------------------
    def get_joint_names(self, part: str, args: NoArgs) -> rv.JointNamesReply:
        """The part's joint names."""
        return rv.JointNamesReply(names=self._names(part))

    def get_limits(self, part: str, args: NoArgs) -> rv.LimitsReply:
        """The software joint limits (rad) and the clamping tolerance beyond them (rad)."""
        limits = self._loop.limits[part]
        return rv.LimitsReply(
            names=self._names(part),
            min=list(limits.lower),
            max=list(limits.upper),
            tolerance=limits.tolerance,
        )

    def get_positions(self, part: str, args: NoArgs) -> rv.PositionsReply:
        """Encoders: positions (rad), velocities (rad/s), sim time (s)."""
        return self._loop.positions(part)

    def get_history(self, part: str, args: rv.HistoryArgs) -> rv.HistoryReply:
        """Encoders at every joint-state period of sim time since `args.since` (s)."""
        return self._loop.history(part, args.since)

    def get_targets(self, part: str, args: NoArgs) -> rv.TargetsReply:
        """The part's current (clamped) targets (rad)."""
        return rv.TargetsReply(names=self._names(part), position=self._loop.targets(part))

    def check_motion_done(self, part: str, args: NoArgs) -> rv.MotionDoneReply:
        """Whether the part reached its targets and settled."""
        return rv.MotionDoneReply(done=self._loop.motion_done(part))

    def set_ref_speeds(self, part: str, args: rv.SetRefSpeedsArgs) -> rv.RefSpeedsReply:
        """Set the reference speeds (rad/s: one for all joints, or one per joint), after
        claiming the part when `claim` is given (a lease taken for speeds that are then refused
        is dropped again)."""
        leases = self._loop.leases
        if args.claim is None:
            leases.check(part, args.lease, counted=False)
            speeds = self._loop.set_ref_speeds(part, args.speeds)
            return rv.RefSpeedsReply(names=self._names(part), speeds=speeds)
        if args.lease:
            raise BadRequest("setRefSpeeds takes a lease or a claim, not both")
        claim = args.claim
        lease = leases.claim(part, self._owner(claim), claim.ttl, claim.takeover).lease
        try:
            speeds = self._loop.set_ref_speeds(part, args.speeds)  # under the lease just taken
        except BaseException:
            leases.drop(part, lease)
            raise
        return rv.RefSpeedsReply(names=self._names(part), speeds=speeds, lease=lease)

    def get_ref_speeds(self, part: str, args: NoArgs) -> rv.RefSpeedsReply:
        """The reference speeds (rad/s)."""
        return rv.RefSpeedsReply(names=self._names(part), speeds=self._loop.ref_speeds(part))

    def position_move(self, part: str, args: rv.PositionMoveArgs) -> rv.TargetsReply:
        """Validate and apply targets (rad) like a command; the part's targets after it."""
        self._loop.leases.check(part, args.lease)
        position = self._loop.position_move(part, args.position, args.names)
        return rv.TargetsReply(names=self._names(part), position=position)

    def follow_part_trajectory(self, part: str, args: rv.PartTrajectoryArgs) -> rv.TrajectoryReply:
        """Play the part's time-stamped waypoints in the robot's loop; replies at the end."""
        names = None if args.names is None else tuple(args.names)
        return self._follow([PartSpec(part, names, args.lease)], args)

    def follow_trajectory(self, args: rv.TrajectoryArgs) -> rv.TrajectoryReply:
        """Play several parts' waypoints and the archery actions at their times; replies at
        the end."""
        specs = [
            PartSpec(p.part, None if p.names is None else tuple(p.names), p.lease)
            for p in args.parts
        ]
        return self._follow(specs, args)

    def _follow(
        self, specs: list[PartSpec], args: rv.PartTrajectoryArgs | rv.TrajectoryArgs
    ) -> rv.TrajectoryReply:
        """Check the leases, start the trajectory and wait for its end (at most as long as
        the caller waits; when it did not say, its duration in wall time and the job timeout).

        Raises:
            NotOwner: another client holds a part. BadTrajectory, Busy, StateError: refused
            before anything moved. TrajectoryAborted: stopped on its way (parts held).
            SimUnavailable: no end in time.
        """
        for spec in specs:
            if spec.part not in self._loop.limits:
                raise BadTrajectory(f"unknown part {spec.part!r}")
            self._loop.leases.check(spec.part, spec.lease)
        reply = self._loop.follow(specs, args)
        cfg = self._loop.config
        sim_s = float(args.times[-1]) + args.goal_time
        timeout = caller_left()
        if timeout is None:
            timeout = cfg.job_timeout + (sim_s / cfg.rtf if cfg.rtf > 0 else sim_s)
        try:
            return reply.result(max(0.0, timeout))
        except TimeoutError:
            raise SimUnavailable(
                f"the trajectory had not ended after {timeout:g} wall s (it plays on)"
            ) from None

    def counters(self, part: str, args: NoArgs) -> rv.CountersReply:
        """Commands accepted, clamped and rejected (by reason), watchdog trips, undecodable."""
        return self._loop.counters(part, undecodable=self._commands[part].dropped)

    def part_status(self, part: str, args: NoArgs) -> rv.PartStatusReply:
        """Names, motion done, counters and the encoders."""
        encoders = self._loop.positions(part)
        return rv.PartStatusReply(
            part=part,
            names=self._names(part),
            motion_done=self._loop.motion_done(part),
            counters=self.counters(part, args),
            position=encoders.position,
            velocity=encoders.velocity,
            sim_time=encoders.sim_time,
        )

    def claim(self, part: str, args: rv.ClaimArgs) -> rv.LeaseReply:
        """Take the part for `ttl` wall s: only commands carrying the lease id move it."""
        return self._loop.leases.claim(part, self._owner(args), args.ttl, args.takeover)

    def renew_claim(self, part: str, args: rv.LeaseArgs) -> rv.LeaseReply:
        """Extend the running lease by its ttl (wall s) from now."""
        return self._loop.leases.renew(part, args.lease)

    def drop_claim(self, part: str, args: rv.LeaseArgs) -> rv.ClaimReply:
        """End the lease: the part takes commands from anyone again."""
        return self._loop.leases.drop(part, args.lease)

    def get_claim(self, part: str, args: NoArgs) -> rv.ClaimReply:
        """Who holds the part and for how long (wall s)."""
        return self._loop.leases.holder(part)

    # -- archery verbs -----------------------------------------------------------------------
    def grasp(self, args: NoArgs) -> rv.GraspReply:
        """Whole shot: close the right hand on the arrow (grasp_missed when off the shaft)."""
        return self._loop.grasp()

    def nock(self, args: NoArgs) -> rv.NockReply:
        """Put a fresh arrow on the bow (whole shot: the held one; nock_missed when off the
        string)."""
        return self._loop.nock()

    def release(self, args: NoArgs) -> rv.ReleaseReply:
        """Release the nocked arrow; replies once it has landed."""
        return self._loop.release()

    def reset(self, args: rv.ResetArgs) -> rv.ResetReply:
        """Home joint positions at sim time 0, the arrow stowed; reseeded when `seed` is given."""
        return self._loop.reset(args.seed)

    def set_wind(self, args: rv.SetWindArgs) -> rv.WindReply:
        """Set the constant wind (m/s, root frame) of the shots released from now on."""
        return rv.WindReply(wind=self._loop.set_wind(args.wind))

    def archery_status(self, args: NoArgs) -> rv.ArcheryStatusReply:
        """Arrow, phase, shot, sim time, counters, the scene and world configs."""
        return self._loop.status()
