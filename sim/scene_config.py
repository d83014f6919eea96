"""What the archery scene is made of: its validated parameters and the names of its parts.

`SceneConfig` fully determines the model `sim.model_build.build_scene` compiles; the names are
those of the compiled model's sites, bodies, joints, tendon and cameras. Hand sites carry the
URDF's hand-frame names from `protocol.robotspec`, so the controller (Pinocchio) and the
simulator (MuJoCo) talk about the same frames.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import msgspec

from archery.protocol.errors import ConfigError
from archery.protocol.robotspec import BOW_HAND_FRAME, STRING_HAND_FRAME
from archery.protocol.vectors import finite_vector
from archery.protocol.verbs.robot import Scene
from archery.sim.bow import Bow
from archery.sim.geometry import TARGET_DISTANCE

__all__ = [
    "ARROW_BODY",
    "ARROW_JOINT",
    "ARROW_NOCK_SITE",
    "ARROW_TIP_RGBA",
    "ARROW_TIP_SITE",
    "BOWSTRING_TENDON",
    "BOW_HAND_SITE",
    "GRASP_SITE",
    "GRASP_WELD",
    "GRIP_JOINT",
    "HOLDER_BODY",
    "HOLDER_WELD",
    "RING_COLOURS",
    "SHOTS",
    "SIDE_CAMERA",
    "STRING_HAND_SITE",
    "STRING_NOCK_BODY",
    "STRING_NOCK_SITE",
    "TARGET_CAMERA",
    "TARGET_CENTRE_SITE",
    "SceneConfig",
]

# Names in the compiled model.
BOW_HAND_SITE = BOW_HAND_FRAME  # the left (bow) hand's end-effector frame, as a site
STRING_HAND_SITE = STRING_HAND_FRAME  # the right (string) hand's end-effector frame, as a site
BOWSTRING_TENDON = "bowstring"
ARROW_BODY = "arrow"
ARROW_JOINT = "arrow_free"
ARROW_TIP_SITE = "arrow_tip"
TARGET_CENTRE_SITE = "target_centre"
TARGET_CAMERA = "target_cam"
SIDE_CAMERA = "side_cam"
# … and those the whole shot adds (`sim.whole_props`).
ARROW_NOCK_SITE = "arrow_nock"  # the arrow's nock end, on its axis, arrow_length behind the tip
GRASP_SITE = "r_grasp"  # between the right hand's fingers, at the string hand's frame
GRIP_JOINT = "r_grip"  # the fingers' hinge and its servo
HOLDER_BODY = "arrow_holder"
HOLDER_WELD = "arrow_in_holder"
GRASP_WELD = "arrow_in_hand"
STRING_NOCK_BODY = "string_nock"  # the bowstring's nocking point (a free body) and its site
STRING_NOCK_SITE = "string_nock"

#: How the arrow gets onto the string: "posture", put there (the paper's simplification), or
#: "whole", grasped from its holder, carried, nocked and drawn by the right hand.
SHOTS = ("posture", "whole")

# The archery target face, innermost first: (outer radius in m, RGBA). The tip's green is in
# none of them, so a colour model can tell the arrow from the target.
RING_COLOURS: tuple[tuple[float, tuple[float, float, float, float]], ...] = (
    (0.05, (1.00, 0.85, 0.05, 1.0)),  # yellow (gold)
    (0.10, (0.90, 0.08, 0.08, 1.0)),  # red
    (0.15, (0.10, 0.35, 0.90, 1.0)),  # blue
    (0.20, (0.06, 0.06, 0.06, 1.0)),  # black
    (0.25, (0.96, 0.96, 0.96, 1.0)),  # white
)
ARROW_TIP_RGBA = (0.10, 1.00, 0.10, 1.0)  # bright green suction-cup tip


@dataclass(frozen=True)
class SceneConfig:
    """Every parameter of the scene, validated. Two equal configs build identical models.

    Attributes:
        root_height: height of the robot's root link above the floor (m); 0.62 puts the soles
            on the floor with straight legs.
        target_distance: root to target plane (m); the face is the plane x = −target_distance.
        arrow_length: tip to nock (m).
        arrow_mass: m of the arrow (kg); should match the bow model's.
        timestep: physics step (s).
        servo_bandwidth: natural frequency ω of every joint's position servo (rad/s).
        servo_damping_ratio: ζ of every joint's servo at the home posture (1 = critical).
        armature: reflected rotor inertia added to every controlled joint (kg·m²).
        limit_margin: each joint's stop engages this far inside its URDF limit (rad); the world
            clamps targets to the limits shrunk by this margin, so joints never pass the URDF
            limits.
        meshes: load the robot's STL meshes (needed to render it; physics does not use them).
        camera_pos: position of `target_cam` (m, root frame), on the robot's frame above and
            to the right of its head, looking at the target centre.
        camera_fovy: vertical field of view of `target_cam` (degrees).
        shot: "posture" (the arrow is put on the string) or "whole" (the scene also has the
            arrow's holder, the right hand's fingers and a bowstring that bends; `SHOTS`).
    """

    root_height: float = 0.62
    target_distance: float = TARGET_DISTANCE
    arrow_length: float = 0.30
    arrow_mass: float = Bow().arrow_mass
    timestep: float = 0.002
    servo_bandwidth: float = 25.0
    servo_damping_ratio: float = 1.0
    armature: float = 0.01
    limit_margin: float = 0.003
    meshes: bool = True
    camera_pos: tuple[float, float, float] = (0.05, 0.30, 0.55)
    camera_fovy: float = 22.0
    shot: str = SHOTS[0]

    def __post_init__(self) -> None:
        limits = {
            "root_height": (0.3, 2.0),
            "target_distance": (0.8, 50.0),
            "arrow_length": (0.1, 1.0),
            "arrow_mass": (1e-3, 0.5),
            "timestep": (1e-4, 0.01),
            "servo_bandwidth": (1.0, 200.0),
            "servo_damping_ratio": (0.1, 5.0),
            "armature": (0.0, 1.0),
            "limit_margin": (0.0, 0.05),
            "camera_fovy": (5.0, 120.0),
        }
        for name, (low, high) in limits.items():
            value = getattr(self, name)
            if not isinstance(value, int | float) or not math.isfinite(value):
                raise ConfigError(f"scene {name} must be a finite number, got {value!r}")
            if not low <= value <= high:
                raise ConfigError(f"scene {name} must be in [{low}, {high}], got {value!r}")
            object.__setattr__(self, name, float(value))
        if not isinstance(self.meshes, bool):
            raise ConfigError(f"scene meshes must be True or False, got {self.meshes!r}")
        if self.shot not in SHOTS:
            raise ConfigError(f"scene shot must be one of {', '.join(SHOTS)}, got {self.shot!r}")
        pos = finite_vector("scene camera_pos", self.camera_pos, ConfigError, unit="m")
        object.__setattr__(self, "camera_pos", tuple(pos.tolist()))

    def to_dict(self) -> dict[str, object]:
        """JSON-friendly copy of the parameters (for the camera to rebuild the same scene)."""
        return {f.name: getattr(self, f.name) for f in fields(self)}

    def to_status(self) -> Scene:
        """The parameters as the robot's status carries them (typed)."""
        return msgspec.convert(self.to_dict(), Scene)

    @classmethod
    def of(cls, scene: Scene) -> SceneConfig:
        """The scene a robot's status tells (`Scene`), validated again here.

        Raises:
            ConfigError: a parameter out of its range.
        """
        return cls(**{f.name: getattr(scene, f.name) for f in fields(cls)})
