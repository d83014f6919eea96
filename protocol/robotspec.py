"""The facts about the robot and the range that more than one service relies on, stated once.

Services may import only `protocol/` (and, for robot and camera, `sim/`), so whatever the
simulated robot, the controller, the detector and the learner must agree on lives here: the
service names, the URDF model, which hand holds the bow and the names of the hand frames, the
home posture, the nominal archery geometry (θ, the bow hand, the hit radius), the joint speed
bound, command ownership and the default waits between services.

Frame and units: the iCub `root_link` frame (x backward, y to the robot's right, z up; the robot
faces −x), metres, radians, seconds (wall clock unless said otherwise).
"""

from __future__ import annotations

from collections.abc import Mapping
from types import MappingProxyType

from archery.protocol.parts import ARM_PARTS, PARTS

__all__ = [
    "BOW_ARM",
    "BOW_HAND",
    "BOW_HAND_FRAME",
    "CALL_TIMEOUT",
    "CAMERA",
    "CAMERA_TIMEOUT",
    "COMMAND_BURST",
    "COMMAND_RATE",
    "CONTROLLER",
    "DETECTOR",
    "HAND_FRAMES",
    "HIT_RADIUS",
    "HOME_POSTURE",
    "LEARNER",
    "LEASE_TTL",
    "LEASE_TTL_RANGE",
    "MAX_REFERENCE_SPEED",
    "MODEL_NAME",
    "NOMINAL_THETA",
    "REFERENCE_SPEED",
    "ROBOT",
    "ROBOT_TIMEOUT",
    "RPC_TIMEOUT",
    "SERVICES",
    "STATE_MAX_AGE",
    "STRING_ARM",
    "STRING_HAND_FRAME",
    "THETA0",
    "TOLERANCES",
    "TORSO",
    "home_of",
    "model_file",
]

# -- the services ------------------------------------------------------------------------------
ROBOT = "robot"
CAMERA = "camera"
DETECTOR = "detector"
CONTROLLER = "controller"
LEARNER = "learner"
#: Every service of the mesh, in the order the closed loop reaches them.
SERVICES: tuple[str, ...] = (ROBOT, CAMERA, DETECTOR, CONTROLLER, LEARNER)

# -- the robot model ---------------------------------------------------------------------------
#: The `icub-models` URDF both the simulator (MuJoCo) and the controller (Pinocchio) load.
MODEL_NAME = "iCubGazeboV2_5"


def model_file() -> str:
    """Where the installed `icub-models` keeps `MODEL_NAME`'s URDF (a path; nothing is read).

    The simulator (`sim/urdf.py`: MuJoCo), the controller (`services/controller/model.py`:
    Pinocchio), the robot frames and the bridges all load the robot from this one file.
    """
    import icub_models

    return str(icub_models.get_model_file(MODEL_NAME))


#: The arm part whose hand holds the bow, and the one that draws the string.
BOW_ARM = "left_arm"
STRING_ARM = "right_arm"
TORSO = "torso"

#: The end-effector frame of each arm part (iKin's hand frame, origin on the palm): URDF links
#: in Pinocchio, sites of the same name in the MuJoCo scene.
HAND_FRAMES: Mapping[str, str] = MappingProxyType(
    {"left_arm": "l_hand_dh_frame", "right_arm": "r_hand_dh_frame"}
)
BOW_HAND_FRAME = HAND_FRAMES[BOW_ARM]
STRING_HAND_FRAME = HAND_FRAMES[STRING_ARM]

# rad, YARP order (shoulder pitch, roll, yaw, elbow, wrist prosup, pitch, yaw): arms bent in
# front, inside every joint's limits.
_ARM_HOME = (-0.5, 0.4, 0.0, 0.9, 0.0, 0.0, 0.0)

#: The home posture, joint name → angle (rad): torso straight, both arms at `_ARM_HOME`. The
#: simulated robot (`sim.scene`, `sim.world`) starts every session here and tunes its joint
#: servos at it, so it is the posture the running system is actually in before the first move.
#: The controller used to keep its own copy, iCub's customary (−30°, 30°, 0°, 45°) arm posture;
#: there it only seeds the IK (the default warm start, the rest posture q̂ of Eq. 9 and the
#: first start of the archery reference-posture search), never a posture the robot is sent to.
#: The simulator's value wins: the controller's seed now equals the robot's real starting
#: posture. `tests/test_robotspec.py` checks that MuJoCo and Pinocchio put the hand frames at
#: the same place at this posture.
HOME_POSTURE: Mapping[str, float] = MappingProxyType(
    {name: 0.0 for name in PARTS["torso"]}
    | {
        name: value
        for part in ARM_PARTS
        for name, value in zip(PARTS[part], _ARM_HOME, strict=True)
    }
)


def home_of(part: str) -> tuple[float, ...]:
    """The home angles (rad) of `part`'s joints in YARP order.

    Raises:
        KeyError: `part` is not a controlled part; the message lists them.
    """
    if part not in PARTS:
        raise KeyError(f"unknown part {part!r}; parts: {', '.join(PARTS)}")
    return tuple(HOME_POSTURE[name] for name in PARTS[part])


# -- the archery geometry ----------------------------------------------------------------------
#: Nominal bow-hand position (m, root frame): the controller's posture puts the left hand here
#: and the target centre sits straight ahead of it.
BOW_HAND: tuple[float, float, float] = (-0.30, -0.10, 0.10)

#: Nominal θ = p_string − p_bow (m): the controller's reference posture and the analytic
#: world's starting offset.
NOMINAL_THETA: tuple[float, float, float] = (0.17, 0.03, -0.03)

#: θ0 (m) where learning sessions on the simulated robot start: its arrows land on the target
#: face about 11 cm up and left of the centre (`NOMINAL_THETA` lands outside the face at 2.2 m).
THETA0: tuple[float, float, float] = (0.17, 0.006, -0.026)

#: A shot hits when its distance to the target centre ‖r‖ is below this (m): the innermost
#: ring (the paper's Section IV).
HIT_RADIUS = 0.05

# -- motion ------------------------------------------------------------------------------------
#: The robot's upper bound for joint reference speeds (rad/s); the controller never asks for
#: more. Up to this, commanded moves never pass the URDF joint limits in the simulator.
MAX_REFERENCE_SPEED = 2.0
#: The joints' reference speed (rad/s) of a robot at its start and after a reset.
REFERENCE_SPEED = 0.5

# -- command ownership (wall s) ----------------------------------------------------------------
#: How long a part's lease (the `claim` verb of `ROBOT/PART/rpc:i`) lasts unless renewed: a
#: controller that dies mid-posture frees the arm this long after its last renewal at most. The
#: controller claims with it and renews every quarter of it.
LEASE_TTL = 2.0
#: The lease durations a client may ask for: from a test's short lease to a hand user's session.
LEASE_TTL_RANGE = (0.05, 600.0)
#: Commands per wall second a part's `command:i` admits in the long run (the robot's default
#: `--command-rate`): twice a 100 Hz teleoperation stream, while a flood's excess never
#: reaches the simulation thread. The excess is dropped: a streaming client stays below it.
COMMAND_RATE = 200.0
#: Commands a part admits at once after a pause (a controller sends one per move).
COMMAND_BURST = 50

# -- default waits (wall s) --------------------------------------------------------------------
#: One RPC call to any service when the caller says nothing else.
CALL_TIMEOUT = 5.0
#: A joint state or a controlboard RPC reply from the robot (controller, camera).
ROBOT_TIMEOUT = 3.0

#: What "reached" means for every client of the robot (`mesh/robot_client.py`), rad: a move
#: `until="rest"` ends once the whole robot rests (motion done, states of one simulated time)
#: with each moved joint within `TOLERANCES["rest"]` of its target; `until="passing"` once each
#: moved joint is within `TOLERANCES["passing"]`, still moving (a waypoint the next follows).
#: The controller's `--joint-tolerance` defaults to the first.
TOLERANCES: Mapping[str, float] = MappingProxyType({"rest": 0.005, "passing": 0.03})
#: A robot state older than this (by its arrival on the receiver) is stale: never used, the
#: caller gets `StaleState` (controller).
STATE_MAX_AGE = 0.5
#: A camera frame newer than a given time (detector).
CAMERA_TIMEOUT = 10.0
#: A reply from another service during a learning session (a posture move, a shot, a measure).
RPC_TIMEOUT = 20.0
