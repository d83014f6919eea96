"""`archery ros2 --operator`'s `PART/joint_trajectory` against the real robot: a JointTrajectory
becomes one `followTrajectory`, its points kept at their times (the robot runs at rtf 2 with 100
joint states per simulated s, so that its stream shows the way); a bad one (a joint faster than
the robot's speed bound among them, refused by the robot) moves nothing; a trajectory that
comes while one plays waits for its end; read-only declares no command path. The samples
are raw Zenoh puts with rmw_zenoh's attachment, CDR written by rosbags."""

from __future__ import annotations

import logging
import os
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import zenoh

from archery.apps.ros2 import convert, typestore
from archery.apps.ros2.endpoints import Counts
from archery.apps.ros2.graph import Ros2Node
from archery.apps.ros2.latest import LatestPerKey
from archery.apps.ros2.wire import Attachment, data_key
from archery.apps.topics.robot_frames import RobotFrames
from archery.mesh.netflags import NetConfig, open_session
from archery.mesh.node import Node, open_node
from archery.mesh.subscription import Subscription
from archery.protocol.messages import JointState
from archery.protocol.parts import PARTS
from archery.protocol.robotspec import MAX_REFERENCE_SPEED
from archery.protocol.robotspec import ROBOT as ROBOT_SERVICE
from archery.protocol.verbs import robot as rv
from archery.sim.scene_config import SceneConfig
from archery.sim.urdf import urdf_text
from tests.ros2_sdk import until

ROBOT = f"rostraj{os.getpid()}"
NS = f"/{ROBOT}"
DOMAIN = 4  # the operator's; the read-only node's is 5
ARM = "right_arm"
JOINTS = PARTS[ARM]
# the trajectory's joints, named out of the part's order
NAMED = ["r_elbow", "r_shoulder_pitch"]


@dataclass
class Rig:
    """The robot (a child process at rtf 2), a node on its mesh, an operator node on ROS 2
    domain `DOMAIN`, a raw Zenoh session that plays the ROS 2 client."""

    net: NetConfig
    robot: subprocess.Popen[bytes]
    node: Node
    operator: Ros2Node
    raw: zenoh.Session
    scene: SceneConfig


@pytest.fixture(scope="module")
def rig(router_endpoint: str, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Rig]:
    net = NetConfig(connect=(router_endpoint,), robot=ROBOT)
    log = tmp_path_factory.mktemp("ros2_trajectory") / "robot.log"
    with Path(log).open("wb") as out:
        robot = subprocess.Popen(
            [sys.executable, "-m", "archery.apps.cli", "robot", "--connect", router_endpoint,
             "--robot", ROBOT, "--rtf", "2", "--state-rate", "100"],
            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=out,
        )  # fmt: skip
    node = open_node(net, 30)
    raw = open_session(net)
    operator = None
    try:
        node.wait_alive([ROBOT_SERVICE], timeout=120)
        status = node.call_typed(node.keys.archery_rpc(), rv.ARCHERY_STATUS)
        scene = SceneConfig.of(status.scene)
        operator = Ros2Node(
            node, RobotFrames(ROBOT, scene), urdf_text(), scene.camera_fovy, domain=DOMAIN,
            namespace=NS, operator=True, rtf=status.rtf,
        )  # fmt: skip
        yield Rig(net, robot, node, operator, raw, scene)
    finally:
        if operator is not None:
            operator.close()
        raw.close()
        node.close()
        robot.terminate()
        robot.wait(30)


def _trajectory_key(domain: int) -> str:
    ros_type = convert.TRAJECTORY_COMMAND
    name = f"{NS}/{ARM}/joint_trajectory"
    return data_key(domain, name, typestore.dds_type_name(ros_type), typestore.type_hash(ros_type))


def _duration(seconds: float) -> object:
    ns = round(seconds * 1e9)
    return typestore.new(
        "builtin_interfaces/msg/Duration", sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000
    )


def _trajectory(names: list[str], times: list[float], rows: list[list[float]]) -> bytes:
    """A JointTrajectory's CDR: point i holds `rows[i]` (rad) at `times[i]` (s), no velocities."""
    empty = np.zeros(0, dtype=np.float64)
    points = [
        typestore.new(
            "trajectory_msgs/msg/JointTrajectoryPoint",
            positions=np.array(row, dtype=np.float64),
            velocities=empty,
            accelerations=empty,
            effort=empty,
            time_from_start=_duration(t),
        )
        for t, row in zip(times, rows, strict=True)
    ]
    message = typestore.new(
        convert.TRAJECTORY_COMMAND,
        header=typestore.new("std_msgs/msg/Header", stamp=convert.stamp(0.0), frame_id=""),
        joint_names=names,
        points=points,
    )
    return typestore.serialize(message, convert.TRAJECTORY_COMMAND)


class Client:
    """A raw Zenoh publisher on the arm's `joint_trajectory` of `domain`, as rmw_zenoh sends."""

    def __init__(self, rig: Rig, domain: int = DOMAIN) -> None:
        self.publisher = rig.raw.declare_publisher(_trajectory_key(domain))
        self.seq = 0

    def send(self, payload: bytes) -> None:
        self.seq += 1
        attachment = Attachment(self.seq, time.time_ns(), bytes(range(16))).encode()
        self.publisher.put(payload, attachment=attachment)

    def close(self) -> None:
        self.publisher.undeclare()


def _named(position: list[float]) -> np.ndarray:
    """The positions of the `NAMED` joints (rad), in `NAMED`'s order."""
    return np.array([position[JOINTS.index(n)] for n in NAMED])


def _waypoints(rig: Rig) -> tuple[np.ndarray, list[np.ndarray]]:
    """The arm's targets now, and three waypoints of the named joints: out by 0.2 rad, out by
    0.4 rad, back to 0.2 rad (each joint away from its nearer limit)."""
    keys = rig.node.keys
    home = np.array(rig.node.call_typed(keys.part_rpc(ARM), rv.GET_TARGETS).position)
    limits = rig.node.call_typed(keys.part_rpc(ARM), rv.GET_LIMITS)
    low, high = _named(limits.min), _named(limits.max)
    start = _named(list(home))
    sign = np.where(high - start >= start - low, 1.0, -1.0)
    assert np.all(np.maximum(high - start, start - low) > 0.5), (start, low, high)
    return home, [start + sign * d for d in (0.2, 0.4, 0.2)]


def _states(rig: Rig) -> tuple[list[JointState], Subscription[JointState]]:
    got: list[JointState] = []
    sub = Subscription(rig.node.session, rig.node.keys.state(ARM), JointState, "fifo", got.append)
    return got, sub


def test_a_trajectory_is_followed_at_its_points_times(rig: Rig) -> None:
    """Times 0.5, 1.0, 1.5 s: the arm passes the middle point around 1.0 s of simulated time
    after the start, not straight on to the last point, and ends at the last point."""
    home, points = _waypoints(rig)
    followed = rig.operator.counts.snapshot().get("trajectories", 0)
    states, sub = _states(rig)
    client = Client(rig)
    try:
        until(lambda: client.publisher.matching_status.matching, "the trajectory subscription")
        client.send(_trajectory(NAMED, [0.5, 1.0, 1.5], [list(p) for p in points]))
        until(
            lambda: rig.operator.counts.snapshot().get("trajectories", 0) == followed + 1,
            f"the robot's reply at the trajectory's end ({rig.operator.counts.snapshot()})",
        )
        reply = rig.operator.followed[ARM]
        until(lambda: states and (states[-1].sim_time or 0.0) >= reply.ended, "its end's state")
    finally:
        client.close()
        sub.close()
    assert reply.parts == [ARM] and reply.goal_error <= 0.02, reply
    timed = [
        (s.sim_time - reply.started, _named(s.position)) for s in states if s.sim_time is not None
    ]
    middle = [q for t, q in timed if abs(t - 1.0) <= 0.05]
    assert middle, [round(t, 3) for t, _ in timed]
    assert all(np.max(np.abs(q - points[1])) < 0.05 for q in middle), (middle, points[1])
    start = _named(list(home))
    early = [q for t, q in timed if 0.0 <= t <= 0.6]
    assert early and all(np.max(np.abs(q - start)) < 0.33 for q in early), early  # not at 0.4
    last = [s for s in states if s.sim_time is not None and s.sim_time >= reply.ended][-1]
    np.testing.assert_allclose(_named(last.position), points[2], atol=0.03)
    others = [i for i, n in enumerate(JOINTS) if n not in NAMED]
    np.testing.assert_allclose(np.array(last.position)[others], home[others], atol=0.03)


def test_a_bad_trajectory_is_refused_and_nothing_moves(
    rig: Rig, caplog: pytest.LogCaptureFixture
) -> None:
    """Times that do not increase, or a point at 0 s: one log line each quoting the times, no
    call to the robot."""
    keys = rig.node.keys
    _, points = _waypoints(rig)
    before = rig.node.call_typed(keys.part_rpc(ARM), rv.GET_TARGETS).position
    counts = rig.operator.counts.snapshot()
    client = Client(rig)
    with caplog.at_level(logging.ERROR, logger="archery.ros2"):
        try:
            until(lambda: client.publisher.matching_status.matching, "the subscription")
            rows = [list(p) for p in points]
            client.send(_trajectory(NAMED, [0.5, 0.5, 1.0], rows))
            client.send(_trajectory(NAMED, [0.0, 0.5, 1.0], rows))
            until(
                lambda: (
                    rig.operator.counts.snapshot().get("refused", 0) == counts.get("refused", 0) + 2
                ),
                f"two refusals ({rig.operator.counts.snapshot()})",
            )
        finally:
            client.close()
    lines = [r.getMessage() for r in caplog.records if r.name == "archery.ros2"]
    assert any("refused, nothing moves" in line and "[0.5, 0.5, 1.0]" in line for line in lines)
    assert any("> 0 s" in line and "[0.0, 0.5, 1.0]" in line for line in lines), lines
    after = rig.node.call_typed(keys.part_rpc(ARM), rv.GET_TARGETS).position
    assert after == before
    now = rig.operator.counts.snapshot()
    assert now.get("trajectories", 0) == counts.get("trajectories", 0)


def test_a_trajectory_faster_than_the_joints_is_refused_by_the_robot_and_nothing_moves(
    rig: Rig, caplog: pytest.LogCaptureFixture
) -> None:
    """0.4 rad in 10 ms (40 rad/s, the bound is positionMove's 2 rad/s): the robot refuses it
    `bad_trajectory` naming the point, joint and speed; one log line, the arm's targets kept."""
    keys = rig.node.keys
    _, points = _waypoints(rig)
    before = rig.node.call_typed(keys.part_rpc(ARM), rv.GET_TARGETS).position
    counts = rig.operator.counts.snapshot()
    client = Client(rig)
    with caplog.at_level(logging.ERROR, logger="archery.ros2"):
        try:
            until(lambda: client.publisher.matching_status.matching, "the subscription")
            client.send(_trajectory(NAMED, [0.01], [list(points[1])]))
            until(
                lambda: (
                    rig.operator.counts.snapshot().get("refused", 0) == counts.get("refused", 0) + 1
                ),
                f"the refusal ({rig.operator.counts.snapshot()})",
            )
        finally:
            client.close()
    lines = [r.getMessage() for r in caplog.records if r.name == "archery.ros2"]
    said = [line for line in lines if "the robot says" in line]
    assert len(said) == 1, lines
    assert f"positions[0] moves {ARM}.{NAMED[0]} at 40 rad/s" in said[0], said
    assert f"over the maximum joint speed of {MAX_REFERENCE_SPEED:g} rad/s" in said[0], said
    assert rig.node.call_typed(keys.part_rpc(ARM), rv.GET_TARGETS).position == before
    now = rig.operator.counts.snapshot()
    assert now.get("trajectories", 0) == counts.get("trajectories", 0)


def test_a_trajectory_that_comes_while_one_plays_waits_for_its_end(rig: Rig) -> None:
    """The first plays; of the two that come meanwhile the newer replaces the older in the
    part's slot and goes once the first has ended (never refused `busy`)."""
    home, points = _waypoints(rig)
    start = _named(list(home))
    counts = rig.operator.counts.snapshot()
    states, sub = _states(rig)
    client = Client(rig)
    try:
        until(lambda: client.publisher.matching_status.matching, "the subscription")
        client.send(_trajectory(NAMED, [0.5, 1.0], [list(points[0]), list(points[1])]))
        until(
            lambda: states and np.max(np.abs(_named(states[-1].position) - start)) > 0.005,
            "the first one under way",
        )
        client.send(_trajectory(NAMED, [0.2], [list(points[0])]))
        client.send(_trajectory(NAMED, [0.2], [list(points[2])]))
        until(
            lambda: (
                rig.operator.counts.snapshot().get("trajectories", 0)
                == counts.get("trajectories", 0) + 2
            ),
            f"two trajectories followed ({rig.operator.counts.snapshot()})",
        )
    finally:
        client.close()
        sub.close()
    now = rig.operator.counts.snapshot()
    assert now.get("refused", 0) == counts.get("refused", 0), now
    assert now.get("dropped stale", 0) == counts.get("dropped stale", 0) + 1, now
    position = rig.node.call_typed(rig.node.keys.part_rpc(ARM), rv.GET_POSITIONS).position
    np.testing.assert_allclose(_named(position), points[2], atol=0.03)


def test_read_only_declares_no_trajectory_subscription(rig: Rig) -> None:
    """Without the operator: no subscription on the graph or the mesh; a put reaches nobody."""
    node = Ros2Node(
        rig.node, RobotFrames(ROBOT, rig.scene), "", rig.scene.camera_fovy, domain=5,
        namespace=NS,
    )  # fmt: skip
    client = Client(rig, domain=5)
    keys = rig.node.keys
    home, points = _waypoints(rig)
    try:
        until(lambda: list(rig.raw.liveliness().get("@ros2_lv/5/**")), "the node's tokens")
        tokens = rig.raw.liveliness().get("@ros2_lv/5/*/*/*/MS/**")
        assert not [reply for reply in tokens if reply.ok is not None]
        assert not client.publisher.matching_status.matching  # no subscriber on the mesh
        client.send(_trajectory(NAMED, [0.5, 1.0, 1.5], [list(p) for p in points]))
    finally:
        client.close()
        node.close()
    assert rig.node.call_typed(keys.part_rpc(ARM), rv.GET_TARGETS).position == list(home)
    assert node.counts.snapshot().get("refused") is None


def test_a_part_whose_send_runs_keeps_its_newest_item_waiting() -> None:
    """The keep-last queue: while a key's send runs its newer items replace one another and the
    newest goes once the send returns; another key goes meanwhile on another thread."""
    release = threading.Event()
    sent: list[tuple[str, int]] = []

    def send(item: tuple[str, int]) -> None:
        sent.append(item)
        if item == ("a", 1):
            release.wait(30)

    counts = Counts()
    queue = LatestPerKey(send, 0.0, counts, logging.getLogger("test"))
    threads = [threading.Thread(target=queue.run, daemon=True) for _ in range(2)]
    for thread in threads:
        thread.start()
    try:
        queue.offer("a", ("a", 1))
        until(lambda: ("a", 1) in sent, "the first item sent")
        queue.offer("a", ("a", 2))
        queue.offer("a", ("a", 3))
        queue.offer("b", ("b", 1))
        until(lambda: ("b", 1) in sent, "the other key's item sent meanwhile")
        assert queue.waiting() == 1 and ("a", 3) not in sent
        release.set()
        until(lambda: ("a", 3) in sent, "the newest item once the send returned")
    finally:
        release.set()
        queue.close()
        for thread in threads:
            thread.join(5)
    assert [item for item in sent if item[0] == "a"] == [("a", 1), ("a", 3)]
    assert counts.snapshot() == {"dropped stale": 1}
