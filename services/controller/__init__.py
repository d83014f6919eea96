"""The controller service: Eq. 9 inverse kinematics and the archery posture for iCub's arms."""

from services.controller.errors import ConfigError, ControllerError, JointError, TargetError
from services.controller.ik import (
    IkResult,
    IkSettings,
    IkSolver,
    OrientationTarget,
    PositionTarget,
    TargetsResult,
)
from services.controller.model import (
    HAND_FRAMES,
    HOME_POSTURE,
    JOINT_NAMES,
    ArmsModel,
    load_arms_model,
)
from services.controller.posture import (
    ArcheryPosture,
    PostureConfig,
    PostureResult,
    arrow_direction,
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
    "arrow_direction",
    "hand_orientations",
    "load_arms_model",
]
