"""A part of a YARP robot that vanishes mid-session and comes back, with YARP's own devices
(YARP 3.5's `fakeMotionControl` behind `controlboardwrapper2`, one `yarpdev` per part): the
left arm's `yarpdev` killed, `archery robot --body yarp` says so once, withdraws its liveliness
(a session waits for the robot as for any lost service), keeps the torso's states going and
refuses the arm's verbs; the `yarpdev` started again (its encoders first out of the limits,
refused, then posed), the body opens the board again, says it is back, is alive again and moves
the arm."""

from __future__ import annotations

import os
import signal
import subprocess
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from archery.mesh.netflags import NetConfig
from archery.mesh.node import Node
from archery.mesh.robot_client import RobotClient
from archery.protocol.errors import RpcError
from archery.protocol.parts import PARTS
from archery.protocol.robotspec import ROBOT, TOLERANCES
from archery.protocol.verbs import robot as rv
from tests.ros2_sdk import until
from tests.test_yarp_body import POSE, Board, _arm, _fake_motion_control
from tests.test_yarp_body_robot import _robot
from tests.yarp_setup import YarpSetup

yarp = pytest.importorskip("yarp", reason="YARP's bindings: `make setup` builds and installs them")

AXES = {"torso": list(PARTS["torso"]), "left_arm": _arm("l"), "right_arm": _arm("r")}


@dataclass
class Body:
    setup: YarpSetup
    tmp: Path
    devices: dict[str, subprocess.Popen[bytes]]

    def start(self, part: str) -> None:
        """The part's `yarpdev`, once its ports answer (a killed one's name may linger)."""
        conf = self.tmp / f"{part}.ini"
        conf.write_text(
            "device controlboardwrapper2\nsubdevice fakeMotionControl\n"
            f"name /v/{part}\nperiod 10\n[GENERAL]\nJoints {len(AXES[part])}\n"
            f"AxisName {' '.join(AXES[part])}\n"
        )
        with (self.tmp / f"{part}.log").open("ab") as log:
            self.devices[part] = subprocess.Popen(
                [self.setup.tool("yarpdev"), "--from", str(conf)],
                env=self.setup.env,
                stdin=subprocess.DEVNULL,
                stdout=log,
                stderr=subprocess.STDOUT,
                start_new_session=True,
            )
        until(
            lambda: (
                self.devices[part].poll() is None
                and yarp.Network.exists(f"/v/{part}/stateExt:o", True)
            ),
            f"/v/{part} up",
            timeout=30,
        )

    def pose(self, part: str) -> None:
        board = Board(f"/v/{part}", f"/test/vanish/pose/{part}/{os.getpid()}")
        try:
            board.pose(AXES[part])
        finally:
            board.close()

    def kill(self, part: str) -> None:
        os.killpg(self.devices[part].pid, signal.SIGKILL)
        self.devices[part].wait()


@pytest.fixture
def body(tmp_path: Path) -> Iterator[Body]:
    if not _fake_motion_control():
        pytest.skip("this YARP has no fakeMotionControl device (tools/yarp_wheel.py builds it)")
    setup = YarpSetup(yarp, tmp_path / "server")
    running = Body(setup, tmp_path, {})
    try:
        for part in AXES:
            running.start(part)
            running.pose(part)
        yield running
    finally:
        signal.signal(signal.SIGCHLD, signal.SIG_DFL)
        for device in running.devices.values():
            if device.poll() is None:
                os.killpg(device.pid, signal.SIGTERM)
                device.wait(30)
        setup.close()


def test_a_vanished_arm_is_waited_for_and_moves_again_once_back(
    body: Body, router_endpoint: str, tmp_path: Path
) -> None:
    net = NetConfig(connect=(router_endpoint,), robot=f"vanish{os.getpid()}")
    log = tmp_path / "robot.log"
    proc = _robot(net, body.setup.env, log, "--remote", "/v")
    try:
        with Node(None, net) as node:
            node.wait_alive([ROBOT], 60)
            client = RobotClient(node, timeout=10)
            try:
                assert client.joints("left_arm").position == pytest.approx(
                    [POSE[n] for n in PARTS["left_arm"]], abs=1e-6
                )
                body.kill("left_arm")
                until(lambda: ROBOT not in node.alive(), "the robot withdrawn", timeout=30)
                torso = client.joints("torso")  # the other parts' states go on
                assert torso.position == pytest.approx([POSE[n] for n in PARTS["torso"]], abs=1e-6)
                with pytest.raises(RpcError) as refused:
                    client.part_call(
                        "left_arm",
                        rv.POSITION_MOVE,
                        rv.PositionMoveArgs(position=[POSE[n] for n in PARTS["left_arm"]]),
                    )
                assert refused.value.code == "part_lost", refused.value.message
                assert refused.value.message.split(": ", 1)[1].startswith("left_arm ")
                body.start("left_arm")  # its encoders at 0°: the elbow out of its limits
                until(lambda: "outside its limits" in log.read_text(), "the refusal", timeout=30)
                assert ROBOT not in node.alive()
                body.pose("left_arm")
                until(lambda: ROBOT in node.alive(), "the robot alive again", timeout=30)
                k = PARTS["left_arm"].index("l_elbow")
                target = POSE["l_elbow"] + 0.1
                with client.claim(["left_arm"], "archer") as held:
                    moved = client.move({"l_elbow": target}, claim=held, until="rest")
                assert moved.reached, moved.reason
                assert client.joints("left_arm").position[k] == pytest.approx(
                    target, abs=TOLERANCES["rest"]
                )
            finally:
                client.close()
    finally:
        signal.signal(signal.SIGCHLD, signal.SIG_DFL)
        proc.terminate()
        assert proc.wait(20) == 0, log.read_text(errors="replace")[-2000:]
    text = log.read_text()
    assert text.count("left_arm is lost") == 1 and text.count("left_arm is back") == 1, text
    assert text.count("joint states of left_arm not published") == 1, text
