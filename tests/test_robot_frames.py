"""The robot in 3D in a recording: link transforms, joint states, the scene's meshes and the
robot description, read back as a generic MCAP reader (Foxglove) reads them."""

from __future__ import annotations

import base64
import json
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import mujoco
import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

from archery.apps.topics.recording import DESCRIPTION_METADATA, Recorder, open_recording
from archery.apps.topics.robot_frames import DESCRIPTION_ATTACHMENT, RobotFrames
from archery.mesh.instances import describe_all
from archery.mesh.netflags import NetConfig
from archery.mesh.node import Node
from archery.protocol.codec import encode
from archery.protocol.messages import Array, JointState, WorldState
from archery.protocol.parts import PARTS
from archery.protocol.robotspec import ROBOT
from archery.services.robot.config import RobotConfig
from archery.services.robot.service import run
from archery.sim.geometry import BOW_HAND, START_THETA
from archery.sim.model_build import build_scene
from archery.sim.scene_config import SceneConfig
from archery.sim.world import ArcheryWorld, WorldConfig
from tests.conftest import serving
from tests.postures import archery_posture
from tests.rpc import rpc_call

ROBOT_KEY = "icubSim"


@pytest.fixture(scope="module")
def frames() -> RobotFrames:
    return RobotFrames(ROBOT_KEY)


def _decoded(path: Path) -> Iterator[tuple[str, str, int, Any]]:
    """(topic, schema, log time, message) as Foxglove decodes them: protobuf from the file's
    schemas, JSON as parsed JSON."""
    factory = DecoderFactory()
    with open(path, "rb") as stream:
        for schema, channel, record in make_reader(stream).iter_messages():
            assert schema is not None
            if channel.message_encoding == "json":
                message = json.loads(record.data)
            else:
                decoder = factory.decoder_for(channel.message_encoding, schema)
                assert decoder is not None
                message = decoder(record.data)
            yield channel.topic, schema.name, record.log_time, message


def _world_poses(transforms: Any) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Each frame's pose in `world` (position m, rotation matrix), chained from the file's
    parent-relative transforms."""
    local = {}
    for t in transforms.transforms:
        quat = np.array([t.rotation.w, t.rotation.x, t.rotation.y, t.rotation.z])
        mat = np.empty(9)
        mujoco.mju_quat2Mat(mat, quat)
        position = np.array([t.translation.x, t.translation.y, t.translation.z])
        local[t.child_frame_id] = (t.parent_frame_id, position, mat.reshape(3, 3))
    poses: dict[str, tuple[np.ndarray, np.ndarray]] = {"world": (np.zeros(3), np.eye(3))}

    def pose(frame: str) -> tuple[np.ndarray, np.ndarray]:
        if frame not in poses:
            parent, position, mat = local[frame]
            p, r = pose(parent)
            poses[frame] = (p + r @ position, r @ mat)
        return poses[frame]

    for frame in local:
        pose(frame)
    return poses


def test_link_poses_rebuilt_from_the_file_match_the_simulators(
    frames: RobotFrames, tmp_path: Path
) -> None:
    # The simulator moves to the joint positions that aim START_THETA, nocks and shoots; every
    # 20 ms its qpos is recorded as the robot publishes it, and its own link poses are kept to
    # compare with.
    world = ArcheryWorld(WorldConfig(scene=SceneConfig(meshes=False)))
    world.reset(3)
    aim_joints = archery_posture(world.model, BOW_HAND, BOW_HAND + START_THETA, tolerance=5e-3)
    for part, q in aim_joints.items():
        world.set_joint_targets(part, q)
    path = tmp_path / "robot.mcap"
    recorder = Recorder(path, ROBOT_KEY, [f"{ROBOT_KEY}/**"], frames=frames)
    truth = []
    for seq in range(1, 121):
        world.step(0.02)
        if seq == 60:
            world.nock()
        if seq == 70:
            world.launch()
        world.physics.kinematics()  # the simulator's poses of the qpos it publishes
        data = world.physics.data
        names = [world.model.body(i).name for i in range(1, world.model.nbody)]
        truth.append(
            {
                n: (data.xpos[i + 1].copy(), data.xmat[i + 1].reshape(3, 3).copy())
                for i, n in enumerate(names)
            }
        )
        state = WorldState(qpos=Array.from_numpy(world.qpos()), seq=seq, stamp=1000.0 + seq)
        recorder.put(f"{ROBOT_KEY}/world/state:o", encode(state))
        joints = world.joint_positions("left_arm")
        left = JointState(
            part="left_arm",
            names=list(PARTS["left_arm"]),
            position=joints.tolist(),
            velocity=world.joint_velocities("left_arm").tolist(),
            seq=seq,
            stamp=1000.0 + seq,
        )
        recorder.put(f"{ROBOT_KEY}/left_arm/state:o", encode(left))
    stats = recorder.close()
    assert stats.derived == 1 + 2 * 120  # the scene, then a record per world and joint state
    tf = [m for topic, _, _, m in _decoded(path) if topic == f"{ROBOT_KEY}/tf"]
    assert len(tf) == len(truth) == 120
    worst_mm, worst_rad = 0.0, 0.0
    for message, expected in zip(tf, truth, strict=True):
        poses = _world_poses(message)
        assert set(expected) <= set(poses)
        for name, (position, mat) in expected.items():
            got_position, got_mat = poses[name]
            worst_mm = max(worst_mm, 1000 * float(np.linalg.norm(got_position - position)))
            cos = (np.trace(got_mat.T @ mat) - 1) / 2
            worst_rad = max(worst_rad, float(np.arccos(np.clip(cos, -1, 1))))
    assert worst_mm <= 1.0 and worst_rad <= 1e-3, (worst_mm, worst_rad)
    # the arrow and the hands moved: the comparison covered a motion and a flight
    tips = [p["arrow"][0] for p in (_world_poses(m) for m in tf)]
    assert np.linalg.norm(tips[-1] - tips[0]) > 0.5
    stamps = [m.transforms[0].timestamp.seconds for m in tf]
    assert stamps == [1000 + seq for seq in range(1, 121)]


def test_joint_states_scene_and_description_are_in_the_file(
    frames: RobotFrames, tmp_path: Path
) -> None:
    path = tmp_path / "scene.mcap"
    recorder = Recorder(path, ROBOT_KEY, [f"{ROBOT_KEY}/**"], frames=frames)
    state = JointState(
        part="torso",
        names=list(PARTS["torso"]),
        position=[0.1, 0.2, 0.3],
        velocity=[0.0, -1.0, 2.0],
        seq=1,
        stamp=5.0,
    )
    recorder.put(f"{ROBOT_KEY}/torso/state:o", encode(state))
    recorder.close()
    decoded = list(_decoded(path))
    by_topic = {topic: (schema, message) for topic, schema, _, message in decoded}
    schema, joints = by_topic[f"{ROBOT_KEY}/joint_states"]
    assert schema == "foxglove.JointStates"
    assert [j.name for j in joints.joints] == list(PARTS["torso"])
    assert [j.position for j in joints.joints] == [0.1, 0.2, 0.3]
    assert [j.velocity for j in joints.joints] == [0.0, -1.0, 2.0]
    schema, scene = by_topic[f"{ROBOT_KEY}/robot_description/scene"]
    assert schema == "foxglove.SceneUpdate" and decoded[0][0].endswith("/scene")
    entities = {e.id: e for e in scene.entities}
    # the compiled scene fuses fixed bodies: the bow into l_hand, the target into world
    assert {"world", "chest", "l_hand", "r_forearm", "arrow"} <= set(entities)
    chest = entities["chest"]
    assert chest.frame_id == "chest" and chest.frame_locked and chest.models
    stl = chest.models[0].data
    triangles = int.from_bytes(stl[80:84], "little")
    assert chest.models[0].media_type == "model/stl" and len(stl) == 84 + 50 * triangles > 84
    assert entities["arrow"].cylinders and entities["l_hand"].cylinders  # arrow, bow
    assert len(entities["world"].cylinders) >= 6  # the target's rings and boss
    # the replay reads the recorded messages only, not the derived records
    recording = open_recording(path)
    assert [key for key, _, _ in recording.messages()] == [f"{ROBOT_KEY}/torso/state:o"]
    urdf = recording.attachment(DESCRIPTION_ATTACHMENT)
    assert urdf is not None and b'<robot name="iCub">' in urdf and b"package://iCub/" in urdf
    with open(path, "rb") as stream:
        metadata = {m.name: m.metadata for m in make_reader(stream).iter_metadata()}
    assert metadata[DESCRIPTION_METADATA]["tf"] == f"{ROBOT_KEY}/tf"


def _until_tapped(node: Node) -> None:
    """Call the robot's `status` until its tap publishes it (the recorder's subscription has
    reached the robot), as its `describe` counts."""
    key = f"{node.keys.robot}/archery/requests:o"
    deadline = time.monotonic() + 30
    while True:
        rpc_call(node, node.keys.archery_rpc(), "status", timeout=30)
        described = describe_all(node.session, node.keys)
        if any(p.key == key and p.count for d in described.values() for p in d.ports):
            return
        assert time.monotonic() < deadline, "the robot never saw the recorder subscribe"


@pytest.mark.slow
def test_archery_record_of_a_running_robot_has_it_in_3d_and_its_calls(
    net: NetConfig, tmp_path: Path
) -> None:
    path = tmp_path / "run.mcap"
    config = RobotConfig(net=net, world=WorldConfig(scene=SceneConfig(meshes=False)))
    flags = ["--connect", net.connect[0], "--robot", net.robot]
    with serving(run, config), Node(None, net) as node:
        node.wait_alive([ROBOT], 30)
        recorder = subprocess.Popen(
            [sys.executable, "-m", "archery.apps.cli", "record", "--out", str(path), *flags],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        try:
            assert recorder.stdout is not None
            assert "recording" in recorder.stdout.readline()  # subscribed: the mesh can go on
            _until_tapped(node)
            for verb in ("nock", "release", "reset"):
                rpc_call(node, node.keys.archery_rpc(), verb, timeout=30)
        finally:
            recorder.terminate()
            _, err = recorder.communicate(timeout=60)
        assert recorder.returncode == 0, err
    decoded = list(_decoded(path))
    states = [m for t, _, _, m in decoded if t == f"{net.robot}/world/state:o"]
    tf = [m for t, _, _, m in decoded if t == f"{net.robot}/tf"]
    assert len(tf) == len(states) >= 3
    model = build_scene(SceneConfig(meshes=False))  # the simulator's kinematics, built anew
    data = mujoco.MjData(model)
    for state, message in zip(states, tf, strict=True):
        qpos = state["qpos"]
        data.qpos[:] = np.frombuffer(base64.b64decode(qpos["data"]), dtype=qpos["dtype"])
        mujoco.mj_kinematics(model, data)
        poses = _world_poses(message)
        for i in range(1, model.nbody):
            got, _ = poses[model.body(i).name]
            assert np.linalg.norm(got - data.xpos[i]) <= 1e-3
    # what the robot was asked and answered, on their own channels
    asked = [m["verb"] for t, _, _, m in decoded if t == f"{net.robot}/archery/requests:o"]
    answered = [m["ok"] for t, _, _, m in decoded if t == f"{net.robot}/archery/replies:o"]
    assert asked[-3:] == ["nock", "release", "reset"] and set(asked[:-3]) == {"status"}
    assert len(answered) == len(asked) and all(answered)
    info = subprocess.run(
        [sys.executable, "-m", "archery.apps.cli", "info", str(path)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert info.returncode == 0, info.stderr
    channels = ("tf", "joint_states", "robot_description/scene", "world/state:o")
    for channel in (*channels, "archery/requests:o", "archery/replies:o"):
        assert f"{net.robot}/{channel} " in info.stdout, info.stdout
    assert DESCRIPTION_ATTACHMENT in info.stdout


def _urdf_parents() -> dict[str, str]:
    """{link: its parent link} of the robot description, read with the standard XML parser."""
    import xml.etree.ElementTree as ET

    from archery.sim.urdf import urdf_text

    root = ET.fromstring(urdf_text())
    return {
        j.find("child").get("link"): j.find("parent").get("link")  # type: ignore[union-attr]
        for j in root.findall("joint")
    }


def test_every_link_of_the_urdf_has_its_transform_from_its_urdf_parent(
    frames: RobotFrames,
) -> None:
    """`/tf` and `/tf_static` (and Foxglove's transforms) are the URDF's own tree: every link
    but the root reached from its URDF parent, with the URDF's frame names."""
    parents = _urdf_parents()
    edges = [*frames.static_links, *frames.links]
    by_child = {child: parent for parent, child in edges}
    assert len(by_child) == len(edges)  # one transform per frame
    for link, parent in parents.items():
        assert by_child.get(link) == parent, link
    root = (set(parents.values()) - set(parents)).pop()
    assert by_child[root] == "world"
    assert {"root_link", "r_upper_arm", "r_elbow_1"} <= set(by_child)
    assert set(by_child) - set(parents) == {root, "arrow"}  # the scene's one other body


def test_the_urdf_tree_at_any_posture_is_where_the_simulator_puts_each_body(
    frames: RobotFrames,
) -> None:
    """The forward kinematics over the URDF's joints (origins, axes, the positions in qpos)
    agrees with MuJoCo's for every body of the scene."""
    model = frames.model
    data = mujoco.MjData(model)
    rng = np.random.default_rng(7)
    qpos = model.qpos0.copy()
    for j in range(model.njnt):
        if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE:
            low, high = model.jnt_range[j] if model.jnt_limited[j] else (-1.0, 1.0)
            qpos[model.jnt_qposadr[j]] = rng.uniform(low, high)
    translations, rotations = frames.poses(qpos)
    fixed_t, fixed_q = frames.static_poses()
    edges = {
        child: (parent, t, q)
        for (parent, child), t, q in zip(
            [*frames.static_links, *frames.links],
            np.concatenate([fixed_t, translations]),
            np.concatenate([fixed_q, rotations]),
            strict=True,
        )
    }
    world: dict[str, tuple[np.ndarray, np.ndarray]] = {"world": (np.zeros(3), np.eye(3))}

    def pose(frame: str) -> tuple[np.ndarray, np.ndarray]:
        if frame not in world:
            parent, t, q = edges[frame]
            p, r = pose(parent)
            mat = np.empty(9)
            mujoco.mju_quat2Mat(mat, q)
            world[frame] = (p + r @ t, r @ mat.reshape(3, 3))
        return world[frame]

    data.qpos[:] = qpos
    mujoco.mj_kinematics(model, data)
    for b in range(1, model.nbody):
        position, mat = pose(model.body(b).name)
        np.testing.assert_allclose(position, data.xpos[b], atol=1e-9)
        np.testing.assert_allclose(mat, data.xmat[b].reshape(3, 3), atol=1e-9)
