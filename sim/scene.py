"""The MuJoCo archery scene: the iCub (icub-models URDF), bow, arrow, target, floor and cameras.

Frame: the MuJoCo world frame *is* the iCub `root_link` frame of `sim.geometry` (x backward,
y right, z up; metres). The URDF's root link is welded to the world, and the floor is the plane
z = −root_height below it, so every position the physics reports is already in the frame the
controller, the learner and the reward use. The robot faces −x; the target face is the plane
x = −target_distance.

What `build_scene` does to the official model (the URDF `iCubGazeboV2_5`, CC BY-SA 4.0):
* resolves `package://iCub/` mesh paths to the package's own mesh files;
* keeps only the 17 joints of `protocol.parts.PARTS` (torso, both arms); the legs and the neck
  are frozen at zero by deleting their joints;
* switches every robot collision off (no self-collision, nothing for the arrow to hit) and also
  disables contact globally: the arrow's impact is found geometrically by `sim.arrow`;
* compensates gravity on the robot's links (the firmware's gravity compensation) and adds one
  position servo per joint whose stiffness and damping are tuned from the joint's inertia at the
  home posture, so every joint settles like a critically damped system of the same bandwidth;
* adds the URDF frames that MuJoCo fuses away, `l_hand_dh_frame` and `r_hand_dh_frame`, as sites
  at their exact URDF poses;
* adds the bow (held in the left hand, with a bowstring tendon through the right hand's site),
  the arrow (a free body whose origin is its tip, marked in bright green), the ringed target on a
  stand, a floor, lights and two fixed cameras.

The model is fully determined by `SceneConfig`; a renderer that rebuilds it with the same config
reproduces any state from `qpos` alone. `ScenePhysics` is the thin layer of physics queries by
name (joint slices per part, sites, the arrow's pose and velocity) that task logic builds on.
"""

from __future__ import annotations

import math
import pathlib
import xml.etree.ElementTree as ET
from dataclasses import dataclass, fields
from itertools import pairwise

import mujoco
import numpy as np

from protocol.parts import PARTS
from sim.bow import Bow
from sim.errors import CommandError, ConfigError, SceneError
from sim.geometry import TARGET_DIAMETER, TARGET_DISTANCE, target_centre

__all__ = [
    "ARROW_BODY",
    "ARROW_JOINT",
    "ARROW_TIP_SITE",
    "BOWSTRING_TENDON",
    "BOW_HAND_SITE",
    "HOME_POSTURE",
    "MODEL_NAME",
    "RING_COLOURS",
    "SIDE_CAMERA",
    "STRING_HAND_SITE",
    "TARGET_CAMERA",
    "TARGET_CENTRE_SITE",
    "SceneConfig",
    "ScenePhysics",
    "build_scene",
    "load_urdf_model",
    "look_at_quat",
    "urdf_frame_placement",
]

MODEL_NAME = "iCubGazeboV2_5"

# Names in the compiled model.
BOW_HAND_SITE = "l_hand_dh_frame"  # the left (bow) hand's end-effector frame
STRING_HAND_SITE = "r_hand_dh_frame"  # the right (string) hand's end-effector frame
BOWSTRING_TENDON = "bowstring"
ARROW_BODY = "arrow"
ARROW_JOINT = "arrow_free"
ARROW_TIP_SITE = "arrow_tip"
TARGET_CENTRE_SITE = "target_centre"
TARGET_CAMERA = "target_cam"
SIDE_CAMERA = "side_cam"

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

# A neutral posture inside every joint's limits (rad), YARP order per part: arms bent in front.
HOME_POSTURE: dict[str, tuple[float, ...]] = {
    "torso": (0.0, 0.0, 0.0),
    "left_arm": (-0.5, 0.4, 0.0, 0.9, 0.0, 0.0, 0.0),
    "right_arm": (-0.5, 0.4, 0.0, 0.9, 0.0, 0.0, 0.0),
}

_ROBOT_NAME_TAG = '<robot name="iCub">'
_PACKAGE_PREFIX = "package://iCub/"


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
        pos = np.asarray(self.camera_pos, dtype=float)
        if pos.shape != (3,) or not np.all(np.isfinite(pos)):
            raise ConfigError(
                f"scene camera_pos must be 3 finite numbers (m), got {self.camera_pos!r}"
            )
        object.__setattr__(self, "camera_pos", tuple(float(v) for v in pos))

    def to_dict(self) -> dict[str, object]:
        """JSON-friendly copy of the parameters (for the camera to rebuild the same scene)."""
        return {f.name: getattr(self, f.name) for f in fields(self)}


# --------------------------------------------------------------------------------------------
# The official model file


def _model_file() -> pathlib.Path:
    import icub_models

    path = pathlib.Path(icub_models.get_model_file(MODEL_NAME))
    if not path.is_file():
        raise SceneError(f"the icub-models file for {MODEL_NAME!r} is missing: {path}")
    return path


def _urdf_text(resolve_meshes: bool = True) -> str:
    """The URDF with `package://iCub/` mesh paths made absolute (the package's share dir)."""
    path = _model_file()
    text = path.read_text()
    if resolve_meshes:
        share = path.parents[2]  # …/share/iCub/robots/<model>/model.urdf → …/share/iCub
        if not (share / "meshes").is_dir():
            raise SceneError(f"no meshes directory next to the iCub model: {share / 'meshes'}")
        text = text.replace(_PACKAGE_PREFIX, f"{share}/")
    return text


def _with_compiler(text: str, attributes: str) -> str:
    if _ROBOT_NAME_TAG not in text:
        raise SceneError(
            f"unexpected URDF: no {_ROBOT_NAME_TAG!r} element in the {MODEL_NAME} file"
        )
    return text.replace(
        _ROBOT_NAME_TAG, f"{_ROBOT_NAME_TAG}<mujoco><compiler {attributes}/></mujoco>", 1
    )


def load_urdf_model() -> mujoco.MjModel:
    """The iCub URDF loaded into MuJoCo unmodified (only the mesh paths resolved).

    This is the baseline the benchmark compares against: MuJoCo's own URDF import, floating legs,
    self-collision on, no actuators.
    """
    return mujoco.MjModel.from_xml_string(_with_compiler(_urdf_text(), 'strippath="false"'))


def _rpy_quat(rpy: tuple[float, float, float]) -> np.ndarray:
    """Quaternion (w, x, y, z) of URDF roll-pitch-yaw: R = Rz(yaw)·Ry(pitch)·Rx(roll)."""
    r, p, y = (0.5 * a for a in rpy)
    qx = np.array([math.cos(r), math.sin(r), 0.0, 0.0])
    qy = np.array([math.cos(p), 0.0, math.sin(p), 0.0])
    qz = np.array([math.cos(y), 0.0, 0.0, math.sin(y)])
    out = np.empty(4)
    tmp = np.empty(4)
    mujoco.mju_mulQuat(tmp, qz, qy)
    mujoco.mju_mulQuat(out, tmp, qx)
    return out


def urdf_frame_placement(frame: str) -> tuple[str, np.ndarray, np.ndarray]:
    """Pose of a URDF link relative to the nearest ancestor that MuJoCo keeps as a body.

    MuJoCo fuses links attached by fixed joints into their parent. This composes the fixed
    joints' origins from `frame` up to the first link whose parent joint moves (or the root).

    Returns:
        (body name, position (m), quaternion w, x, y, z) of `frame` in that body's frame.

    Raises:
        SceneError: `frame` is not a link of the model.
    """
    root = ET.fromstring(_urdf_text(resolve_meshes=False))
    links = {link.get("name") for link in root.iter("link")}
    if frame not in links:
        raise SceneError(
            f"{frame!r} is not a link of {MODEL_NAME}; e.g. l_hand_dh_frame, r_hand_dh_frame"
        )
    parent_joint = {j.find("child").get("link"): j for j in root.iter("joint")}  # type: ignore[union-attr]
    pos, quat = np.zeros(3), np.array([1.0, 0.0, 0.0, 0.0])
    link = frame
    while link in parent_joint and parent_joint[link].get("type") == "fixed":
        joint = parent_joint[link]
        origin = joint.find("origin")
        xyz = tuple(
            float(v)
            for v in (origin.get("xyz", "0 0 0") if origin is not None else "0 0 0").split()
        )
        rpy = tuple(
            float(v)
            for v in (origin.get("rpy", "0 0 0") if origin is not None else "0 0 0").split()
        )
        joint_quat = _rpy_quat(rpy)  # type: ignore[arg-type]
        rotated = np.empty(3)
        mujoco.mju_rotVecQuat(rotated, pos, joint_quat)
        pos = np.asarray(xyz) + rotated
        new_quat = np.empty(4)
        mujoco.mju_mulQuat(new_quat, joint_quat, quat)
        quat = new_quat
        link = joint.find("parent").get("link")  # type: ignore[union-attr]
    return link, pos, quat


def look_at_quat(eye: np.ndarray, target: np.ndarray, up: np.ndarray | None = None) -> np.ndarray:
    """Quaternion (w, x, y, z) of a MuJoCo camera at `eye` looking at `target` (m), `up` ≈ +z.

    A MuJoCo camera looks along its −z axis with +y up in the image.
    """
    up = np.array([0.0, 0.0, 1.0]) if up is None else np.asarray(up, dtype=float)
    forward = np.asarray(target, dtype=float) - np.asarray(eye, dtype=float)
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    cam_up = np.cross(right, forward)
    mat = np.column_stack([right, cam_up, -forward])
    quat = np.empty(4)
    mujoco.mju_mat2Quat(quat, mat.ravel())
    return quat


# --------------------------------------------------------------------------------------------
# Building the scene


def _robot_spec(config: SceneConfig) -> mujoco.MjSpec:
    spec = mujoco.MjSpec.from_string(_with_compiler(_urdf_text(), 'strippath="false"'))
    # Keep the contype-0 geoms (URDF import would discard them as visual-only), and fuse every
    # body without a joint into its parent (the URDF's ~180 fixed frames, the frozen legs and
    # neck, the bow and the target): fewer bodies, same kinematics.
    spec.compiler.discardvisual = False
    spec.compiler.fusestatic = True
    controlled = {name for joints in PARTS.values() for name in joints}
    present = {joint.name for joint in spec.joints}
    missing = sorted(controlled - present)
    if missing:
        raise SceneError(f"{MODEL_NAME} lacks the controlled joints {missing}")
    for joint in list(spec.joints):
        if joint.name not in controlled:
            spec.delete(joint)  # legs and neck: frozen at zero
        else:
            joint.armature = config.armature
            joint.solref_limit = [2.0 * config.timestep, 1.0]  # stiff joint stops
            joint.solimp_limit = [0.99, 0.999, 0.001, 0.5, 2.0]
            joint.margin = config.limit_margin  # the stop engages this far before the limit
    for geom in list(spec.geoms):
        if not config.meshes and geom.type == mujoco.mjtGeom.mjGEOM_MESH:
            spec.delete(geom)
            continue
        geom.contype = 0
        geom.conaffinity = 0
        geom.group = 1  # the robot's visuals
    if not config.meshes:
        for mesh in list(spec.meshes):
            spec.delete(mesh)
    for body in spec.bodies:
        if body.name != "world":
            body.gravcomp = 1.0
    for part, joints in PARTS.items():
        for name in joints:
            actuator = spec.add_actuator(name=name, target=name, group=int(part != "torso"))
            actuator.trntype = mujoco.mjtTrn.mjTRN_JOINT
            actuator.set_to_position(kp=1.0, kv=0.0)
            actuator.ctrllimited = True
            actuator.inheritrange = 1.0  # ctrlrange = the joint's range
    return spec


def _add_hand_sites(spec: mujoco.MjSpec) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    poses = {}
    for frame in (BOW_HAND_SITE, STRING_HAND_SITE):
        body_name, pos, quat = urdf_frame_placement(frame)
        body = spec.body(body_name)
        if body is None:
            raise SceneError(f"the URDF frame {frame!r} hangs from {body_name!r}, not a body")
        body.add_site(
            name=frame, pos=pos, quat=quat, size=[0.006, 0, 0], rgba=[1, 0.5, 0, 0.6], group=4
        )
        poses[frame] = (pos, quat)
    return poses


def _add_bow(spec: mujoco.MjSpec, hand_site: tuple[np.ndarray, np.ndarray]) -> None:
    """A bow held in the left hand. In the hand frame: −y up along the grip (thumb side),
    −z toward the target (out of the palm), +z toward the string hand."""
    pos, quat = hand_site
    bow = spec.body("l_hand").add_body(name="bow", pos=pos, quat=quat, gravcomp=1.0)
    bow.explicitinertial = True
    bow.mass = 0.15
    bow.inertia = [3e-3, 3e-3, 1e-4]
    wood = [0.45, 0.27, 0.12, 1.0]
    capsule = mujoco.mjtGeom.mjGEOM_CAPSULE

    def seg(a: tuple[float, float, float], b: tuple[float, float, float], radius: float) -> None:
        bow.add_geom(
            type=capsule,
            fromto=[*a, *b],
            size=[radius, 0, 0],
            rgba=wood,
            contype=0,
            conaffinity=0,
            group=2,
            mass=0,
        )

    # The hand mesh is an open hand: fingers along +x, thumb along −y, palm surface at z ≈ −0.012.
    gx, gz = 0.02, -0.028  # grip axis: across the palm, just in front of it (m)
    seg((gx, -0.06, gz), (gx, 0.06, gz), 0.012)
    # Each limb: three segments curving back toward the string side (+z).
    for sign in (-1.0, 1.0):
        points = [
            (gx, sign * 0.06, gz),
            (gx, sign * 0.16, gz + 0.012),
            (gx, sign * 0.25, gz + 0.035),
            (gx, sign * 0.32, gz + 0.07),
        ]
        for (a, b), radius in zip(pairwise(points), (0.009, 0.007, 0.005), strict=True):
            seg(a, b, radius)
    bow.add_site(name="bow_top", pos=[gx, -0.32, gz + 0.07], size=[0.004, 0, 0], group=4)
    bow.add_site(name="bow_bottom", pos=[gx, 0.32, gz + 0.07], size=[0.004, 0, 0], group=4)
    string = spec.add_tendon(name=BOWSTRING_TENDON, width=0.0015, rgba=[0.95, 0.95, 0.9, 1.0])
    string.wrap_site("bow_top")
    string.wrap_site(STRING_HAND_SITE)
    string.wrap_site("bow_bottom")


def _add_arrow(spec: mujoco.MjSpec, config: SceneConfig) -> None:
    """The arrow: a free body whose origin is its tip and whose +x axis points forward."""
    length, mass = config.arrow_length, config.arrow_mass
    stowed = np.array([0.12, 0.30, -config.root_height + 0.002])  # upright beside the right foot
    arrow = spec.worldbody.add_body(
        name=ARROW_BODY, pos=stowed, quat=[math.sqrt(0.5), 0, math.sqrt(0.5), 0]
    )
    arrow.add_freejoint(name=ARROW_JOINT)
    arrow.explicitinertial = True
    arrow.mass = mass
    arrow.ipos = [-0.5 * length, 0.0, 0.0]
    arrow.inertia = [0.5 * mass * 0.004**2, mass * length**2 / 12, mass * length**2 / 12]
    cyl = mujoco.mjtGeom.mjGEOM_CYLINDER
    common = {"contype": 0, "conaffinity": 0, "group": 2, "mass": 0}
    # Suction cup: a flat disc whose front face is the tip.
    arrow.add_geom(
        type=cyl, fromto=[0, 0, 0, -0.012, 0, 0], size=[0.015, 0, 0], rgba=ARROW_TIP_RGBA, **common
    )
    arrow.add_geom(
        type=cyl,
        fromto=[-0.012, 0, 0, -length, 0, 0],
        size=[0.0035, 0, 0],
        rgba=[0.35, 0.35, 0.38, 1.0],
        **common,
    )
    for angle in (0.0, 2 * math.pi / 3, 4 * math.pi / 3):
        arrow.add_geom(
            type=mujoco.mjtGeom.mjGEOM_BOX,
            pos=[-length + 0.045, 0.012 * math.cos(angle), 0.012 * math.sin(angle)],
            quat=[math.cos(angle / 2), math.sin(angle / 2), 0, 0],
            size=[0.035, 0.0005, 0.011],
            rgba=[0.55, 0.55, 0.55, 1.0],
            **common,
        )
    arrow.add_site(name=ARROW_TIP_SITE, size=[0.003, 0, 0], group=4)


def _add_target(spec: mujoco.MjSpec, config: SceneConfig) -> None:
    """The target face in the plane x = −distance, facing the robot, on a stand."""
    centre = target_centre(config.target_distance)
    # Local frame: +z toward the robot (world +x), y = world y, x = world −z.
    target = spec.worldbody.add_body(
        name="target", pos=centre, quat=[math.sqrt(0.5), 0, math.sqrt(0.5), 0]
    )
    cyl = mujoco.mjtGeom.mjGEOM_CYLINDER
    common = {"contype": 0, "conaffinity": 0, "group": 2}
    if abs(RING_COLOURS[-1][0] - TARGET_DIAMETER / 2) > 1e-12:
        raise SceneError("the outer ring must have the target's radius")
    step = 0.0004  # m, each outer ring sits this much behind the one inside it
    for i, (radius, rgba) in enumerate(RING_COLOURS):
        front = -i * step
        target.add_geom(
            type=cyl,
            fromto=[0, 0, front - 0.004, 0, 0, front],
            size=[radius, 0, 0],
            rgba=rgba,
            name=f"target_ring_{i}",
            **common,
        )
    boss = -len(RING_COLOURS) * step - 0.004
    target.add_geom(
        type=cyl,
        fromto=[0, 0, boss - 0.06, 0, 0, boss],
        size=[TARGET_DIAMETER / 2, 0, 0],
        rgba=[0.42, 0.40, 0.36, 1.0],
        name="target_boss",
        **common,
    )
    target.add_site(name=TARGET_CENTRE_SITE, size=[0.004, 0, 0], group=4)
    # Stand: two legs from behind the face's rim down to the floor, and a back strut (world frame).
    floor_z = -config.root_height
    x0 = centre[0] - 0.07
    stand_rgba = [0.30, 0.30, 0.30, 1.0]
    for side in (-1.0, 1.0):
        y = centre[1] + side * 0.18
        spec.worldbody.add_geom(
            type=mujoco.mjtGeom.mjGEOM_CAPSULE,
            fromto=[x0, y, centre[2] + 0.1, x0 + 0.05, y, floor_z],
            size=[0.015, 0, 0],
            rgba=stand_rgba,
            name=f"stand_leg_{int(side > 0)}",
            **common,
        )
    spec.worldbody.add_geom(
        type=mujoco.mjtGeom.mjGEOM_CAPSULE,
        fromto=[x0, centre[1], centre[2], x0 - 0.35, centre[1], floor_z],
        size=[0.015, 0, 0],
        rgba=stand_rgba,
        name="stand_strut",
        **common,
    )


def _add_environment(spec: mujoco.MjSpec, config: SceneConfig) -> None:
    floor_z = -config.root_height
    spec.add_texture(
        name="grid",
        type=mujoco.mjtTexture.mjTEXTURE_2D,
        builtin=mujoco.mjtBuiltin.mjBUILTIN_CHECKER,
        width=512,
        height=512,
        rgb1=[0.55, 0.55, 0.55],
        rgb2=[0.50, 0.50, 0.50],
    )
    floor_mat = spec.add_material(name="floor", texrepeat=[8, 8], reflectance=0.0)
    floor_mat.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = "grid"
    spec.add_texture(
        name="sky",
        type=mujoco.mjtTexture.mjTEXTURE_SKYBOX,
        builtin=mujoco.mjtBuiltin.mjBUILTIN_GRADIENT,
        width=256,
        height=256,
        rgb1=[0.80, 0.85, 0.90],
        rgb2=[0.35, 0.40, 0.45],
    )
    spec.worldbody.add_geom(
        name="floor",
        type=mujoco.mjtGeom.mjGEOM_PLANE,
        pos=[-1.5, 0, floor_z],
        size=[5, 5, 0.1],
        material="floor",
        contype=0,
        conaffinity=0,
        group=0,
    )
    light = spec.worldbody.add_light(
        name="sun",
        type=mujoco.mjtLightType.mjLIGHT_DIRECTIONAL,
        pos=[1.0, 1.0, 3.0],
        dir=[-0.6, -0.3, -1.0],
        castshadow=True,
    )
    light.diffuse = [0.6, 0.6, 0.6]
    light.specular = [0.1, 0.1, 0.1]
    # A soft fill light facing the target face so the rings keep their colours in the camera.
    fill = spec.worldbody.add_light(
        name="fill",
        type=mujoco.mjtLightType.mjLIGHT_DIRECTIONAL,
        pos=[0.5, 0.0, 1.5],
        dir=[-1.0, 0.0, -0.3],
        castshadow=False,
    )
    fill.diffuse = [0.35, 0.35, 0.35]
    fill.specular = [0.0, 0.0, 0.0]
    headlight = spec.visual.headlight
    headlight.ambient = [0.35, 0.35, 0.35]
    headlight.diffuse = [0.25, 0.25, 0.25]
    headlight.specular = [0.05, 0.05, 0.05]
    spec.visual.global_.offwidth = 1920
    spec.visual.global_.offheight = 1080
    spec.visual.quality.shadowsize = 2048  # software GL renders 1280×720 in ~0.1 s with this
    centre = target_centre(config.target_distance)
    eye = np.asarray(config.camera_pos)
    spec.worldbody.add_camera(
        name=TARGET_CAMERA, pos=eye, quat=look_at_quat(eye, centre), fovy=config.camera_fovy
    )
    side_eye = np.array([-1.15, 3.2, 0.35])
    side_look = np.array([-1.15, 0.0, -0.05])
    spec.worldbody.add_camera(
        name=SIDE_CAMERA, pos=side_eye, quat=look_at_quat(side_eye, side_look), fovy=45.0
    )


def _tune_servos(model: mujoco.MjModel, config: SceneConfig) -> None:
    """Set kp = I·ω² and kv = 2ζ·I·ω − (joint damping), with I the joint's inertia at home."""
    data = mujoco.MjData(model)
    for part, joints in PARTS.items():
        for name, value in zip(joints, HOME_POSTURE[part], strict=True):
            data.qpos[model.joint(name).qposadr[0]] = value
    mujoco.mj_forward(model, data)
    mass = np.zeros((model.nv, model.nv))
    mujoco.mj_fullM(model, data, mass)
    omega, zeta = config.servo_bandwidth, config.servo_damping_ratio
    for joints in PARTS.values():
        for name in joints:
            dof = model.joint(name).dofadr[0]
            act = model.actuator(name).id
            inertia = mass[dof, dof]
            kp = inertia * omega**2
            kv = max(0.0, 2.0 * zeta * inertia * omega - model.dof_damping[dof])
            model.actuator_gainprm[act, 0] = kp
            model.actuator_biasprm[act, :3] = (0.0, -kp, -kv)


def build_scene(config: SceneConfig | None = None) -> mujoco.MjModel:
    """Build and compile the archery scene described by `config` (defaults if None).

    Raises:
        SceneError: the icub-models file or its meshes are missing or unexpected.
    """
    config = SceneConfig() if config is None else config
    spec = _robot_spec(config)
    spec.modelname = "icub_archery"
    option = spec.option
    option.timestep = config.timestep
    option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    option.disableflags |= mujoco.mjtDisableBit.mjDSBL_CONTACT
    option.density = 0.0  # air drag is applied explicitly to the arrow (sim.arrow)
    option.viscosity = 0.0
    sites = _add_hand_sites(spec)
    _add_bow(spec, sites[BOW_HAND_SITE])
    _add_arrow(spec, config)
    _add_target(spec, config)
    _add_environment(spec, config)
    try:
        model = spec.compile()
    except ValueError as exc:
        raise SceneError(f"the archery scene does not compile: {exc}") from exc
    _tune_servos(model, config)
    return model


# --------------------------------------------------------------------------------------------
# Physics queries by name


class ScenePhysics:
    """Name-resolved access to a compiled archery scene's state; no task logic.

    Positions are metres in the root frame (= MuJoCo world), angles radians, times seconds.
    """

    def __init__(self, model: mujoco.MjModel, data: mujoco.MjData | None = None) -> None:
        self.model = model
        self.data = mujoco.MjData(model) if data is None else data
        try:
            self._qpos = {
                p: np.array([model.joint(j).qposadr[0] for j in js]) for p, js in PARTS.items()
            }
            self._dof = {
                p: np.array([model.joint(j).dofadr[0] for j in js]) for p, js in PARTS.items()
            }
            self._act = {p: np.array([model.actuator(j).id for j in js]) for p, js in PARTS.items()}
            self._margin = {
                p: model.jnt_margin[[model.joint(j).id for j in js]].copy()
                for p, js in PARTS.items()
            }
            self._range = {
                p: model.jnt_range[[model.joint(j).id for j in js]].copy()
                for p, js in PARTS.items()
            }
            self._site = {
                n: model.site(n).id
                for n in (BOW_HAND_SITE, STRING_HAND_SITE, ARROW_TIP_SITE, TARGET_CENTRE_SITE)
            }
            arrow = model.joint(ARROW_JOINT)
            self._arrow_body = model.body(ARROW_BODY).id
        except KeyError as exc:
            raise SceneError(
                f"not an archery scene (build it with sim.scene.build_scene): {exc}"
            ) from exc
        self._arrow_qpos = int(arrow.qposadr[0])
        self._arrow_dof = int(arrow.dofadr[0])
        self.arrow_mass = float(model.body_mass[self._arrow_body])

    # -- joints ---------------------------------------------------------------------------
    def _part(self, part: str) -> str:
        if part not in PARTS:
            raise CommandError(f"unknown part {part!r}; parts: {', '.join(PARTS)}")
        return part

    def joint_names(self, part: str) -> tuple[str, ...]:
        """Joint names of `part` in YARP order."""
        return PARTS[self._part(part)]

    def qpos_indices(self, part: str) -> np.ndarray:
        """Indices of `part`'s joint angles in `data.qpos`, YARP order."""
        return self._qpos[self._part(part)].copy()

    def dof_indices(self, part: str) -> np.ndarray:
        """Indices of `part`'s joint velocities in `data.qvel`, YARP order."""
        return self._dof[self._part(part)].copy()

    def actuator_indices(self, part: str) -> np.ndarray:
        """Indices of `part`'s position servos in `data.ctrl`, YARP order."""
        return self._act[self._part(part)].copy()

    def joint_limits(self, part: str) -> tuple[np.ndarray, np.ndarray]:
        """(lower, upper) URDF joint limits of `part` (rad)."""
        limits = self._range[self._part(part)]
        return limits[:, 0].copy(), limits[:, 1].copy()

    def joint_margins(self, part: str) -> np.ndarray:
        """How far inside its URDF limits each of `part`'s joint stops engages (rad)."""
        return self._margin[self._part(part)].copy()

    def joint_positions(self, part: str) -> np.ndarray:
        """Joint angles of `part` (rad)."""
        return self.data.qpos[self._qpos[self._part(part)]].copy()

    def joint_velocities(self, part: str) -> np.ndarray:
        """Joint velocities of `part` (rad/s)."""
        return self.data.qvel[self._dof[self._part(part)]].copy()

    def set_joint_positions(self, part: str, values: np.ndarray) -> None:
        """Teleport `part`'s joints to `values` (rad) at rest; kinematics are not recomputed."""
        self.data.qpos[self._qpos[self._part(part)]] = values
        self.data.qvel[self._dof[part]] = 0.0

    def controls(self, part: str) -> np.ndarray:
        """Position-servo setpoints of `part` (rad)."""
        return self.data.ctrl[self._act[self._part(part)]].copy()

    def set_controls(self, part: str, values: np.ndarray) -> None:
        """Write `part`'s position-servo setpoints (rad); no clamping here."""
        self.data.ctrl[self._act[self._part(part)]] = values

    # -- sites ----------------------------------------------------------------------------
    def site_position(self, name: str) -> np.ndarray:
        """Position of the site `name` (m) as of the last kinematics pass."""
        site = self._site.get(name)
        if site is None:
            raise CommandError(f"unknown site {name!r}; sites: {', '.join(self._site)}")
        return self.data.site_xpos[site].copy()

    def site_rotation(self, name: str) -> np.ndarray:
        """3×3 rotation of the site `name` (columns: its axes in the root frame)."""
        site = self._site.get(name)
        if site is None:
            raise CommandError(f"unknown site {name!r}; sites: {', '.join(self._site)}")
        return self.data.site_xmat[site].reshape(3, 3).copy()

    def hand_positions(self) -> tuple[np.ndarray, np.ndarray]:
        """(bow hand, string hand) end-effector positions (m) as of the last kinematics pass."""
        return self.site_position(BOW_HAND_SITE), self.site_position(STRING_HAND_SITE)

    # -- the arrow ------------------------------------------------------------------------
    def arrow_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """(tip position (m), orientation quaternion w, x, y, z) of the arrow."""
        q = self.data.qpos[self._arrow_qpos : self._arrow_qpos + 7]
        return q[:3].copy(), q[3:].copy()

    def set_arrow_pose(self, tip: np.ndarray, quat: np.ndarray) -> None:
        """Place the arrow's tip at `tip` (m) with orientation `quat` (w, x, y, z)."""
        self.data.qpos[self._arrow_qpos : self._arrow_qpos + 3] = tip
        self.data.qpos[self._arrow_qpos + 3 : self._arrow_qpos + 7] = quat

    def stowed_arrow_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """(tip (m), quaternion) of the arrow's place off the bow: the model's initial pose."""
        q = self.model.qpos0[self._arrow_qpos : self._arrow_qpos + 7]
        return q[:3].copy(), q[3:].copy()

    def arrow_tip(self) -> np.ndarray:
        """The arrow tip's position (m): the free joint's translation, exact after any step."""
        return self.data.qpos[self._arrow_qpos : self._arrow_qpos + 3].copy()

    def arrow_velocity(self) -> np.ndarray:
        """The arrow's linear velocity (m/s)."""
        return self.data.qvel[self._arrow_dof : self._arrow_dof + 3].copy()

    def set_arrow_velocity(self, linear: np.ndarray, angular: np.ndarray | None = None) -> None:
        """Set the arrow's linear (m/s, world) and angular (rad/s, body frame) velocity."""
        self.data.qvel[self._arrow_dof : self._arrow_dof + 3] = linear
        self.data.qvel[self._arrow_dof + 3 : self._arrow_dof + 6] = (
            0.0 if angular is None else angular
        )

    def set_arrow_force(self, force: np.ndarray) -> None:
        """Apply `force` (N, world frame) at the arrow's centre of mass until changed."""
        self.data.xfrc_applied[self._arrow_body, :3] = force
        self.data.xfrc_applied[self._arrow_body, 3:] = 0.0

    # -- time and integration ---------------------------------------------------------------
    @property
    def time(self) -> float:
        """Simulated time (s)."""
        return float(self.data.time)

    @property
    def timestep(self) -> float:
        """Physics step (s)."""
        return float(self.model.opt.timestep)

    @property
    def gravity(self) -> np.ndarray:
        """Gravity (m/s², root frame)."""
        return self.model.opt.gravity.copy()

    def reset(self) -> None:
        """Reset the data to the model's initial state (time 0, qpos0, zero velocity)."""
        mujoco.mj_resetData(self.model, self.data)

    def kinematics(self) -> None:
        """Recompute body and site poses from qpos."""
        mujoco.mj_kinematics(self.model, self.data)

    def forward(self) -> None:
        """Recompute every derived quantity from the state (no integration)."""
        mujoco.mj_forward(self.model, self.data)

    def step(self) -> None:
        """Advance the physics by one timestep."""
        mujoco.mj_step(self.model, self.data)

    def qpos(self) -> np.ndarray:
        """A copy of the full generalised position vector (enough to render the scene)."""
        return self.data.qpos.copy()

    def unstable(self) -> bool:
        """True if MuJoCo flagged a bad (NaN/Inf/huge) acceleration since the last reset."""
        return bool(self.data.warning[mujoco.mjtWarning.mjWARN_BADQACC].number > 0)
