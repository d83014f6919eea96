"""The robot's controlboard parts and their joint names, in YARP order (the shape of the ports).

Joint names are those of the `icub-models` URDF (`iCubGazeboV2_5`); angles are radians. The
torso is ordered yaw, roll, pitch as on iCub's `torso` controlboard.
"""

from __future__ import annotations

__all__ = ["ARM_PARTS", "PARTS"]

_ARM_JOINTS = (
    "shoulder_pitch",
    "shoulder_roll",
    "shoulder_yaw",
    "elbow",
    "wrist_prosup",
    "wrist_pitch",
    "wrist_yaw",
)

PARTS: dict[str, tuple[str, ...]] = {
    "torso": ("torso_yaw", "torso_roll", "torso_pitch"),
    "left_arm": tuple(f"l_{joint}" for joint in _ARM_JOINTS),
    "right_arm": tuple(f"r_{joint}" for joint in _ARM_JOINTS),
}

ARM_PARTS: tuple[str, ...] = ("left_arm", "right_arm")
