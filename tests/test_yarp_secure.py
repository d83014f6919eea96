"""`archery yarp --secure`: the bridge on a mutual-TLS router with its access control, beside
a real robot service. YARP has no authentication, so the bridge is the boundary: read-only it
runs as the `viewer` identity and YARP's `remote_controlboard` moves nothing through it; with
`--operator` it runs as `operator`, whose grants move the arm."""

from __future__ import annotations

import math
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from archery.apps.up.launcher import Launcher
from archery.mesh.credentials import init_deployment
from archery.mesh.netflags import NetConfig
from archery.mesh.node import open_node
from archery.mesh.router import free_tcp_endpoint
from archery.protocol.messages import JointState
from tests.ros2_sdk import until
from tests.test_yarp import ARM, ELBOW, Board
from tests.yarp_setup import YarpSetup

yarp = pytest.importorskip("yarp", reason="YARP's bindings: `make setup` builds and installs them")

ROBOT = "icubSim"


class SecureYarp:
    """A secure router and the robot service, YARP's name server, and a read-only and an
    operator bridge with the deployment's identities."""

    def __init__(self, base: Path) -> None:
        self.deployment = init_deployment(base / "deploy", robot=ROBOT)
        self.endpoint = free_tcp_endpoint().replace("tcp/", "tls/")
        self.launcher = Launcher(self.endpoint, ROBOT, base / "logs", secure=str(self.deployment))
        self.launcher.up(180, services=["robot"])
        self.yarp = YarpSetup(yarp, base / "yarp")
        self.bridges = []
        for prefix, extra in (("/ro", []), ("/op", ["--operator"])):
            bridge = subprocess.Popen(
                [sys.executable, "-m", "archery.apps.cli", "yarp", "--secure",
                 str(self.deployment), "--connect", self.endpoint, "--robot", ROBOT,
                 "--prefix", prefix, "--yarp-server", f"127.0.0.1:{self.yarp.port}", *extra],
                stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
            )  # fmt: skip
            self.bridges.append(bridge)
            assert bridge.stdout is not None
            ready = bridge.stdout.readline()
            assert ready.startswith("archery yarp: on YARP"), ready
        net = NetConfig(
            connect=(self.endpoint,), robot=ROBOT, secure=str(self.deployment), identity="viewer"
        )
        self.node = open_node(net, 30)

    def elbow(self) -> float:
        sub = self.node.subscribe(self.node.keys.state(ARM), JointState)
        try:
            return sub.wait_newer(10).position[ELBOW]
        finally:
            self.node.unsubscribe(sub)

    def close(self) -> None:
        self.node.close()
        for bridge in self.bridges:
            bridge.terminate()
            bridge.communicate(timeout=60)
        self.yarp.close()
        self.launcher.stop_all()
        self.launcher.forget_identities()


@pytest.fixture(scope="module")
def mesh(tmp_path_factory: pytest.TempPathFactory) -> Iterator[SecureYarp]:
    running = SecureYarp(tmp_path_factory.mktemp("yarp-secure"))
    try:
        yield running
    finally:
        running.close()


def test_the_viewer_bridge_reads_and_moves_nothing_the_operator_bridge_moves(
    mesh: SecureYarp,
) -> None:
    start = mesh.elbow()
    reader = Board("/ro/left_arm", "/test/sro/left_arm")
    try:
        assert reader.read()[ELBOW] == pytest.approx(math.degrees(start), abs=0.5)
        assert not reader.position.positionMove(ELBOW, math.degrees(start) + 10)
    finally:
        reader.close()
    operator = Board("/op/left_arm", "/test/sop/left_arm")
    try:
        goal = math.degrees(start) + (12 if start < 1.0 else -12)
        assert operator.position.positionMove(ELBOW, goal)
        until(
            lambda: abs(mesh.elbow() - math.radians(goal)) < math.radians(0.5),
            "the operator's move on the mesh",
            timeout=20,
        )
    finally:
        operator.close()
