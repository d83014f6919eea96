"""`archery ros2 --secure`: the `ros2` identities of `archery keys init` on a mutual-TLS router
with its access control, beside a real robot service: the node publishes its topics; a command
put by the read-only identity reaches nobody, the operator identity's moves the arm."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import zenoh

from archery.apps.ros2 import convert, typestore
from archery.apps.ros2.graph import COMMANDS, SERVICES, TOPICS
from archery.apps.ros2.wire import Attachment, data_key
from archery.apps.up.launcher import Launcher
from archery.mesh.acl import (
    OPERATOR,
    ROS2,
    ROS2_COMMANDS,
    ROS2_OPERATOR,
    ROS2_SERVICES,
    ROS2_TOPICS,
    roles,
)
from archery.mesh.credentials import IDENTITIES, init_deployment
from archery.mesh.netflags import NetConfig, open_session
from archery.mesh.node import open_node
from archery.mesh.router import free_tcp_endpoint
from archery.protocol.verbs import robot as rv
from tests.ros2_sdk import until
from tests.test_secure_session import _wait_for_line

ROBOT = "icubSim"


class SecureMesh:
    """A secure router and the robot service (`archery up`'s launcher), and `archery ros2
    --secure --operator` on it."""

    def __init__(self, base: Path) -> None:
        self.deployment = init_deployment(base / "deploy", robot=ROBOT)
        self.endpoint = free_tcp_endpoint().replace("tcp/", "tls/")
        self.launcher = Launcher(self.endpoint, ROBOT, base / "logs", secure=str(self.deployment))
        self.launcher.up(180, services=["robot"])
        self.ros2 = subprocess.Popen(
            [sys.executable, "-m", "archery.apps.cli", "ros2", "--secure", str(self.deployment),
             "--connect", self.endpoint, "--robot", ROBOT, "--operator"],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        )  # fmt: skip
        assert self.ros2.stdout is not None
        self.ready = self.ros2.stdout.readline()

    def net(self, identity: str) -> NetConfig:
        return NetConfig(
            connect=(self.endpoint,), robot=ROBOT, secure=str(self.deployment), identity=identity
        )

    def close(self) -> None:
        if self.ros2.poll() is None:
            self.ros2.terminate()
            self.ros2.communicate(timeout=60)
        self.launcher.stop_all()
        self.launcher.forget_identities()


@pytest.fixture(scope="module")
def mesh(tmp_path_factory: pytest.TempPathFactory) -> Iterator[SecureMesh]:
    running = SecureMesh(tmp_path_factory.mktemp("ros2-secure"))
    try:
        yield running
    finally:
        running.close()


def test_the_acls_ros2_names_are_the_nodes() -> None:
    assert {ROS2, ROS2_OPERATOR} <= set(IDENTITIES)
    assert set(ROS2_TOPICS) == {t.name for t in TOPICS if not t.name.startswith("/")}
    assert set(ROS2_SERVICES) == set(SERVICES)
    assert set(ROS2_COMMANDS) == set(COMMANDS)
    command = zenoh.KeyExpr(f"0/{ROBOT}/torso/command/T/H")
    viewer, operator = roles(ROBOT)[ROS2], roles(ROBOT)[ROS2_OPERATOR]
    assert not [k for k in (*viewer.publish, *viewer.subscribe) if command.intersects(k)]
    assert [k for k in operator.subscribe if command.intersects(k)]
    assert not [c for c in viewer.call if not c.endswith("/status")]


def test_the_secure_node_runs_and_publishes(mesh: SecureMesh) -> None:
    assert mesh.ready.startswith("archery ros2: on the ROS 2 graph"), mesh.ros2.stderr
    session = open_session(mesh.net(ROS2))
    got: list[zenoh.Sample] = []
    sub = session.declare_subscriber(f"0/{ROBOT}/joint_states/**", got.append)
    try:
        until(lambda: got, "a joint state on ROS 2 through the secure router")
        tokens = [r for r in session.liveliness().get("@ros2_lv/0/**") if r.ok is not None]
        assert any(f"/NN/%/%{ROBOT}/archery" in str(r.ok.key_expr) for r in tokens)
    finally:
        sub.undeclare()
        session.close()
    Attachment.decode(got[0].attachment.to_bytes() if got[0].attachment else None)


def _command(values: list[float]) -> bytes:
    layout = typestore.new("std_msgs/msg/MultiArrayLayout", dim=[], data_offset=0)
    message = typestore.new(
        convert.FLOAT_COMMAND, layout=layout, data=np.array(values, dtype=np.float64)
    )
    return typestore.serialize(message, convert.FLOAT_COMMAND)


def test_only_the_operator_identity_commands_through_ros2(mesh: SecureMesh) -> None:
    ros_type = convert.FLOAT_COMMAND
    key = data_key(
        0,
        f"/{ROBOT}/torso/command",
        typestore.dds_type_name(ros_type),
        typestore.type_hash(ros_type),
    )
    with open_node(mesh.net(OPERATOR), 60.0) as node:
        rpc = node.keys.part_rpc("torso")
        before = node.call_typed(rpc, rv.GET_TARGETS).position
        viewer = open_session(mesh.net(ROS2))
        try:
            publisher = viewer.declare_publisher(key)
            # the router forwards it no subscription: the put reaches nobody
            assert not publisher.matching_status.matching
            attachment = Attachment(1, time.time_ns(), bytes(16)).encode()
            publisher.put(_command([v + 0.1 for v in before]), attachment=attachment)
            publisher.undeclare()
        finally:
            viewer.close()
        assert node.call_typed(rpc, rv.GET_TARGETS).position == before
        operator = open_session(mesh.net(ROS2_OPERATOR))
        target = [before[0] + 0.05, *before[1:]]
        try:
            publisher = operator.declare_publisher(key)
            until(lambda: publisher.matching_status.matching, "the node's command subscription")

            def moved() -> bool:
                attachment = Attachment(2, time.time_ns(), bytes(16)).encode()
                publisher.put(_command(target), attachment=attachment)
                now = node.call_typed(rpc, rv.GET_TARGETS).position
                return bool(np.allclose(now, target, atol=1e-9))

            until(moved, "the torso's target from the operator identity's ROS 2 command")
            publisher.undeclare()
        finally:
            operator.close()


def test_up_secure_runs_the_read_only_ros2_node(tmp_path: Path) -> None:
    deployment = init_deployment(tmp_path / "deploy", robot=ROBOT)
    endpoint = free_tcp_endpoint().replace("tcp/", "tls/")
    up = subprocess.Popen(
        [sys.executable, "-m", "archery.apps.cli", "up", "--secure", str(deployment), "--listen",
         endpoint, "--robot", ROBOT, "--logs", str(tmp_path / "logs"), "--runs",
         str(tmp_path / "runs"), "--ros2", "0"],
        stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        _wait_for_line(up, "archery up: on the ROS 2 graph", timeout=180)
        net = NetConfig(connect=(endpoint,), robot=ROBOT, secure=str(deployment), identity=ROS2)
        with open_session(net) as session:
            tokens = [str(r.ok.key_expr) for r in session.liveliness().get("@ros2_lv/0/**")]
        assert any("/NN/" in token for token in tokens), tokens  # the node is on the graph
        assert not any("/MS/" in t and "command" in t for t in tokens), tokens  # read-only
    finally:
        up.send_signal(signal.SIGINT)
        up.communicate(timeout=60)
    assert up.returncode == 0
