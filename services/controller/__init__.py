"""The controller service: Eq. 9 inverse kinematics and the archery posture for iCub's arms."""

from protocol.robotspec import HAND_FRAMES, HOME_POSTURE
from services.controller.errors import ConfigError, ControllerError, JointError, TargetError
from services.controller.ik import IkSolver
from services.controller.ik_types import (
    IkResult,
    IkSettings,
    OrientationTarget,
    PositionTarget,
    TargetsResult,
)
from services.controller.model import JOINT_NAMES, ArmsModel, load_arms_model
from services.controller.posture import (
    ArcheryPosture,
    PostureConfig,
    PostureResult,
    hand_orientations,
)

__all__ = [
    "HAND_FRAMES",
    "HOME_POSTURE",
    "JOINT_NAMES",
    "ArcheryPosture",
    "ArmsModel",
    "ConfigError",
    "ControllerError",
    "IkResult",
    "IkSettings",
    "IkSolver",
    "JointError",
    "OrientationTarget",
    "PositionTarget",
    "PostureConfig",
    "PostureResult",
    "TargetError",
    "TargetsResult",
    "hand_orientations",
    "load_arms_model",
]
