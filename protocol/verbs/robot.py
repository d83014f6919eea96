"""Verbs of the simulated robot: the controlboards `ROBOT/{part}/rpc:i` and `ROBOT/archery/rpc:i`.

Joint vectors are in YARP order, in rad (rad/s for speeds). Limits that depend on the loaded
model (joint limits, joint names) are checked by the robot itself. A client takes a part with
`claim` and gets a lease id that its commands carry (the comment above `CLAIM` tells the rules;
docs/names.md tells them from the user's side).
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from msgspec import Meta

from archery.protocol.messages import MAX_LEASE_ID
from archery.protocol.parts import PARTS
from archery.protocol.robotspec import LEASE_TTL, LEASE_TTL_RANGE, MAX_REFERENCE_SPEED
from archery.protocol.theta import Theta
from archery.protocol.verbs.base import Args, NoArgs, Reply, Verb, VerbTable

__all__ = [
    "ARCHERY_VERBS",
    "HISTORY_SPAN",
    "MAX_HISTORY_POINTS",
    "MAX_TRAJECTORY_DURATION",
    "MAX_TRAJECTORY_POINTS",
    "MAX_WIND",
    "PART_VERBS",
    "TRAJECTORY_ACTIONS",
]

MAX_JOINTS = 64
MAX_WIND = 50.0  # m/s, per axis
#: A trajectory's most waypoints (one message; a 10 s movement at 100 points/s fits twice over)
MAX_TRAJECTORY_POINTS = 2000
MAX_TRAJECTORY_DURATION = 120.0  # s of simulated time from a trajectory's start to its last point
#: The archery verbs a multi-part trajectory may run at a time of its own (`TrajectoryAction`)
TRAJECTORY_ACTIONS = ("grasp", "nock")
#: s of simulated time a part's joint-state history keeps (`getHistory`): a demonstration's
#: longest movement (`protocol.demonstration.MAX_DURATION`, 60 s) and some
HISTORY_SPAN = 65.0
MAX_STATE_RATE = 1000.0  # Hz of simulated time: the fastest joint-state grid (`--state-rate`)
MAX_HISTORY_POINTS = int(HISTORY_SPAN * MAX_STATE_RATE) + 1

Speed = Annotated[float, Meta(gt=0.0, le=MAX_REFERENCE_SPEED, description="rad/s")]
Joints = Annotated[list[float], Meta(min_length=1, max_length=MAX_JOINTS, description="rad")]
JointNames = Annotated[list[str], Meta(min_length=1, max_length=MAX_JOINTS)]
LeaseId = Annotated[
    str,
    Meta(max_length=MAX_LEASE_ID, description='the id `claim` returned; "" for none'),
]
Owner = Annotated[
    str,
    Meta(
        min_length=1,
        max_length=64,
        pattern=r"^[A-Za-z0-9_.:@-]+$",
        description="who claims: a service or a person (letters, digits, _ . : @ -)",
    ),
]
Ttl = Annotated[
    float,
    Meta(
        ge=LEASE_TTL_RANGE[0],
        le=LEASE_TTL_RANGE[1],
        description=f"wall s the lease lasts unless renewed (default {LEASE_TTL:g})",
    ),
]


# -- controlboard ---------------------------------------------------------------------------------
class JointNamesReply(Reply, frozen=True):
    names: list[str]


class LimitsReply(Reply, frozen=True):
    names: list[str]
    min: Annotated[list[float], Meta(description="rad")]
    max: Annotated[list[float], Meta(description="rad")]
    tolerance: Annotated[float, Meta(description="rad")]


class PositionsReply(Reply, frozen=True):
    names: list[str]
    position: Annotated[list[float], Meta(description="rad")]
    velocity: Annotated[list[float], Meta(description="rad/s")]
    sim_time: Annotated[float, Meta(description="s")]


class HistoryArgs(Args, frozen=True):
    """The joint-state history from `since` (s of simulated time) on."""

    since: Annotated[float, Meta(ge=0.0, description="s of sim time")] = 0.0


class HistoryReply(Reply, frozen=True):
    """The part's encoder positions (rad, `names` in YARP order) at `times` (s of simulated
    time, increasing, one joint-state period apart)."""

    names: list[str]
    times: Annotated[list[float], Meta(max_length=MAX_HISTORY_POINTS, description="s of sim time")]
    positions: Annotated[list[Joints], Meta(max_length=MAX_HISTORY_POINTS)]


class TargetsReply(Reply, frozen=True):
    names: list[str]
    position: Annotated[list[float], Meta(description="rad")]


class MotionDoneReply(Reply, frozen=True):
    done: bool


class ClaimArgs(Args, frozen=True):
    """`takeover`: take the part even from another owner whose lease still runs (the operator's
    explicit override); without it such a claim is refused (`not_owner`). A claim by the owner
    that holds the part (the same name, e.g. a restarted controller) replaces its lease. In
    secure mode the owner is the caller's identity (`owner` is not used) and only the operator
    may take over."""

    owner: Owner
    ttl: Ttl = LEASE_TTL
    takeover: bool = False


class SetRefSpeedsArgs(Args, frozen=True):
    """`claim`: claim the part first, as the `claim` verb does, in the same round trip (the
    reply carries the new lease; `lease` must then be empty): a move takes its lease and sets
    its speeds with one call per part."""

    speeds: Speed | Annotated[list[Speed], Meta(min_length=1, max_length=MAX_JOINTS)]
    lease: LeaseId = ""
    claim: ClaimArgs | None = None


class RefSpeedsReply(Reply, frozen=True, omit_defaults=True):
    """`lease`: the lease a claiming call took (left out otherwise, and by a robot that keeps no
    leases)."""

    names: list[str]
    speeds: Annotated[list[float], Meta(description="rad/s")]
    lease: str = ""


class PositionMoveArgs(Args, frozen=True):
    position: Joints
    names: JointNames | None = None
    lease: LeaseId = ""


class CountersReply(Reply, frozen=True):
    accepted: int
    clamped: int
    rejected: int
    rejected_by_reason: dict[str, int]
    watchdog_trips: int
    last_rejection: str
    streaming: bool
    undecodable: int


class PartStatusReply(Reply, frozen=True):
    part: str
    names: list[str]
    motion_done: bool
    counters: CountersReply
    position: Annotated[list[float], Meta(description="rad")]
    velocity: Annotated[list[float], Meta(description="rad/s")]
    sim_time: Annotated[float, Meta(description="s")]


class LeaseArgs(Args, frozen=True):
    lease: Annotated[str, Meta(min_length=1, max_length=MAX_LEASE_ID)]


class LeaseReply(Reply, frozen=True):
    """A lease granted or renewed: its id (carry it in `JointCommand.lease`), its owner, its
    duration and the wall time left; `took_over`: the owner whose running lease a takeover
    ended ("" when none)."""

    lease: str
    owner: str
    ttl: Annotated[float, Meta(description="wall s")]
    expires_in: Annotated[float, Meta(description="wall s")]
    took_over: str = ""


class ClaimReply(Reply, frozen=True):
    """Who holds the part now (never the lease id): `held` False when nobody does."""

    held: bool
    owner: str
    ttl: Annotated[float, Meta(description="wall s; 0 when not held")]
    expires_in: Annotated[float, Meta(description="wall s; 0 when not held")]


# -- trajectories ---------------------------------------------------------------------------------
# A trajectory is one message: time-stamped waypoints the robot interpolates in its own loop, at
# its physics rate (as ros2_control's joint trajectory controller does): quintic between two
# waypoints, the velocity given at each one (or, when `velocities` is left out, the central
# difference of its neighbours, zero at the last point), the acceleration zero there; so a
# waypoint to waypoint move from rest and back to rest is a minimum-jerk one, as iCub's position
# control makes. It starts from where each part's setpoints are, at rest, at the simulated time
# it is accepted; `times` are s of simulated time from then. While it plays, a joint farther than
# `path_tolerance` (rad) from where the trajectory wants it aborts it (`path_tolerance`: the part
# fell behind), as does a part's lease ending or another owner's (`not_owner`) or a failed
# action (its code: `grasp_missed`, `nock_missed`); an abort holds every part of it where it is.
# After its last point every joint must be within `goal_tolerance` (rad) of it within
# `goal_time` s, else `goal_tolerance`. A trajectory that breaks a rule of its form
# (times not increasing from > 0, NaN, more than MAX_TRAJECTORY_POINTS, a joint of another
# part, outside the limits, rows of the wrong length, an action outside the times, a joint
# faster than `MAX_REFERENCE_SPEED`, the speed bound `positionMove` keeps: |Δq|/Δt from the
# waypoint before, the first from the setpoint at the start, or a velocity given) is refused
# with `bad_trajectory` before anything moves. A new trajectory or command for a part that plays
# one is refused (`busy`) until it ends. The reply comes once it has ended (at rtf 0 once the
# robot also rests, as a release's: `ended` is then that simulated time): a waiting verb, so
# the caller's timeout must cover its duration in wall time (duration ÷ rtf).
TrajTimes = Annotated[
    list[float],
    Meta(min_length=1, max_length=MAX_TRAJECTORY_POINTS, description="s of sim time from start"),
]
TrajRows = Annotated[list[Joints], Meta(min_length=1, max_length=MAX_TRAJECTORY_POINTS)]
PathTolerance = Annotated[float, Meta(gt=0.0, le=3.2, description="rad")]
GoalTime = Annotated[float, Meta(ge=0.0, le=10.0, description="s of sim time")]


class TrajectoryAction(Args, frozen=True):
    """An archery verb the robot runs when the trajectory's time reaches `t` (s from its
    start): `grasp` closes the right hand on the arrow, `nock` puts the held arrow on the string
    (their rules are those of the verbs)."""

    t: Annotated[float, Meta(ge=0.0, description="s of sim time from the start")]
    verb: Literal["grasp", "nock"]


class TrajectoryPart(Args, frozen=True):
    """One part of a multi-part trajectory: its joints (`names`, a subset in YARP order; None:
    all of them) and the lease it moves under ("" where the part holds none)."""

    part: Annotated[str, Meta(max_length=32)]
    names: JointNames | None = None
    lease: LeaseId = ""


class PartTrajectoryArgs(Args, frozen=True):
    """A trajectory of one part (`ROBOT/{part}/rpc:i followTrajectory`): `positions[i]` (rad)
    and `velocities[i]` (rad/s) are the joints of `names` (None: all, YARP order) at
    `times[i]`."""

    times: TrajTimes
    positions: TrajRows
    velocities: TrajRows | None = None
    names: JointNames | None = None
    lease: LeaseId = ""
    path_tolerance: PathTolerance = 0.25
    goal_tolerance: PathTolerance = 0.02
    goal_time: GoalTime = 1.0


class TrajectoryArgs(Args, frozen=True):
    """A trajectory of several parts at once (`ROBOT/archery/rpc:i followTrajectory`): each row
    holds the joints of `parts` one part after the other; `actions` run at their times."""

    parts: Annotated[list[TrajectoryPart], Meta(min_length=1, max_length=len(PARTS))]
    times: TrajTimes
    positions: TrajRows
    velocities: TrajRows | None = None
    actions: Annotated[tuple[TrajectoryAction, ...], Meta(max_length=8)] = ()
    path_tolerance: PathTolerance = 0.25
    goal_tolerance: PathTolerance = 0.02
    goal_time: GoalTime = 1.0


class TrajectoryReply(Reply, frozen=True):
    """A trajectory played to its end: the simulated times it started and settled at, how far
    a joint fell behind at worst on the way and ended from its goal (rad), and the simulated
    time each action ran at."""

    parts: list[str]
    started: Annotated[float, Meta(description="s, sim time")]
    ended: Annotated[float, Meta(description="s, sim time")]
    path_error: Annotated[float, Meta(description="rad")]
    goal_error: Annotated[float, Meta(description="rad")]
    actions: Annotated[dict[str, float], Meta(description="verb: s, sim time")]


FOLLOW_PART_TRAJECTORY = Verb(
    "followTrajectory",
    PartTrajectoryArgs,
    TrajectoryReply,
    "play time-stamped waypoints in the robot's loop; replies once they have ended",
    waits=True,
)

GET_JOINT_NAMES = Verb(
    "getJointNames",
    NoArgs,
    JointNamesReply,
    "the part's joint names, in YARP order",
    blocking=False,
    reads=True,
)

GET_LIMITS = Verb(
    "getLimits",
    NoArgs,
    LimitsReply,
    "software joint limits (rad) and clamp tolerance",
    blocking=False,
    reads=True,
)

GET_POSITIONS = Verb(
    "getPositions",
    NoArgs,
    PositionsReply,
    "encoders: positions, velocities, sim time",
    reads=True,
)

# The joint-state history: the encoders at every point of the joint-state grid (`--state-rate`
# per simulated second) over the last HISTORY_SPAN s of simulated time, whatever the rtf. At rtf 0
# the `state:o` streams go out at most `--state-rate` times per wall second, so a movement that
# runs faster than the wall clock skips grid points there; a recording of it (`archery
# demonstrate`) reads them here, after the movement. A reset (sim time 0) clears it.
GET_HISTORY = Verb(
    "getHistory",
    HistoryArgs,
    HistoryReply,
    "encoders at every joint-state period of sim time since `since` (the last 65 s)",
    reads=True,
)

GET_TARGETS = Verb(
    "getTargets", NoArgs, TargetsReply, "the current (clamped) position targets", reads=True
)

CHECK_MOTION_DONE = Verb(
    "checkMotionDone",
    NoArgs,
    MotionDoneReply,
    "True once every joint has settled",
    reads=True,
)

SET_REF_SPEEDS = Verb(
    "setRefSpeeds",
    SetRefSpeedsArgs,
    RefSpeedsReply,
    "reference speeds: one for every joint, or one per joint",
    names_caller=True,  # it may claim the part
)

GET_REF_SPEEDS = Verb("getRefSpeeds", NoArgs, RefSpeedsReply, "the reference speeds", reads=True)

POSITION_MOVE = Verb(
    "positionMove",
    PositionMoveArgs,
    TargetsReply,
    "move to targets, validated like a command (names: a subset of joints)",
)

COUNTERS = Verb(
    "counters",
    NoArgs,
    CountersReply,
    "command counters: accepted, clamped, rejected",
    reads=True,
)

PART_STATUS = Verb(
    "status",
    NoArgs,
    PartStatusReply,
    "names, motion done, counters and encoders",
    reads=True,
)

# Ownership: a client takes a part with `claim {owner, ttl?, takeover?}` and gets a lease id;
# while the lease lasts (`ttl` wall s from the claim or the latest `renewClaim`) the part obeys
# only commands that carry it (`JointCommand.lease`, and the `lease` argument of `positionMove`
# and `setRefSpeeds`); `dropClaim` ends it, and `getClaim` tells who holds the part (never the
# lease id). With no lease held a part takes commands from anyone. In secure mode the owner is
# the caller's identity, vouched for by the router (`claim` and `setRefSpeeds` name their
# caller: `Verb.names_caller`), not the `owner` it writes, and only the `operator` takes a part
# over.
CLAIM = Verb(
    "claim",
    ClaimArgs,
    LeaseReply,
    "take the part: only commands with the lease id move it until the lease ends",
    blocking=False,
    names_caller=True,  # the lease's owner
)

RENEW_CLAIM = Verb(
    "renewClaim",
    LeaseArgs,
    LeaseReply,
    "extend the lease by its ttl from now (not_owner once it ended)",
    blocking=False,
)

DROP_CLAIM = Verb(
    "dropClaim",
    LeaseArgs,
    ClaimReply,
    "end the lease: the part takes commands from anyone again",
    blocking=False,
)

GET_CLAIM = Verb(
    "getClaim",
    NoArgs,
    ClaimReply,
    "who holds the part, for how long",
    blocking=False,
    reads=True,
)

PART_VERBS = VerbTable(
    "robot controlboard",
    tuple(f"{part}/rpc:i" for part in PARTS),
    (
        GET_JOINT_NAMES,
        GET_LIMITS,
        GET_POSITIONS,
        GET_HISTORY,
        GET_TARGETS,
        CHECK_MOTION_DONE,
        SET_REF_SPEEDS,
        GET_REF_SPEEDS,
        POSITION_MOVE,
        FOLLOW_PART_TRAJECTORY,
        COUNTERS,
        PART_STATUS,
        CLAIM,
        RENEW_CLAIM,
        DROP_CLAIM,
        GET_CLAIM,
    ),
)


# -- archery --------------------------------------------------------------------------------------
class NockReply(Reply, frozen=True):
    shot: int
    arrow: str
    sim_time: Annotated[float, Meta(description="s")]


class GraspReply(Reply, frozen=True):
    """A grasp that holds: the grasp site's distance from the arrow's shaft and the tolerance it
    was within."""

    arrow: str
    distance: Annotated[float, Meta(description="m")]
    tolerance: Annotated[float, Meta(description="m")]
    sim_time: Annotated[float, Meta(description="s")]


class ReleaseReply(Reply, frozen=True):
    shot: int
    outcome: str
    hit: bool
    reason: str
    sim_time: Annotated[float, Meta(description="s")]
    release_sim_time: Annotated[float, Meta(description="s")]
    flight_time: Annotated[float, Meta(description="s")]
    #: None from a robot that cannot tell it (a real robot's finger release)
    theta: Annotated[Theta, Meta(description="θ the arrow was launched with, m")] | None = None


class ResetArgs(Args, frozen=True):
    seed: Annotated[int, Meta(ge=0, le=2**63 - 1)] | None = None


class ResetReply(Reply, frozen=True):
    sim_time: Annotated[float, Meta(description="s")]
    seed: int | None
    shot: int


class SetWindArgs(Args, frozen=True):
    """The robot refuses a component beyond ±MAX_WIND (a NaN is refused here, as not finite)."""

    wind: Annotated[
        list[float], Meta(min_length=3, max_length=3, description="m/s, each within ±50")
    ]


class WindReply(Reply, frozen=True):
    wind: Annotated[list[float], Meta(description="m/s, root frame")]


class Scene(Reply, frozen=True):
    """The robot's scene as its `status` tells it: the parameters of `sim.scene_config.
    SceneConfig` (a test keeps the two the same), typed, for a camera, a controller or a
    bridge to rebuild the same scene (`SceneConfig.of`). Units: m, kg, s, rad/s, kg·m², rad,
    degrees (`camera_fovy`)."""

    root_height: Annotated[float, Meta(description="m")]
    target_distance: Annotated[float, Meta(description="m")]
    arrow_length: Annotated[float, Meta(description="m")]
    arrow_mass: Annotated[float, Meta(description="kg")]
    timestep: Annotated[float, Meta(description="s")]
    servo_bandwidth: Annotated[float, Meta(description="rad/s")]
    servo_damping_ratio: float
    armature: Annotated[float, Meta(description="kg·m²")]
    limit_margin: Annotated[float, Meta(description="rad")]
    meshes: bool
    camera_pos: Annotated[
        list[float], Meta(min_length=3, max_length=3, description="m, root frame")
    ]
    camera_fovy: Annotated[float, Meta(description="degrees")]
    shot: Literal["posture", "whole"]


class ArcheryStatusReply(Reply, frozen=True):
    sim_time: Annotated[float, Meta(description="s")]
    arrow: str
    phase: Literal["idle", "nocked", "flying", "stuck", "missed"]
    shot: int
    motion_done: bool
    seed: int | None
    rtf: float
    state_rate: float
    world_rate: float
    watchdog: float
    limit_tolerance: float
    timestep: float
    counters: dict[str, dict[str, Any]]
    scene: Scene
    world: dict[str, Any]
    #: m, the string hand's frame (`r_hand_dh_frame`): where a nocked arrow's nock sits, for a
    #: controller to aim the arrow rather than the hand; None on a posture-shot robot
    nock_in_hand: Annotated[list[float], Meta(min_length=3, max_length=3)] | None = None


# The whole shot (`archery robot --shot whole`): the arrow waits in a holder; `grasp` closes the
# right hand's fingers on it, `nock` puts the held arrow's nock on the string (the right arm
# carries it there first, on `command:i` or `positionMove`), the right arm draws, `release`
# opens the fingers and the arrow leaves at the bow's speed for the draw length. Their error
# codes: `grasp_missed` (the hand is farther from the shaft than the world's grasp_tolerance;
# the arrow stays in its holder), `nock_missed` (the nock is farther from the string than
# nock_tolerance; the arrow stays in the hand), `arrow_dropped` (release of an arrow in the
# hand but off the string: it falls), `bad_state` (out of order, or `grasp` under --shot
# posture). Under --shot posture `nock` puts a fresh arrow on the bow, as the paper's robot.
GRASP = Verb("grasp", NoArgs, GraspReply, "whole shot: close the right hand on the arrow")

NOCK = Verb("nock", NoArgs, NockReply, "put a fresh arrow (whole shot: the held one) on the bow")

RELEASE = Verb(
    "release",
    NoArgs,
    ReleaseReply,
    "release the arrow (whole shot: open the fingers); replies once it has landed",
)

FOLLOW_TRAJECTORY = Verb(
    "followTrajectory",
    TrajectoryArgs,
    TrajectoryReply,
    "play several parts' waypoints and the archery actions at their times; replies at the end",
    waits=True,
)

RESET = Verb("reset", ResetArgs, ResetReply, "home posture at sim time 0; reseed with seed")

SET_WIND = Verb(
    "setWind",
    SetWindArgs,
    WindReply,
    "the constant wind (m/s, root frame) of the following shots; the wind now in force",
)

ARCHERY_STATUS = Verb(
    "status",
    NoArgs,
    ArcheryStatusReply,
    "arrow, phase, counters, scene and world",
    reads=True,
)

ARCHERY_VERBS = VerbTable(
    "robot archery",
    ("archery/rpc:i",),
    (
        GRASP,
        NOCK,
        RELEASE,
        FOLLOW_TRAJECTORY,
        RESET,
        SET_WIND,
        ARCHERY_STATUS,
    ),
)
