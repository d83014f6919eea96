"""Verbs of the cartesian controllers: `ROBOT/cartesianController/{left_arm,right_arm}/rpc:i`
(iKin style) and `ROBOT/cartesianController/archery/rpc:i` (the archery posture for θ).

Positions are metres in `root_link`; orientations iKin axis-angle [ax, ay, az, angle (rad)].
θ is `protocol.theta.Theta`; the controller's θ box (`protocol.theta.THETA_BOX` unless it is
configured otherwise) is told by its `status` as a `ThetaBox`, which the learner reads. A
request's size and finiteness are checked where it is decoded (these types and `Args`); the box,
the zero-axis rule and reachability depend on the controller's configuration and model and are
checked by it.
"""

from __future__ import annotations

from typing import Annotated, Literal

from msgspec import Meta

from archery.protocol.theta import Theta, ThetaBox
from archery.protocol.verbs.base import Args, NoArgs, Reply, Verb, VerbTable

__all__ = [
    "ARCHERY_VERBS",
    "ARM_VERBS",
    "TIMEOUT_RANGE",
    "TRAJ_TIME_RANGE",
]

TRAJ_TIME_RANGE = (0.05, 60.0)  # s of simulated time
TIMEOUT_RANGE = (0.1, 3600.0)  # wall s
TOLERANCE_RANGE = (1e-6, 0.1)  # m

Position = Annotated[list[float], Meta(min_length=3, max_length=3, description="[x, y, z] m")]
AxisAngle = Annotated[
    list[float], Meta(min_length=4, max_length=4, description="[ax, ay, az] unit axis, angle rad")
]
TrajTime = Annotated[
    float, Meta(ge=TRAJ_TIME_RANGE[0], le=TRAJ_TIME_RANGE[1], description="s, sim time")
]
Timeout = Annotated[float, Meta(ge=TIMEOUT_RANGE[0], le=TIMEOUT_RANGE[1], description="wall s")]


# -- arms -----------------------------------------------------------------------------------------
class AskForPoseArgs(Args, frozen=True):
    xd: Position
    od: AxisAngle | None = None


class GoToPoseArgs(Args, frozen=True):
    xd: Position
    od: AxisAngle | None = None
    timeout: Timeout | None = None


class AskForPoseReply(Reply, frozen=True):
    q: Annotated[dict[str, float], Meta(description="rad")]
    x: Annotated[list[float], Meta(description="m")]
    o: Annotated[list[float], Meta(description="axis-angle")]
    position_error_m: float
    orientation_error_rad: float
    reachable: bool
    iterations: int
    warm_start: str


class GoToPoseReply(Reply, frozen=True):
    q: Annotated[dict[str, float], Meta(description="rad")]
    x: Annotated[list[float], Meta(description="m")]
    o: Annotated[list[float], Meta(description="axis-angle")]
    position_error_m: float
    orientation_error_rad: float
    reachable: bool
    iterations: int
    reached: bool
    reason: str
    wall_s: float
    sim_time: float
    x_measured: Annotated[list[float], Meta(description="m")]
    position_error_measured_m: float


class PoseReply(Reply, frozen=True):
    x: Annotated[list[float], Meta(description="m")]
    o: Annotated[list[float], Meta(description="axis-angle")]
    q: Annotated[dict[str, float], Meta(description="rad")]
    sim_time: float


class SetToleranceArgs(Args, frozen=True):
    tolerance: Annotated[float, Meta(ge=TOLERANCE_RANGE[0], le=TOLERANCE_RANGE[1], description="m")]


class ToleranceReply(Reply, frozen=True):
    tolerance: Annotated[float, Meta(description="m")]


class SetTrajTimeArgs(Args, frozen=True):
    time: TrajTime


class TrajTimeReply(Reply, frozen=True):
    time: Annotated[float, Meta(description="s, sim time")]


class SetDofArgs(Args, frozen=True):
    torso: bool


class DofReply(Reply, frozen=True):
    torso: bool
    joints: list[str]


SET_TRAJ_TIME = Verb(
    "setTrajTime", SetTrajTimeArgs, TrajTimeReply, "set the trajectory time of next moves"
)
GET_TRAJ_TIME = Verb(
    "getTrajTime",
    NoArgs,
    TrajTimeReply,
    "trajectory time of the next moves",
    blocking=False,
    reads=True,
)
_TRAJ = (SET_TRAJ_TIME, GET_TRAJ_TIME)  # both tables serve them

ASK_FOR_POSE = Verb(
    "askForPose",
    AskForPoseArgs,
    AskForPoseReply,
    "solve IK for a pose, without moving",
    reads=True,
)

GO_TO_POSE = Verb(
    "goToPose", GoToPoseArgs, GoToPoseReply, "solve IK and move there; replies when done"
)

GET_POSE = Verb("getPose", NoArgs, PoseReply, "the hand pose now (forward kinematics)", reads=True)

SET_TOLERANCE = Verb("setTolerance", SetToleranceArgs, ToleranceReply, "IK position tolerance")

GET_TOLERANCE = Verb(
    "getTolerance",
    NoArgs,
    ToleranceReply,
    "IK position tolerance",
    blocking=False,
    reads=True,
)

SET_DOF = Verb("setDOF", SetDofArgs, DofReply, "solve and move the torso with the arm, or hold it")

GET_DOF = Verb(
    "getDOF",
    NoArgs,
    DofReply,
    "whether the torso moves, and the moving joints",
    blocking=False,
    reads=True,
)

ARM_VERBS = VerbTable(
    "cartesian controller of one arm",
    ("cartesianController/left_arm/rpc:i", "cartesianController/right_arm/rpc:i"),
    (
        ASK_FOR_POSE,
        GO_TO_POSE,
        GET_POSE,
        SET_TOLERANCE,
        GET_TOLERANCE,
        *_TRAJ,
        SET_DOF,
        GET_DOF,
    ),
)


# -- archery --------------------------------------------------------------------------------------
class PostureArgs(Args, frozen=True):
    """θ: 3 finite numbers (`Args` refuses NaN and inf); its box is the controller's.

    `shot`: the robot's shot the posture is for. "posture": both arms (and the torso) straight
    into the archery posture for θ, the paper's robot with the arrow put on the bow. "whole": on
    a `--shot whole` robot, the demonstration's movement (reach, grasp, carry, nock, draw) played
    as one trajectory whose draw ends in that same posture, grasp and nock at their demonstrated
    times. A shot the robot does not run is refused (`bad_state`, naming the robot's)."""

    theta: Theta
    timeout: Timeout | None = None
    shot: Literal["posture", "whole"] = "posture"


class PostureReply(Reply, frozen=True):
    q: Annotated[dict[str, float], Meta(description="rad")]
    theta: Theta
    theta_achieved: Theta
    theta_measured: Theta
    relative_error_m: float
    measured_error_m: float
    reachable: bool
    bow_hand: Annotated[list[float], Meta(description="m")]
    reached: bool
    reason: str
    wall_s: float
    sim_time: float
    shot: str = "posture"
    movement_sim_s: Annotated[
        float,
        Meta(description="whole shot: s of sim time from the demonstrated start to the draw's end"),
    ] = 0.0
    lead_sim_s: Annotated[
        float,
        Meta(description="whole shot: s of sim time from where the robot stood to that start"),
    ] = 0.0


class ArcheryStatusReply(Reply, frozen=True):
    theta_box: ThetaBox
    bow_hand: Annotated[list[float], Meta(description="m")]
    nominal_theta: Theta
    use_torso: bool
    traj_time: Annotated[float, Meta(description="s, sim time")]
    joints: list[str]


POSTURE = Verb("posture", PostureArgs, PostureReply, "move both arms to the posture for θ")

STATUS = Verb(
    "status",
    NoArgs,
    ArcheryStatusReply,
    "θ box, bow hand, joints, trajectory time",
    blocking=False,
    reads=True,
)

ARCHERY_VERBS = VerbTable(
    "cartesian controller: archery posture",
    ("cartesianController/archery/rpc:i",),
    (
        POSTURE,
        *_TRAJ,
        STATUS,
    ),
)
