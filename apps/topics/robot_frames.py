"""The robot in 3D for a recording: link poses, joint states and the scene's meshes, derived in
the recorder from the streams it records.

The robot service publishes its full generalized position on `world/state:o` (`WorldState.qpos`,
30 Hz of simulated time) and each part's joints on `PART/state:o`. The recorder already
receives them, so it derives the 3D records itself, with the very kinematics the simulator
runs: the robot's loop pays nothing for them, and a recording of any robot of this version gets
them. `RobotFrames` lists the derived channels; docs/commands.md, under
`archery record`, tells them from the user's side.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from typing import Any

import mujoco
import numpy as np
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate

from archery.apps.topics.foxglove_records import (
    FRAME_TRANSFORMS,
    JOINT_STATES,
    SCENE_UPDATE,
    frame_transforms,
    joint_states,
    stamp,
    stl_bytes,
)
from archery.apps.topics.recording import Derived
from archery.apps.topics.urdf_tree import UrdfJoint, parse_joints
from archery.protocol.messages import JointState, WorldState
from archery.protocol.messages import Message as ArcheryMessage
from archery.protocol.robotspec import MODEL_NAME
from archery.sim.model_build import build_scene
from archery.sim.scene_config import TARGET_CAMERA, SceneConfig
from archery.sim.urdf import urdf_text

__all__ = [
    "DESCRIPTION_ATTACHMENT",
    "RobotFrames",
    "link_poses",
]

DESCRIPTION_ATTACHMENT = "robot_description.urdf"
_DRAWN_GROUPS = (0, 1, 2)  # floor, robot, props; higher groups are markers


def link_poses(model: mujoco.MjModel, data: mujoco.MjData) -> tuple[np.ndarray, np.ndarray]:
    """Every body's pose (bodies 1…) in its parent body's frame, from `data`'s kinematics:
    translations (N, 3, m) and rotations (N, 4, w x y z)."""
    parents = model.body_parentid[1:]
    child_pos, child_quat = data.xpos[1:], data.xquat[1:]
    parent_pos, parent_mat = data.xpos[parents], data.xmat[parents].reshape(-1, 3, 3)
    translations = np.einsum("nji,nj->ni", parent_mat, child_pos - parent_pos)
    rotations = np.empty((len(parents), 4))
    inverse = np.empty(4)
    for i, parent in enumerate(parents):
        mujoco.mju_negQuat(inverse, data.xquat[parent])
        mujoco.mju_mulQuat(rotations[i], inverse, child_quat[i])
    return translations, rotations


class RobotFrames:
    """Derives the 3D records of one robot's recording, with the scene compiled from the
    robot's `SceneConfig` and `mj_kinematics`. Derived channels, next to the recorded keys:

    * `ROBOT/tf` (`foxglove.FrameTransforms`): per world state, the URDF's own tree (every
      link in its URDF parent's frame, by the URDF's joints: `apps.topics.urdf_tree`, the
      fixed ones with them) and the scene's other bodies (the arrow) in their parent's frame;
      `world` is the iCub's `root_link` frame (x backward, y right, z up; m);
    * `ROBOT/joint_states` (`foxglove.JointStates`): per joint state, the part's joints (rad,
      rad/s); the JSON `PART/state:o` channel stays as it was;
    * `ROBOT/robot_description/scene` (`foxglove.SceneUpdate`, once at the start): one entity
      per body, locked to its frame, with the robot's meshes embedded (binary STL) and the
      props' primitives, so Foxglove's 3D panel draws the robot without any file of this
      machine.

    The robot description itself (the URDF the robot runs, `icub-models`' file, its meshes as
    `package://iCub/` URIs) goes into the recording as an attachment (`attachments`), and the
    scene parameters as a metadata record (`metadata`).

    Args:
        robot: the robot's key prefix.
        scene: the scene the robot runs (its status's `scene`); the model is built with its
            meshes (about a second).
    """

    def __init__(self, robot: str, scene: SceneConfig | None = None) -> None:
        import dataclasses

        self.scene = dataclasses.replace(scene or SceneConfig(), meshes=True)
        self.model = build_scene(self.scene)
        self.data = mujoco.MjData(self.model)
        names = [self.model.body(i).name for i in range(self.model.nbody)]
        names[0] = "world"
        self.frames = names
        joints = parse_joints(urdf_text())
        linked = {j.child for j in joints} | {j.parent for j in joints}
        root = next(j.parent for j in joints if j.parent not in {k.child for k in joints})
        self.root = root
        # the scene's own bodies (the arrow), in their MuJoCo parent's frame
        self._extras = [b for b in range(1, self.model.nbody) if names[b] not in linked]
        self._moving = [j for j in joints if j.moving]
        self._qpos_of = [self._qpos_address(j.name) for j in self._moving]
        fixed = [j for j in joints if not j.moving]
        #: (parent, child) of each fixed transform (`static_poses`): `world` to the URDF's
        #: root, then every fixed joint of the URDF.
        self.static_links: list[tuple[str, str]] = [
            ("world", root),
            *((j.parent, j.child) for j in fixed),
        ]
        #: (parent, child) of each moving transform (`poses`): every moving joint of the
        #: URDF, then the scene's bodies that are no link of it (the arrow).
        self.links: list[tuple[str, str]] = [
            *((j.parent, j.child) for j in self._moving),
            *((names[self.model.body_parentid[b]], names[b]) for b in self._extras),
        ]
        self._static = self._static_poses(fixed)
        self.tf_topic = f"{robot}/tf"
        self.joints_topic = f"{robot}/joint_states"
        self.scene_topic = f"{robot}/robot_description/scene"
        self._world_state = f"{robot}/world/state:o"

    def attachments(self) -> dict[str, tuple[str, bytes]]:
        """{name: (media type, data)}: the URDF the robot runs."""
        return {DESCRIPTION_ATTACHMENT: ("application/xml", urdf_text().encode())}

    def metadata(self) -> dict[str, str]:
        """The description's metadata record: model, mesh package, scene parameters, topics."""
        return {
            "model": MODEL_NAME,
            "urdf_attachment": DESCRIPTION_ATTACHMENT,
            "mesh_uris": "package://iCub/ = the icub-models package's share/iCub folder",
            "scene": json.dumps(self.scene.to_dict()),
            "tf": self.tf_topic,
            "joint_states": self.joints_topic,
            "scene_update": self.scene_topic,
        }

    def derive(self, key: str, message: ArcheryMessage, ns: int) -> list[Derived]:
        """The records derived from one recorded message (none for most keys)."""
        if isinstance(message, WorldState) and key == self._world_state:
            poses = self.state_poses(message)
            if poses is None:
                return []  # another scene
            return [Derived(self.tf_topic, FRAME_TRANSFORMS, self._transforms(*poses, ns))]
        if isinstance(message, JointState):
            data = joint_states(ns, message.names, message.position, message.velocity)
            return [Derived(self.joints_topic, JOINT_STATES, data)]
        return []

    def _qpos_address(self, joint: str) -> int | None:
        """Where the scene keeps the URDF joint `joint`'s position (None: the scene does not
        move it; it stays at 0)."""
        index = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_JOINT, joint)
        return None if index < 0 else int(self.model.jnt_qposadr[index])

    def _static_poses(self, fixed: Sequence[UrdfJoint]) -> tuple[np.ndarray, np.ndarray]:
        # the scene merges the URDF's root into its world: the same frame
        translations = [np.zeros(3)]
        rotations = [np.array([1.0, 0.0, 0.0, 0.0])]
        for joint in fixed:
            t, r = joint.pose()
            translations.append(t)
            rotations.append(_quat(r))
        return np.array(translations), np.array(rotations)

    def static_poses(self) -> tuple[np.ndarray, np.ndarray]:
        """The fixed transforms, in the order of `self.static_links` (`/tf_static`):
        translations (N, 3, m) and rotations (N, 4, w x y z); `world` to the URDF's root is
        the identity (the scene's world is the robot's `root_link` frame)."""
        return self._static

    def poses(self, qpos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The moving transforms at `qpos` (`self.model.nq` values), in the order of
        `self.links`: each moving URDF joint's child in its parent link's frame (the URDF's
        kinematics: origin, axis, the joint's position in `qpos`), then the scene's other
        bodies in their parent's frame; translations (N, 3, m) and rotations (N, 4, w x y z).
        The transforms of the recorder's, the Foxglove bridge's and the ROS 2 node's `/tf`."""
        translations = np.empty((len(self.links), 3))
        rotations = np.empty((len(self.links), 4))
        for i, (joint, address) in enumerate(zip(self._moving, self._qpos_of, strict=True)):
            t, r = joint.pose(0.0 if address is None else float(qpos[address]))
            translations[i] = t
            rotations[i] = _quat(r)
        if self._extras:
            self.data.qpos[:] = qpos
            mujoco.mj_kinematics(self.model, self.data)
            t, q = link_poses(self.model, self.data)
            rows = [b - 1 for b in self._extras]
            translations[len(self._moving) :] = t[rows]
            rotations[len(self._moving) :] = q[rows]
        return translations, rotations

    def state_poses(self, state: WorldState) -> tuple[np.ndarray, np.ndarray] | None:
        """`poses` at a world state's joints; None for a state of another scene (its joint
        vector not this model's: its poses cannot be computed here)."""
        qpos = state.qpos.to_numpy()
        if qpos.shape != (self.model.nq,):
            return None
        return self.poses(qpos)

    def _transforms(self, translations: np.ndarray, rotations: np.ndarray, ns: int) -> bytes:
        """The `foxglove.FrameTransforms` record of the whole tree: the fixed transforms and
        the moving ones (`poses`)."""
        fixed_t, fixed_q = self._static
        return frame_transforms(
            ns,
            [*self.static_links, *self.links],
            np.concatenate([fixed_t, translations]),
            np.concatenate([fixed_q, rotations]),
        )

    def camera_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """The target camera's optical frame (z forward, x right, y down, as ROS 2's image
        frames) in `world`: translation (3, m) and rotation (4, w x y z). The camera is fixed in
        the world, so its pose does not depend on the robot's joints."""
        mujoco.mj_kinematics(self.model, self.data)
        mujoco.mj_comPos(self.model, self.data)
        mujoco.mj_camlight(self.model, self.data)  # the cameras' poses (mj_kinematics leaves them)
        cam = self.model.camera(TARGET_CAMERA).id
        optical = self.data.cam_xmat[cam].reshape(3, 3) @ np.diag([1.0, -1.0, -1.0])
        rotation = np.empty(4)
        mujoco.mju_mat2Quat(rotation, optical.reshape(-1))
        return self.data.cam_xpos[cam].copy(), rotation

    def scene_update(self, ns: int) -> Derived:
        """The `foxglove.SceneUpdate` record: every drawn geom, on its body's frame."""
        model = self.model
        update = SceneUpdate()
        entities: dict[int, Any] = {}
        for g in range(model.ngeom):
            kind = mujoco.mjtGeom(int(model.geom_type[g]))
            if model.geom_group[g] not in _DRAWN_GROUPS or kind == mujoco.mjtGeom.mjGEOM_PLANE:
                continue
            body = int(model.geom_bodyid[g])
            entity = entities.get(body)
            if entity is None:
                entity = update.entities.add(
                    frame_id=self.frames[body], id=self.frames[body], frame_locked=True
                )
                stamp(entity.timestamp, ns)
                entities[body] = entity
            self._add_geom(entity, g)
        return Derived(self.scene_topic, SCENE_UPDATE, update.SerializeToString())

    def _add_geom(self, entity: object, g: int) -> None:
        model = self.model
        kind = mujoco.mjtGeom(int(model.geom_type[g]))
        mat = model.geom_matid[g]
        rgba = model.mat_rgba[mat] if mat >= 0 else model.geom_rgba[g]
        size = model.geom_size[g]
        if kind == mujoco.mjtGeom.mjGEOM_MESH:
            mesh = model.geom_dataid[g]
            vert = model.mesh_vert[
                model.mesh_vertadr[mesh] : model.mesh_vertadr[mesh] + model.mesh_vertnum[mesh]
            ]
            face = model.mesh_face[
                model.mesh_faceadr[mesh] : model.mesh_faceadr[mesh] + model.mesh_facenum[mesh]
            ]
            shape = entity.models.add(  # type: ignore[attr-defined]  # a SceneEntity
                media_type="model/stl", data=stl_bytes(vert, face), override_color=True
            )
            shape.scale.x = shape.scale.y = shape.scale.z = 1.0
        elif kind in (mujoco.mjtGeom.mjGEOM_CYLINDER, mujoco.mjtGeom.mjGEOM_CAPSULE):
            shape = entity.cylinders.add()  # type: ignore[attr-defined]  # a SceneEntity
            capsule = kind == mujoco.mjtGeom.mjGEOM_CAPSULE
            shape.size.x = shape.size.y = 2 * size[0]
            shape.size.z = 2 * size[1] + (2 * size[0] if capsule else 0.0)
            shape.bottom_scale = shape.top_scale = 1.0
        elif kind == mujoco.mjtGeom.mjGEOM_BOX:
            shape = entity.cubes.add()  # type: ignore[attr-defined]  # a SceneEntity
            shape.size.x, shape.size.y, shape.size.z = (2 * float(s) for s in size)
        elif kind == mujoco.mjtGeom.mjGEOM_SPHERE:
            shape = entity.spheres.add()  # type: ignore[attr-defined]  # a SceneEntity
            shape.size.x = shape.size.y = shape.size.z = 2 * size[0]
        else:
            return
        _pose(shape.pose, model.geom_pos[g], model.geom_quat[g])
        shape.color.r, shape.color.g, shape.color.b, shape.color.a = map(float, rgba)


def _quat(rotation: np.ndarray) -> np.ndarray:
    """A rotation matrix as a unit quaternion (w, x, y, z)."""
    q = np.empty(4)
    mujoco.mju_mat2Quat(q, np.ascontiguousarray(rotation).reshape(-1))
    return q


def _pose(target: object, position: Sequence[float], quat: Sequence[float]) -> None:
    """Set a protobuf `Pose` from a position (m) and a MuJoCo quaternion (w, x, y, z)."""
    p, q = target.position, target.orientation  # type: ignore[attr-defined]  # a Pose
    p.x, p.y, p.z = map(float, position)
    q.w, q.x, q.y, q.z = map(float, quat)
