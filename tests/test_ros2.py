"""`archery up --ros2` and the ROS 2 node against an rmw_zenoh client that is not ours
(zenoh-ros2-sdk, its types given from rosbags: it never clones anything) and zenoh-ext's advanced
subscriber (what rmw_zenoh's transient local subscriptions are), beside a real mesh; then
`archery export --ros2` of the run's recording, read back by rosbags."""

from __future__ import annotations

import logging
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import git
import numpy as np
import pytest
import zenoh
import zenoh.ext
import zenoh_ros2_sdk
from rosbags.rosbag2 import Reader
from zenoh_ros2_sdk import (
    ROS2Publisher,
    ROS2ServiceClient,
    ROS2Subscriber,
    ZenohSession,
    get_service_names_and_types,
    get_topic_info,
    get_topic_names_and_types,
)

from archery.apps.ros2 import convert, typestore
from archery.apps.ros2.graph import MAX_COMMAND_BYTES, TOPICS, Ros2Node
from archery.apps.ros2.graph import SERVICES as SERVICE_NAMES
from archery.apps.ros2.wire import Attachment, data_key
from archery.apps.topics.recording import open_recording
from archery.apps.topics.robot_frames import RobotFrames
from archery.mesh.netflags import NetConfig
from archery.mesh.node import open_node
from archery.mesh.router import free_tcp_endpoint
from archery.mesh.subscription import Subscription
from archery.protocol.journal_records import AbortedRecord, DoneRecord, ProposedRecord
from archery.protocol.messages import Image, JointState, Rollout
from archery.protocol.parts import PARTS
from archery.protocol.robotspec import COMMAND_BURST, COMMAND_RATE, SERVICES
from archery.protocol.verbs import robot as rv
from archery.sim.scene_config import SceneConfig
from archery.sim.urdf import urdf_text
from tests.conftest import archery
from tests.ros2_sdk import sdk_session, until

ROBOT = "rostwo"
NS = f"/{ROBOT}"


def _definition(ros_type: str) -> str:
    return typestore.messages().generate_msgdef(ros_type, ros_version=2)[0]


class Mesh:
    """`archery up --ros2 --record` on a free port, a node on it, an SDK session on it."""

    def __init__(self, tmp: Path) -> None:
        self.endpoint = free_tcp_endpoint()
        self.recording = tmp / "run.mcap"
        self.up = subprocess.Popen(
            [sys.executable, "-m", "archery.apps.cli", "up", "--listen", self.endpoint,
             "--robot", ROBOT, "--logs", str(tmp / "logs"), "--runs", str(tmp / "runs"), "--ros2",
             "--record", str(self.recording)],
            stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL,
            text=True,
        )  # fmt: skip
        assert self.up.stdout is not None
        for line in self.up.stdout:
            if line.startswith("archery up: all alive"):
                break
        self.net = NetConfig(connect=(self.endpoint,), robot=ROBOT)
        self.node = open_node(self.net, 60)
        self.node.wait_alive(SERVICES, timeout=120)
        self.host, port = self.endpoint.split("/", 1)[1].rsplit(":", 1)
        self.port = int(port)
        self.sdk = sdk_session(self.net)

    def stop(self) -> None:
        if self.up.poll() is None:
            self.up.terminate()
            self.up.communicate(timeout=120)

    def close(self) -> None:
        self.sdk.session.close()
        ZenohSession._instance = None
        self.node.close()
        self.stop()


@pytest.fixture(scope="module")
def mesh(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Mesh]:
    running = Mesh(tmp_path_factory.mktemp("ros2"))
    try:
        yield running
    finally:
        running.close()


@pytest.fixture(autouse=True)
def _no_clone(monkeypatch: pytest.MonkeyPatch) -> None:
    """The SDK clones message repositories when it lacks a type: fail instead."""

    def refuse(*args: object, **kwargs: object) -> None:
        raise AssertionError(f"zenoh-ros2-sdk tried to fetch message definitions: {args}")

    monkeypatch.setattr(zenoh_ros2_sdk._cache, "clone_to_cache", refuse)
    monkeypatch.setattr(zenoh_ros2_sdk.message_registry, "clone_to_cache", refuse)
    monkeypatch.setattr(git.Repo, "clone_from", refuse)


@pytest.fixture
def operator(mesh: Mesh) -> Iterator[Ros2Node]:
    """A node with the operator's services, on domain 1 (the `up` child's is on domain 0)."""
    status = mesh.node.call_typed(mesh.node.keys.archery_rpc(), rv.ARCHERY_STATUS)
    scene = SceneConfig.of(status.scene)
    node = Ros2Node(
        mesh.node, RobotFrames(ROBOT, scene), urdf_text(), scene.camera_fovy, domain=1,
        namespace=NS, operator=True,
    )  # fmt: skip
    try:
        yield node
    finally:
        node.close()


def _subscriber(mesh: Mesh, topic: str, ros_type: str, got: list[Any], domain: int = 0) -> Any:
    return ROS2Subscriber(
        topic, ros_type, got.append, msg_definition=_definition(ros_type),
        type_hash=typestore.type_hash(ros_type), domain_id=domain, router_ip=mesh.host,
        router_port=mesh.port,
    )  # fmt: skip


def test_the_sdk_discovers_the_node_and_its_topics(mesh: Mesh) -> None:
    def listed() -> dict[str, list[str]]:
        found = get_topic_names_and_types(0, mesh.host, mesh.port, timeout=1.0)
        return {name: types for name, types in found if name.startswith((NS, "/tf"))}

    expected = {
        (t.name if t.name.startswith("/") else f"{NS}/{t.name}"): t.ros_type for t in TOPICS
    }
    topics = until(lambda: (lambda f: f if set(expected) <= set(f) else None)(listed()), "topics")
    for name, ros_type in expected.items():
        assert topics[name] == [ros_type]
    info = get_topic_info(f"{NS}/joint_states", 0, mesh.host, mesh.port, 1.0, verbose=True)
    publisher = info.publishers[0]
    assert (publisher.node_name, publisher.node_namespace) == ("archery", NS)
    assert publisher.type_hash == typestore.type_hash("sensor_msgs/msg/JointState")
    # read-only: the services are on the graph (their SS tokens), a call is answered
    # `success: false` (test_a_reset_without_the_operator_is_refused)
    services = get_service_names_and_types(0, mesh.host, mesh.port, timeout=1.0)
    ours = {name: types for name, types in services if name.startswith(NS)}
    assert ours == {f"{NS}/{name}": [typestore.TRIGGER] for name in SERVICE_NAMES}


def test_every_token_carries_the_hash_rosbags_computes(mesh: Mesh) -> None:
    replies = mesh.sdk.session.liveliness().get(f"@ros2_lv/0/*/*/*/*/%/%{ROBOT}/archery/**")
    tokens = [str(reply.ok.key_expr) for reply in replies if reply.ok is not None]
    assert tokens
    endpoints = [token.split("/") for token in tokens if token.split("/")[5] != "NN"]
    assert len(endpoints) == len(tokens) - 1
    for chunks in endpoints:
        package, kind, rest = chunks[10].split("::", 2)
        ros_type = f"{package}/{kind}/{rest.removeprefix('dds_::').removesuffix('_')}"
        assert chunks[11] == typestore.type_hash(ros_type), chunks


def test_joint_states_equal_the_robots(mesh: Mesh) -> None:
    received: list[Any] = []
    sub = _subscriber(mesh, f"{NS}/joint_states", "sensor_msgs/msg/JointState", received)
    states: dict[int, JointState] = {}
    mesh_subs = [
        Subscription(
            mesh.node.session,
            mesh.node.keys.state(part),
            JointState,
            "fifo",
            lambda s: states.__setitem__(round(s.stamp * 1e9), s),
        )
        for part in PARTS
    ]
    try:

        def matched() -> list[tuple[Any, JointState]]:
            pairs = []
            for message in list(received):
                ns = message.header.stamp.sec * 1_000_000_000 + message.header.stamp.nanosec
                if ns in states:
                    pairs.append((message, states[ns]))
            return pairs if len({s.part for _, s in pairs}) == len(PARTS) else []

        pairs = until(matched, "a joint state of every part, as the robot sent it")
    finally:
        sub.close()
        for s in mesh_subs:
            s.close()
    for message, state in pairs:
        assert list(message.name) == state.names == list(PARTS[state.part])
        np.testing.assert_array_equal(message.position, state.position)
        np.testing.assert_array_equal(message.velocity, state.velocity)


def test_an_image_equals_the_cameras_frame(mesh: Mesh) -> None:
    received: list[Any] = []
    sub = _subscriber(mesh, f"{NS}/camera/image_raw", "sensor_msgs/msg/Image", received)
    frames: dict[int, np.ndarray] = {}
    camera = Subscription(
        mesh.node.session, mesh.node.keys.cam_frames(), Image, "fifo",
        lambda f: frames.__setitem__(round(f.stamp * 1e9), f.unpacked().to_numpy().copy()),
    )  # fmt: skip
    try:

        def matched() -> tuple[Any, np.ndarray] | None:
            for message in list(received):
                ns = message.header.stamp.sec * 1_000_000_000 + message.header.stamp.nanosec
                if ns in frames:
                    return message, frames[ns]
            return None

        message, pixels = until(matched, "a frame of the camera")
    finally:
        sub.close()
        camera.close()
    assert message.encoding == "rgb8"
    assert (message.height, message.width, message.step) == (
        pixels.shape[0], pixels.shape[1], pixels.shape[1] * 3,
    )  # fmt: skip
    np.testing.assert_array_equal(message.data.reshape(pixels.shape), pixels)


def test_the_description_reaches_a_late_transient_local_subscriber(mesh: Mesh) -> None:
    """As rmw_zenoh's transient local subscription does: zenoh-ext's advanced subscriber asks
    the publisher's cache for what it sent before."""
    ros_type = "std_msgs/msg/String"
    key = (
        f"0/{ROBOT}/robot_description/{typestore.dds_type_name(ros_type)}/"
        f"{typestore.type_hash(ros_type)}"
    )
    got: list[zenoh.Sample] = []
    history = zenoh.ext.HistoryConfig(detect_late_publishers=True, max_samples=1)
    sub = zenoh.ext.declare_advanced_subscriber(mesh.sdk.session, key, got.append, history=history)
    try:
        until(lambda: got, "the robot description")
    finally:
        sub.undeclare()
    Attachment.decode(got[0].attachment.to_bytes() if got[0].attachment else None)
    assert typestore.deserialize(got[0].payload.to_bytes(), ros_type).data == urdf_text()


def test_a_reset_without_the_operator_is_refused(mesh: Mesh) -> None:
    client = ROS2ServiceClient(
        f"{NS}/reset", typestore.TRIGGER,
        request_definition="uint8 structure_needs_at_least_one_member",
        response_definition="bool success\nstring message",
        type_hash=typestore.type_hash(typestore.TRIGGER), router_ip=mesh.host,
        router_port=mesh.port, timeout=20,
    )  # fmt: skip
    try:
        status = mesh.node.call_typed(mesh.node.keys.archery_rpc(), rv.ARCHERY_STATUS)
        reply = client.call(structure_needs_at_least_one_member=0)
    finally:
        client.close()
    assert reply is not None and not reply.success
    assert "without --operator" in reply.message
    after = mesh.node.call_typed(mesh.node.keys.archery_rpc(), rv.ARCHERY_STATUS)
    assert after.sim_time >= status.sim_time  # not reset to 0 (the robot's clock went on)


def test_a_command_moves_the_part_and_reset_is_served(mesh: Mesh, operator: Ros2Node) -> None:
    keys = mesh.node.keys
    before = mesh.node.call_typed(keys.part_rpc("torso"), rv.GET_TARGETS)
    target = [before.position[0] + 0.1, *before.position[1:]]
    ros_type = "std_msgs/msg/Float64MultiArray"
    pub = ROS2Publisher(
        f"{NS}/torso/command", ros_type, msg_definition=_definition(ros_type),
        type_hash=typestore.type_hash(ros_type), domain_id=1, router_ip=mesh.host,
        router_port=mesh.port,
    )  # fmt: skip
    try:
        layout = typestore.new("std_msgs/msg/MultiArrayLayout", dim=[], data_offset=0)

        def moved() -> bool:
            pub.publish(layout=layout, data=np.array(target))
            now = mesh.node.call_typed(keys.part_rpc("torso"), rv.GET_TARGETS)
            return abs(now.position[0] - target[0]) < 1e-9

        until(moved, "the torso's target from a ROS 2 command")
    finally:
        pub.close()
    state = until(
        lambda: (lambda s: s if abs(s.position[0] - target[0]) < 0.01 else None)(
            mesh.node.call_typed(keys.part_rpc("torso"), rv.GET_POSITIONS)
        ),
        "the torso at its target",
    )
    assert abs(state.position[0] - target[0]) < 0.01
    client = ROS2ServiceClient(
        f"{NS}/reset", typestore.TRIGGER,
        request_definition="uint8 structure_needs_at_least_one_member",
        response_definition="bool success\nstring message",
        type_hash=typestore.type_hash(typestore.TRIGGER), domain_id=1, router_ip=mesh.host,
        router_port=mesh.port, timeout=30,
    )  # fmt: skip
    try:
        reply = until(lambda: client.call(structure_needs_at_least_one_member=0), "a reply")
    finally:
        client.close()
    assert reply.success and reply.message.startswith("reset:")
    home = mesh.node.call_typed(keys.part_rpc("torso"), rv.GET_TARGETS)
    assert abs(home.position[0] - before.position[0]) < 1e-6
    assert operator.counts.snapshot().get("services") == 1


def _put(mesh: Mesh, key: str, payload: bytes, attachment: bytes | None) -> None:
    mesh.sdk.session.put(key, payload, attachment=attachment)


def test_bad_input_is_dropped_or_refused_and_nothing_moves(mesh: Mesh, operator: Ros2Node) -> None:
    keys = mesh.node.keys
    ros_type = "std_msgs/msg/Float64MultiArray"
    key = data_key(
        1,
        f"{NS}/left_arm/command",
        typestore.dds_type_name(ros_type),
        typestore.type_hash(ros_type),
    )
    before = mesh.node.call_typed(keys.part_rpc("left_arm"), rv.GET_TARGETS)
    gid = bytes(range(16))
    good = Attachment(1, time.time_ns(), gid).encode()
    layout = typestore.new("std_msgs/msg/MultiArrayLayout", dim=[], data_offset=0)

    def command(values: list[float]) -> bytes:
        message = typestore.new(ros_type, layout=layout, data=np.array(values, dtype=np.float64))
        return typestore.serialize(message, ros_type)

    target = [v + 0.05 for v in before.position]
    _put(mesh, key, command(target), None)  # no attachment
    _put(mesh, key, command(target), good[:20])  # cut short
    _put(mesh, key, b"\x00\x01\x00\x00\xff\xff", good)  # not CDR of the type
    _put(mesh, key, command(target[:3]), good)  # the wrong count
    _put(mesh, key, command([float("nan"), *target[1:]]), good)  # NaN
    until(
        lambda: (
            operator.counts.snapshot().get("dropped attachment") == 2
            and operator.counts.snapshot().get("dropped cdr") == 1
            and operator.counts.snapshot().get("refused") == 2
        ),
        f"the drops and refusals counted ({operator.counts.snapshot()})",
    )
    lease = mesh.node.call_typed(
        keys.part_rpc("left_arm"), rv.CLAIM, rv.ClaimArgs(owner="someone", ttl=60.0)
    )
    try:
        _put(mesh, key, command(target), good)  # while another owns the part
        until(lambda: operator.counts.snapshot().get("refused") == 3, "a refusal by the robot")
    finally:
        mesh.node.call_typed(
            keys.part_rpc("left_arm"), rv.DROP_CLAIM, rv.LeaseArgs(lease=lease.lease)
        )
    after = mesh.node.call_typed(keys.part_rpc("left_arm"), rv.GET_TARGETS)
    assert after.position == before.position
    assert operator.counts.snapshot().get("commands") is None


def test_nothing_of_the_mesh_stays_when_the_node_stops(mesh: Mesh) -> None:
    status = mesh.node.call_typed(mesh.node.keys.archery_rpc(), rv.ARCHERY_STATUS)
    scene = SceneConfig.of(status.scene)
    node = Ros2Node(
        mesh.node, RobotFrames(ROBOT, scene), "", scene.camera_fovy, domain=2, namespace=NS
    )
    until(lambda: list(mesh.sdk.session.liveliness().get("@ros2_lv/2/**")), "the node's tokens")
    node.close()
    until(lambda: not list(mesh.sdk.session.liveliness().get("@ros2_lv/2/**")), "no token left")


def _command_key(domain: int, part: str, ros_type: str = convert.FLOAT_COMMAND) -> str:
    name = f"{NS}/{part}/{'command' if ros_type == convert.FLOAT_COMMAND else 'joint_trajectory'}"
    return data_key(domain, name, typestore.dds_type_name(ros_type), typestore.type_hash(ros_type))


def _floats(values: list[float]) -> bytes:
    layout = typestore.new("std_msgs/msg/MultiArrayLayout", dim=[], data_offset=0)
    message = typestore.new(
        convert.FLOAT_COMMAND, layout=layout, data=np.array(values, dtype=np.float64)
    )
    return typestore.serialize(message, convert.FLOAT_COMMAND)


def _trajectory(names: list[str], positions: np.ndarray) -> bytes:
    empty = np.zeros(0, dtype=np.float64)
    point = typestore.new(
        "trajectory_msgs/msg/JointTrajectoryPoint", positions=positions, velocities=empty,
        accelerations=empty, effort=empty,
        time_from_start=typestore.new("builtin_interfaces/msg/Duration", sec=1, nanosec=0),
    )  # fmt: skip
    message = typestore.new(
        convert.TRAJECTORY_COMMAND,
        header=typestore.new("std_msgs/msg/Header", stamp=convert.stamp(0.0), frame_id=""),
        joint_names=names,
        points=[point],
    )
    return typestore.serialize(message, convert.TRAJECTORY_COMMAND)


def _attachment(seq: int) -> bytes:
    return Attachment(seq, time.time_ns(), bytes(range(16))).encode()


def test_read_only_declares_no_command_path_and_a_put_moves_nothing(mesh: Mesh) -> None:
    """`archery up --ros2` runs the node read-only: no command subscription (no token, no
    subscriber), so rmw_zenoh's own put on a command key reaches nobody and nothing moves."""
    tokens = mesh.sdk.session.liveliness().get(f"@ros2_lv/0/*/*/*/MS/%/%{ROBOT}/archery/**")
    assert not [reply for reply in tokens if reply.ok is not None]
    keys = mesh.node.keys
    before = mesh.node.call_typed(keys.part_rpc("right_arm"), rv.GET_TARGETS)
    key = _command_key(0, "right_arm")
    publisher = mesh.sdk.session.declare_publisher(key)
    try:
        assert not publisher.matching_status.matching  # no subscriber anywhere on the mesh
        publisher.put(_floats([v + 0.2 for v in before.position]), attachment=_attachment(1))
    finally:
        publisher.undeclare()
    after = mesh.node.call_typed(keys.part_rpc("right_arm"), rv.GET_TARGETS)
    assert after.position == before.position


def test_a_flood_ends_with_its_last_command_and_reset_is_not_kept_waiting(
    mesh: Mesh, operator: Ros2Node
) -> None:
    """20,000 commands as fast as raw Zenoh sends them: one waits per part (KEEP_LAST 1), the
    robot's command rate is kept, the arm ends at the last command and a reset right after
    the flood is answered at once."""
    keys = mesh.node.keys
    home = mesh.node.call_typed(keys.part_rpc("right_arm"), rv.GET_TARGETS).position
    key = _command_key(1, "right_arm")
    near = [_floats([v + 0.01 * (i % 5) for v in home]) for i in range(5)]
    last = [v + 0.05 for v in home]
    publisher = mesh.sdk.session.declare_publisher(
        key, congestion_control=zenoh.CongestionControl.BLOCK
    )
    until(lambda: publisher.matching_status.matching, "the node's command subscription")
    started = time.monotonic()
    try:
        for i in range(20_000):
            publisher.put(near[i % 5], attachment=_attachment(i + 1))
        publisher.put(_floats(last), attachment=_attachment(20_001))
    finally:
        publisher.undeclare()

    def at_last() -> bool:
        now = mesh.node.call_typed(keys.part_rpc("right_arm"), rv.GET_TARGETS).position
        return bool(np.allclose(now, last, atol=1e-9))

    until(at_last, "the right arm's target at the flood's last command", timeout=10)
    took = time.monotonic() - started
    counts = operator.counts.snapshot()
    assert counts["commands"] <= COMMAND_RATE * took + COMMAND_BURST, counts
    assert counts["dropped stale"] > 0, counts
    client = ROS2ServiceClient(
        f"{NS}/reset", typestore.TRIGGER,
        request_definition="uint8 structure_needs_at_least_one_member",
        response_definition="bool success\nstring message",
        type_hash=typestore.type_hash(typestore.TRIGGER), domain_id=1, router_ip=mesh.host,
        router_port=mesh.port, timeout=30,
    )  # fmt: skip
    again = mesh.sdk.session.declare_publisher(key)
    try:
        for i in range(20_000):
            again.put(near[i % 5], attachment=_attachment(30_000 + i))
        asked = time.monotonic()
        reply = client.call(structure_needs_at_least_one_member=0)
        answered = time.monotonic() - asked
    finally:
        again.undeclare()
        client.close()
    assert reply is not None and reply.success, reply
    assert answered < 10.0, answered  # a reset's own time, not the flood's


def test_an_oversized_trajectory_is_dropped_before_decoding(
    mesh: Mesh, operator: Ros2Node, caplog: pytest.LogCaptureFixture
) -> None:
    """A 38 MB JointTrajectory is dropped on its size; received names reach the log quoted,
    one short line each."""
    keys = mesh.node.keys
    before = mesh.node.call_typed(keys.part_rpc("left_arm"), rv.GET_TARGETS)
    key = _command_key(1, "left_arm", convert.TRAJECTORY_COMMAND)
    huge = _trajectory(["l_elbow"], np.zeros(38 * 1024 * 1024 // 8))
    assert len(huge) > MAX_COMMAND_BYTES
    forged = _trajectory(["l_elbow\narchery.ros2 ERROR forged line"], np.zeros(1))
    many = _trajectory([f"j{i}" for i in range(4_000)], np.zeros(1))
    assert len(many) < MAX_COMMAND_BYTES
    publisher = mesh.sdk.session.declare_publisher(
        key, congestion_control=zenoh.CongestionControl.BLOCK
    )
    until(lambda: publisher.matching_status.matching, "the node's trajectory subscription")
    refused = operator.counts.snapshot().get("refused", 0)
    with caplog.at_level(logging.WARNING, logger="archery.ros2"):
        try:
            publisher.put(huge, attachment=_attachment(1))
            publisher.put(forged, attachment=_attachment(2))
            publisher.put(many, attachment=_attachment(3))
        finally:
            publisher.undeclare()
        until(
            lambda: (
                operator.counts.snapshot().get("dropped size") == 1
                and operator.counts.snapshot().get("refused", 0) == refused + 2
            ),
            f"the size drop and two refusals ({operator.counts.snapshot()})",
            timeout=20,
        )
    lines = [r.getMessage() for r in caplog.records if r.name == "archery.ros2"]
    assert any(f"{len(huge)} bytes, more than" in line for line in lines), lines
    for line in lines:
        assert "\n" not in line and len(line) < 1000, line[:300]
    after = mesh.node.call_typed(keys.part_rpc("left_arm"), rv.GET_TARGETS)
    assert after.position == before.position


def test_each_done_rollout_is_published_once(mesh: Mesh) -> None:
    """The learner's rollout stream (a proposed record, then a done or an aborted one per
    attempt) reaches `/NS/learner/rollout` as one message per done rollout."""
    ros_type = convert.FLOAT_COMMAND
    received: list[Any] = []
    sub = _subscriber(mesh, f"{NS}/learner/rollout", ros_type, received)
    publisher = mesh.node.publisher(mesh.node.keys.learner_rollouts(), Rollout, lossless=True)
    sent: list[int] = []
    try:

        def one_more() -> bool:
            n = len(sent) + 1
            theta = [0.1, 0.2]
            publisher.put(Rollout(record=ProposedRecord(index=n, theta=theta)))
            aborted = AbortedRecord(
                index=n, theta=theta, code="no_arrow", cause="none seen", retry_theta=theta
            )
            publisher.put(Rollout(record=aborted))
            done = DoneRecord(
                index=n, rollout=n, theta=theta, r_m=[0.01, 0.0], distance_m=0.01, hit=True
            )
            publisher.put(Rollout(record=done))
            sent.append(n)
            return bool(received)

        until(one_more, "a done rollout on ROS 2")
        until(lambda: received[-1].data[0] == sent[-1], "the last done rollout")
    finally:
        sub.close()
        publisher.close()
    numbers = [int(m.data[0]) for m in received]
    assert numbers == sorted(set(numbers)) and set(numbers) <= set(sent), (numbers, sent)
    assert list(received[-1].data) == [sent[-1], 1.0, 0.01, 0.1, 0.2, 0.01, 0.0]


def test_tf_and_tf_static_are_the_urdfs_tree(mesh: Mesh) -> None:
    """A late subscriber's `/tf_static` (transient local) and a `/tf` message together give
    every link of `robot_description` its transform from its URDF parent."""
    import xml.etree.ElementTree as ET

    tf_type = "tf2_msgs/msg/TFMessage"
    key = f"0/tf_static/{typestore.dds_type_name(tf_type)}/{typestore.type_hash(tf_type)}"
    got: list[zenoh.Sample] = []
    history = zenoh.ext.HistoryConfig(detect_late_publishers=True, max_samples=1)
    sub = zenoh.ext.declare_advanced_subscriber(mesh.sdk.session, key, got.append, history=history)
    moving: list[Any] = []
    tf = _subscriber(mesh, "/tf", tf_type, moving)
    try:
        until(lambda: got and moving, "/tf_static and /tf")
    finally:
        sub.undeclare()
        tf.close()
    edges = {}
    for message in (typestore.deserialize(got[0].payload.to_bytes(), tf_type), moving[0]):
        for t in message.transforms:
            edges[t.child_frame_id] = t.header.frame_id
    root = ET.fromstring(urdf_text())
    for joint in root.findall("joint"):
        child, parent = joint.find("child"), joint.find("parent")
        assert child is not None and parent is not None
        assert edges.get(child.get("link")) == parent.get("link"), child.get("link")
    assert edges["root_link"] == "world"


def test_export_writes_a_bag_rosbags_reads_message_for_message(mesh: Mesh, tmp_path: Path) -> None:
    """Last: it stops the mesh, so that the recording is complete."""
    mesh.stop()
    out = tmp_path / "bag"
    done = archery("export", str(mesh.recording), "--ros2", str(out), timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    recording = open_recording(mesh.recording)
    expected: dict[str, int] = {}
    for key, _, _ in recording.messages():
        if key.endswith("/state:o") and "/world/" not in key:
            expected[f"{NS}/joint_states"] = expected.get(f"{NS}/joint_states", 0) + 1
        elif key.endswith("/cam/target:o"):
            expected[f"{NS}/camera/image_raw"] = expected.get(f"{NS}/camera/image_raw", 0) + 1
    store = typestore.messages()
    counts: dict[str, int] = {}
    with Reader(out) as reader:
        for connection, _, data in reader.messages():
            message = store.deserialize_cdr(data, connection.msgtype)
            assert message is not None
            counts[connection.topic] = counts.get(connection.topic, 0) + 1
    for topic, n in expected.items():
        assert counts[topic] == n, topic
    assert counts["/tf_static"] == counts[f"{NS}/robot_description"] == 1
    assert counts["/tf"] > 0
    assert counts[f"{NS}/camera/camera_info"] == counts[f"{NS}/camera/image_raw"]
