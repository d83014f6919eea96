"""The cartesian controllers' RPC verbs: one `ArmController` per arm, one `ArcheryController`
(each keeps its own solver and trajectory time, so each key has its own handlers object).

Each controller serves one `rpc:i` key, whose requests run one at a time on that key's worker
thread, so each owns its IK solver (solvers are not thread-safe). Moves of all controllers share
one lock: one motion at a time.
"""

from __future__ import annotations

import functools
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import replace
from typing import TYPE_CHECKING, Any, cast

import numpy as np

from archery.mesh.robot_client import Moved, RobotClient
from archery.protocol.errors import ArcheryError, BadRequest, ConfigError, RobotError
from archery.protocol.parts import PARTS
from archery.protocol.robotspec import CONTROLLER
from archery.protocol.verbs import NoArgs, ServedVerbs
from archery.protocol.verbs import controller as cv
from archery.protocol.verbs import robot as rv
from archery.services.controller.cartesian import (
    axis_angle,
    ik_reply,
    reference_speeds,
    rotation_vector,
)
from archery.services.controller.config import ControllerConfig
from archery.services.controller.ik import IkSolver
from archery.services.controller.model import ArmsModel
from archery.services.controller.posture import ArcheryPosture, PostureResult
from archery.services.controller.whole_shot import PARTS_MOVED, plan_whole_shot

if TYPE_CHECKING:
    from archery.services.controller.movement import Movement

__all__ = ["REST_WAIT", "ArcheryController", "ArmController", "MotionLock", "move"]

TRAJ_TIME_RANGE = cv.TRAJ_TIME_RANGE  # s of simulated time
TIMEOUT_RANGE = cv.TIMEOUT_RANGE  # wall s
REST_WAIT = 1.0  # wall s a move waits for the robot to rest before it starts from its posture


class MotionLock:
    """One move at a time across the controllers; a waiter gives up after its timeout."""

    def __init__(self) -> None:
        self._lock = threading.Lock()

    @contextmanager
    def hold(self, timeout: float) -> Iterator[None]:
        """Own the robot for one move (a context manager).

        Raises:
            ArcheryError (code "busy"): another move still runs after `timeout` wall s.
        """
        if not self._lock.acquire(timeout=timeout):
            raise ArcheryError(
                f"another move is still running after {timeout:g} s; retry later", code="busy"
            )
        try:
            yield
        finally:
            self._lock.release()


def move(
    client: RobotClient, targets: Mapping[str, float], traj_time: float, timeout: float
) -> Moved:
    """Move the joints named in `targets` {joint: rad}, only their parts, under a lease each.

    The move starts from the robot at rest (waiting up to `REST_WAIT` s for it, else from its
    newest states): each moved part's targets are its named joints' and the others' angles
    there, clipped into the part's software limits (`getLimits`), with reference speeds that
    cover every joint's distance in the trajectory time `traj_time` (s of simulated time); the
    client claims each part and sets its speeds in one round trip, commands them as one batch
    and waits until the whole robot rests at the targets (`RobotClient.move`).

    Raises:
        RobotError: kind `not_owner` (a part held by another client: "cannot move PART: …"; a
            part taken over during the move: `moved` tells where it ended), `not_reached` (not
            there within `timeout` wall s: `moved`) or `lost` (code `stale_state`, `timeout`).
    """
    parts = tuple(p for p in PARTS if any(j in targets for j in PARTS[p]))
    current = client.rested(REST_WAIT) or client.posture()
    sent: dict[str, float] = {}
    speeds: dict[str, np.ndarray] = {}
    for part in parts:
        lower, upper = client.limits(part)
        wanted = np.array([targets.get(j, current[j]) for j in PARTS[part]])
        clipped = np.clip(wanted, lower, upper)
        delta = clipped - np.array([current[j] for j in PARTS[part]])
        speeds[part] = reference_speeds(delta, traj_time)
        sent.update(zip(PARTS[part], clipped.tolist(), strict=True))
    return client.move(sent, owner=CONTROLLER, speeds=speeds, timeout=timeout)


def _move_ended(
    client: RobotClient, targets: Mapping[str, float], traj_time: float, timeout: float
) -> Moved:
    """`move`, or where it ended when it did not reach its targets (taken over, timed out)."""
    try:
        return move(client, targets, traj_time, timeout)
    except RobotError as exc:
        if isinstance(exc.moved, Moved):
            return exc.moved
        raise


def _posture_reply(
    theta: np.ndarray,
    result: PostureResult,
    theta_measured: np.ndarray,
    targets: dict[str, float],
    nock: np.ndarray | None = None,
) -> Callable[..., cv.PostureReply]:
    """The posture reply of θ (m) solved as `result` and measured as `theta_measured` (m), the
    joint `targets` (rad) sent; the move's fields are the caller's to add. With `nock` (m, the
    nock's offset from the string hand, root frame: the whole shot), θ is the arrow's and the
    hands' θ achieved and measured are told as the arrow's (the offset added)."""
    offset = np.zeros(3) if nock is None else nock
    achieved = result.theta_achieved + offset
    measured = theta_measured + offset
    return functools.partial(
        cv.PostureReply,
        q=targets,
        theta=theta.tolist(),
        theta_achieved=achieved.tolist(),
        theta_measured=measured.tolist(),
        relative_error_m=float(np.linalg.norm(theta - achieved)),
        measured_error_m=float(np.linalg.norm(theta - measured)),
        reachable=result.reachable,
        bow_hand=result.bow_hand.tolist(),
    )


def _move_reply(moved: Moved) -> dict[str, Any]:
    return {
        "reached": moved.reached,
        "reason": moved.reason,
        "wall_s": moved.wall_s,
        "sim_time": moved.sim_time,
    }


class ArmController:
    """iKin-like cartesian controller of one arm (`left_arm` or `right_arm`)."""

    def __init__(
        self,
        arm: str,
        model: ArmsModel,
        config: ControllerConfig,
        client: RobotClient,
        motion: MotionLock,
    ) -> None:
        self.arm = arm
        self._model = model
        self._config = config
        self._settings = config.ik
        self._solver = IkSolver(model, config.ik)
        self._client = client
        self._motion = motion
        self.torso = config.use_torso
        self.traj_time = config.traj_time

    def verbs(self) -> ServedVerbs:
        """The verbs of `ROBOT/cartesianController/ARM/rpc:i` (`protocol.verbs.controller`)."""
        return cv.ARM_VERBS.bind(
            cv.ASK_FOR_POSE.to(self.ask_for_pose),
            cv.GO_TO_POSE.to(self.go_to_pose),
            cv.GET_POSE.to(self.get_pose),
            cv.SET_TOLERANCE.to(self.set_tolerance),
            cv.GET_TOLERANCE.to(lambda a: self._tolerance()),
            cv.SET_TRAJ_TIME.to(self.set_traj_time),
            cv.GET_TRAJ_TIME.to(lambda a: cv.TrajTimeReply(time=self.traj_time)),
            cv.SET_DOF.to(self.set_dof),
            cv.GET_DOF.to(lambda a: self._dof()),
        )

    def _chain(self) -> tuple[str, ...]:
        return PARTS["torso"] + PARTS[self.arm]

    def _solve(self, args: cv.AskForPoseArgs | cv.GoToPoseArgs, q0: dict[str, float] | None) -> Any:
        xd = np.array(args.xd, dtype=float)
        od = rotation_vector(args.od, "od") if args.od is not None else None
        return self._solver.solve(self.arm, xd, od, q0=q0, use_torso=self.torso)

    def ask_for_pose(self, args: cv.AskForPoseArgs) -> cv.AskForPoseReply:
        """{"xd": [x, y, z] m, "od"?: [ax, ay, az, angle]} → the solution, without moving.

        Warm-started from the robot's posture when its states are fresh, else from home."""
        q0 = self._client.fresh_posture()
        result = self._solve(args, q0)
        return cv.AskForPoseReply(
            **ik_reply(result, self._chain()), warm_start="home" if q0 is None else "robot"
        )

    def go_to_pose(self, args: cv.GoToPoseArgs) -> cv.GoToPoseReply:
        """askForPose, then move the chain there and reply once the robot reports it done.

        The reply adds "reached" (False after `timeout` s, with the reason), the measured hand
        position "x_measured" (m) and its distance to xd "position_error_measured_m"."""
        timeout = self._config.motion_timeout if args.timeout is None else args.timeout
        current = self._client.posture()
        result = self._solve(args, current)
        moving = PARTS[self.arm] if not self.torso else self._chain()
        targets = {j: result.q[j] for j in moving}
        with self._motion.hold(timeout):
            moved = _move_ended(self._client, targets, self.traj_time, timeout)
        x_measured, _ = self._solver.hand_pose(moved.measured, self.arm)
        xd = np.array(args.xd, dtype=float)
        return cv.GoToPoseReply(
            **(
                ik_reply(result, self._chain())
                | {"q": {j: moved.targets.get(j, float(result.q[j])) for j in self._chain()}}
                | _move_reply(moved)
            ),
            x_measured=x_measured.tolist(),
            position_error_measured_m=float(np.linalg.norm(x_measured - xd)),
        )

    def get_pose(self, args: NoArgs) -> cv.PoseReply:
        """The hand pose now, by forward kinematics of the robot's joint states."""
        q = self._client.posture()
        x, rotation = self._solver.hand_pose(q, self.arm)
        return cv.PoseReply(
            x=x.tolist(),
            o=axis_angle(rotation),
            q={j: q[j] for j in self._chain()},
            sim_time=cast(float, self._client.joints(self.arm).sim_time),  # the robot stamps it
        )

    def _tolerance(self) -> cv.ToleranceReply:
        return cv.ToleranceReply(tolerance=self._settings.position_tolerance)

    def set_tolerance(self, args: cv.SetToleranceArgs) -> cv.ToleranceReply:
        """{"tolerance": m}: the IK position tolerance (the radius of the Eq. 9 ε-ball)."""
        try:
            settings = replace(self._settings, position_tolerance=args.tolerance)
        except ConfigError as exc:
            raise BadRequest(str(exc)) from None
        self._settings = settings
        self._solver = IkSolver(self._model, settings)
        return self._tolerance()

    def set_traj_time(self, args: cv.SetTrajTimeArgs) -> cv.TrajTimeReply:
        """{"time": s}: trajectory time of the next moves (s of simulated time)."""
        self.traj_time = args.time
        return cv.TrajTimeReply(time=self.traj_time)

    def _dof(self) -> cv.DofReply:
        joints = self._chain() if self.torso else PARTS[self.arm]
        return cv.DofReply(torso=self.torso, joints=list(joints))

    def set_dof(self, args: cv.SetDofArgs) -> cv.DofReply:
        """{"torso": bool}: solve and move the torso with the arm (True) or hold it (False)."""
        self.torso = args.torso
        return self._dof()


class ArcheryController:
    """The archery posture for θ on `ROBOT/cartesianController/archery/rpc:i`.

    Postures are solved from the reference posture (not from the robot's current one), so the
    same θ always gives the same joint targets, whatever the history.
    """

    def __init__(
        self,
        posture: ArcheryPosture,
        config: ControllerConfig,
        client: RobotClient,
        motion: MotionLock,
        movement: Callable[[], Movement] | None = None,
    ) -> None:
        self._posture = posture
        self._movement_of = movement
        self._movement_cache: Movement | None = None
        self._config = config
        self._client = client
        self._motion = motion
        self.traj_time = config.traj_time

    def verbs(self) -> ServedVerbs:
        """The verbs of the archery key (`protocol.verbs.controller`)."""
        return cv.ARCHERY_VERBS.bind(
            cv.POSTURE.to(self.posture),
            cv.SET_TRAJ_TIME.to(self.set_traj_time),
            cv.GET_TRAJ_TIME.to(lambda a: cv.TrajTimeReply(time=self.traj_time)),
            cv.STATUS.to(lambda a: self._status()),
        )

    def _status(self) -> cv.ArcheryStatusReply:
        cfg = self._posture.config
        return cv.ArcheryStatusReply(
            theta_box=cfg.theta_box,
            bow_hand=cfg.bow_hand.tolist(),
            nominal_theta=cfg.nominal_theta.tolist(),
            use_torso=cfg.use_torso,
            traj_time=self.traj_time,
            joints=list(self._posture.joints),
        )

    def set_traj_time(self, args: cv.SetTrajTimeArgs) -> cv.TrajTimeReply:
        """{"time": s}: trajectory time of the next postures (s of simulated time)."""
        self.traj_time = args.time
        return cv.TrajTimeReply(time=self.traj_time)

    def posture(self, args: cv.PostureArgs) -> cv.PostureReply:
        """{"theta": [x, y, z] m, "timeout"?: s} → move both arms (and the torso) to the
        archery posture for θ and reply once the robot reports the motion done.

        Reply: "q" (targets sent, rad), "theta_achieved" (of the solved posture, m),
        "theta_measured" (forward kinematics of the measured joints, m), "relative_error_m"
        (‖θ − θ_achieved‖), "measured_error_m" (‖θ − θ_measured‖), "reachable" (IK), "reached"
        (robot at the targets in time), "reason", "bow_hand" (m), "wall_s", "sim_time".
        """
        theta = self._posture.check_theta(args.theta)
        timeout = self._config.motion_timeout if args.timeout is None else args.timeout
        robot = self._client.status()
        shot = robot.scene.shot
        if args.shot != shot:
            raise ArcheryError(
                code="bad_state",
                message=f"the robot runs the {shot!r} shot (archery robot --shot {shot}), not the "
                f"{args.shot!r} shot asked: nothing moved",
            )
        if shot == "whole":
            return self._whole(theta, timeout, robot)
        current = self._client.posture()  # the robot must be there before anything is solved
        q0 = None if self._posture.config.use_torso else {j: current[j] for j in PARTS["torso"]}
        result = self._posture.solve_checked(theta, q0=q0)
        targets = {j: float(result.q[j]) for j in self._posture.joints}
        with self._motion.hold(timeout):
            moved = _move_ended(self._client, targets, self.traj_time, timeout)
        return _posture_reply(
            theta, result, self._posture.theta_at(moved.measured), dict(moved.targets)
        )(**_move_reply(moved))

    def _movement(self) -> Movement:
        """The demonstration's DMPs (built on the first whole shot).

        Raises:
            ArcheryError (code `bad_config`): no demonstration was given to this controller.
        """
        if self._movement_of is None:
            raise ConfigError("this controller plays no whole shot (it was given no demonstration)")
        if self._movement_cache is None:
            self._movement_cache = self._movement_of()
        return self._movement_cache

    def _whole(
        self, theta: np.ndarray, timeout: float, robot: rv.ArcheryStatusReply
    ) -> cv.PostureReply:
        """The whole shot for θ (m, the arrow's: its nock from the bow hand, where the robot
        tells the nock sits in the string hand): the demonstration's movement drawn to the
        archery posture for the hands' θ, played by the robot as one trajectory with grasp and
        nock (`whole_shot`); the reply once it has ended, as a posture's."""
        movement = self._movement()
        standing = self._client.posture()
        aimed = plan_whole_shot(movement, self._posture, theta, robot.nock_in_hand, standing)
        plan = aimed.plan
        actions = {"grasp": plan.grasp, "nock": plan.nock}
        started = time.monotonic()
        with self._motion.hold(timeout):
            reply = self._client.follow(
                PARTS_MOVED,
                plan.times,
                plan.rows,
                actions,
                owner=CONTROLLER,
                rtf=robot.rtf,
                ttl=self._config.lease_ttl,
            )
        wall = time.monotonic() - started
        goal = dict(
            zip(
                (j for part in PARTS_MOVED for j in PARTS[part]),
                plan.rows[-1].tolist(),
                strict=True,
            )
        )
        theta_measured = self._posture.theta_at(self._client.posture())
        return _posture_reply(theta, aimed.posture, theta_measured, goal, aimed.nock)(
            reached=True,
            reason="",
            wall_s=wall,
            sim_time=reply.ended,
            shot="whole",
            movement_sim_s=reply.ended - reply.started - plan.lead,
            lead_sim_s=plan.lead,
        )
