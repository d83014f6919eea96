"""The official iCub URDF (`protocol.robotspec.MODEL_NAME`, CC BY-SA 4.0), edited for MuJoCo.

* `urdf_text` reads it (the description the robot runs, as the recorder, the bridges and the
  robot frames carry it; `mesh_root` the folder its `package://iCub/` URIs name); for MuJoCo
  its mesh paths are resolved to the `icub-models` package's own mesh files;
* `urdf_joint_limits` reads the controlled joints' limits (rad) without MuJoCo's compile;
* `load_urdf_model` is MuJoCo's plain import (the benchmarks' baseline);
* `robot_spec` keeps only the controlled joints (legs and neck frozen), switches collisions off
  and compensates gravity;
* `urdf_frame_placement` and `add_hand_sites` bring back the URDF frames that MuJoCo fuses into
  their parent bodies (the hand frames), at their exact URDF poses.
"""

from __future__ import annotations

import math
import pathlib
import xml.etree.ElementTree as ET

import mujoco
import numpy as np

from archery.protocol.parts import PARTS
from archery.protocol.robotspec import MODEL_NAME, model_file
from archery.sim.errors import SceneError
from archery.sim.scene_config import BOW_HAND_SITE, STRING_HAND_SITE, SceneConfig

__all__ = [
    "add_hand_sites",
    "load_urdf_model",
    "mesh_root",
    "robot_spec",
    "urdf_frame_placement",
    "urdf_joint_limits",
    "urdf_text",
]

_ROBOT_NAME_TAG = '<robot name="iCub">'
_PACKAGE_PREFIX = "package://iCub/"


def _model_file() -> pathlib.Path:
    path = pathlib.Path(model_file())
    if not path.is_file():
        raise SceneError(f"the icub-models file for {MODEL_NAME!r} is missing: {path}")
    return path


def mesh_root() -> pathlib.Path:
    """The folder the description's `package://iCub/` URIs name (icub-models' `share/iCub`)."""
    return _model_file().parents[2]  # …/share/iCub/robots/<model>/model.urdf → …/share/iCub


def urdf_text(resolve_meshes: bool = False) -> str:
    """The URDF the robot runs; with `resolve_meshes`, its `package://iCub/` mesh paths made
    absolute (the package's share folder), as MuJoCo reads them.

    Raises:
        SceneError: the model file, or the meshes beside it, are missing.
    """
    path = _model_file()
    text = path.read_text(encoding="utf-8")
    if resolve_meshes:
        share = mesh_root()
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
    return mujoco.MjModel.from_xml_string(
        _with_compiler(urdf_text(resolve_meshes=True), 'strippath="false"')
    )


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
    root = ET.fromstring(urdf_text())
    links = {link.get("name") for link in root.iter("link")}
    if frame not in links:
        raise SceneError(
            f"{frame!r} is not a link of {MODEL_NAME}; e.g. {BOW_HAND_SITE}, {STRING_HAND_SITE}"
        )
    parent_joint = {j.find("child").get("link"): j for j in root.iter("joint")}  # type: ignore[union-attr]  # a URDF joint has a <child>
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
        joint_quat = _rpy_quat(rpy)  # type: ignore[arg-type]  # a URDF rpy is 3 angles
        rotated = np.empty(3)
        mujoco.mju_rotVecQuat(rotated, pos, joint_quat)
        pos = np.asarray(xyz) + rotated
        new_quat = np.empty(4)
        mujoco.mju_mulQuat(new_quat, joint_quat, quat)
        quat = new_quat
        link = joint.find("parent").get("link")  # type: ignore[union-attr,assignment]  # a URDF joint has a <parent link=...>
    return link, pos, quat


def urdf_joint_limits() -> dict[str, tuple[float, float]]:
    """The URDF's (lower, upper) limits (rad) of every controlled joint (`PARTS`), by joint name:
    the limits MuJoCo's scene gives those joints (`ScenePhysics.joint_limits`), read from the
    file alone.

    Raises:
        SceneError: the model file is missing, or a controlled joint is absent or has no
            finite lower < upper limit.
    """
    joints = {joint.get("name"): joint for joint in ET.fromstring(urdf_text()).iter("joint")}
    out: dict[str, tuple[float, float]] = {}
    for name in (name for names in PARTS.values() for name in names):
        limit = joints[name].find("limit") if name in joints else None
        try:
            lower = float(limit.get("lower", "nan")) if limit is not None else math.nan
            upper = float(limit.get("upper", "nan")) if limit is not None else math.nan
        except ValueError:
            lower = upper = math.nan
        if not (math.isfinite(lower) and math.isfinite(upper) and lower < upper):
            raise SceneError(f"{MODEL_NAME}: the joint {name!r} has no finite lower < upper limit")
        out[name] = (lower, upper)
    return out


def robot_spec(config: SceneConfig) -> mujoco.MjSpec:
    """The iCub of the URDF as an editable MjSpec, reduced to what the archery task moves.

    Only the joints of `protocol.parts.PARTS` stay (legs and neck are frozen at zero by deleting
    their joints), each with `config`'s armature (kg·m²) and joint-stop margin (rad); every
    collision is off; gravity is compensated on every link; without `config.meshes` the mesh
    geoms are dropped. The position servos are added by `sim.model_build`.

    Raises:
        SceneError: the model file is missing or lacks a controlled joint.
    """
    spec = mujoco.MjSpec.from_string(
        _with_compiler(urdf_text(resolve_meshes=True), 'strippath="false"')
    )
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
    return spec


def add_hand_sites(spec: mujoco.MjSpec) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Add the hand frames MuJoCo fuses away as sites at their exact URDF poses.

    Returns:
        {frame name: (position (m), quaternion w, x, y, z)} of each site in its body's frame.
    """
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
