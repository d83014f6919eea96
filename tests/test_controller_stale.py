"""A robot whose state streams stop (frozen, stuck) is never trusted: the controller replies
`stale_state` naming the key and the age within ~1 s, before a move and in the middle of one,
instead of using the old states or waiting for its motion timeout; the learner's rig takes that
reply as the robot lost. The robot here is a fake on the mesh that can freeze its streams."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest

from archery.mesh.netflags import NetConfig
from archery.mesh.node import Node
from archery.mesh.subscription import Subscription
from archery.protocol.errors import RpcError
from archery.protocol.messages import JointState
from archery.protocol.parts import PARTS
from archery.protocol.robotspec import CONTROLLER, ROBOT, STATE_MAX_AGE
from archery.services.controller import service as controller_service
from archery.services.controller.config import ControllerConfig
from archery.services.learner.errors import ServiceLost
from archery.services.learner.rig import MeshRig
from tests.conftest import serving
from tests.fake_parts import FakeRobot
from tests.rpc import rpc_call

THETA = [0.17, 0.03, -0.03]
MOTION_TIMEOUT = 20.0  # wall s: the posture's own timeout, far beyond the stale limit


class FrozenRobot(FakeRobot):
    """Publishes every part's joint state at 50 Hz (at rest, or moving once commanded) until
    `freeze` is set; serves getLimits and setRefSpeeds. With `freeze_on_command`, the streams
    stop a few states after the first command: a robot frozen mid-motion."""

    def __init__(self, node: Node, freeze_on_command: bool = False) -> None:
        self.node = node
        self.freeze = threading.Event()
        self.sent_after_command = 0
        self._freeze_on_command = freeze_on_command
        super().__init__(node)

    def _publish(self) -> None:
        while not self.freeze.wait(0.02):
            moving = self.commanded.is_set()
            for part, pub in self._pubs.items():
                n = len(PARTS[part])
                pub.put(
                    JointState(
                        part=part,
                        names=list(PARTS[part]),
                        position=[0.0] * n,
                        velocity=[0.1 if moving else 0.0] * n,
                        motion_done=not moving,
                    )
                )
            if moving:
                self.sent_after_command += 1
                if self._freeze_on_command and self.sent_after_command >= 3:
                    self.freeze.set()

    def close(self) -> None:
        self.freeze.set()
        self._join()


@pytest.fixture
def mesh(net: NetConfig) -> Iterator[Node]:
    with Node(None, net) as node:
        yield node


def _controller(net: NetConfig) -> Any:
    return serving(controller_service.run, ControllerConfig(net=net, motion_timeout=MOTION_TIMEOUT))


def _posture(node: Node) -> tuple[RpcError, float]:
    """The controller's error reply to a posture request, and how long it took (wall s)."""
    start = time.monotonic()
    with pytest.raises(RpcError) as info:
        rpc_call(node, node.keys.cartesian_rpc("archery"), "posture", {"theta": THETA}, timeout=30)
    return info.value, time.monotonic() - start


def _wait_states(node: Node) -> Subscription[JointState]:
    """Until a joint state of every part has reached the mesh's side; the torso's subscription."""
    subs = [node.subscribe(node.keys.state(part), JointState) for part in PARTS]
    for sub in subs:
        sub.wait_newer(10, after_seq=-1)
    return subs[0]


def test_a_robot_frozen_before_the_posture_is_a_stale_state_reply(
    net: NetConfig, mesh: Node
) -> None:
    with Node(ROBOT, net) as robot_node, _controller(net):
        robot = FrozenRobot(robot_node)
        mesh.wait_alive([CONTROLLER], 60)
        torso = _wait_states(mesh)
        robot.freeze.set()
        while torso.age() <= STATE_MAX_AGE:  # until the newest state is stale here too
            time.sleep(0.01)
        error, took = _posture(mesh)
        robot.close()
    assert error.code == "stale_state", error
    assert "torso/state:o" in error.message and " s old (stale after 0.5 s)" in error.message
    # It waited STATE_MAX_AGE for a newer state, not the 3 s robot timeout.
    assert STATE_MAX_AGE <= took < STATE_MAX_AGE + 1.0, took


def test_a_robot_frozen_mid_move_is_a_stale_state_reply_not_a_timeout(
    net: NetConfig, mesh: Node
) -> None:
    with Node(ROBOT, net) as robot_node, _controller(net):
        robot = FrozenRobot(robot_node, freeze_on_command=True)
        mesh.wait_alive([CONTROLLER], 60)
        _wait_states(mesh)
        error, took = _posture(mesh)
        robot.close()
    assert robot.commanded.is_set() and robot.sent_after_command == 3  # frozen mid-move
    assert error.code == "stale_state", error
    assert "/state:o" in error.message
    assert took < 3.0 < MOTION_TIMEOUT, took  # stale after 0.5 s of silence, not the timeout


def test_the_learner_takes_a_stale_robot_as_lost(net: NetConfig, mesh: Node) -> None:
    with Node(ROBOT, net) as robot_node, _controller(net):
        robot = FrozenRobot(robot_node)
        mesh.wait_alive([CONTROLLER, ROBOT], 60)
        _wait_states(mesh)
        robot.freeze.set()  # the robot's token stays: alive, but its streams stopped
        rig = MeshRig(mesh, timeout=10)
        rig.services = (ROBOT, CONTROLLER)  # the only services of this mesh
        with pytest.raises(ServiceLost) as lost:
            rig.move_to(np.array(THETA))
        robot.close()
    assert lost.value.service == ROBOT
    assert "stale" in str(lost.value)
