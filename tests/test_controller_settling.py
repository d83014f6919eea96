"""A move ends when the whole robot rests at its targets after the commands, not on a state
from before them: a simulated robot at rtf 0 steps until every part rests, so a reply sooner
lets the next job (a nock, a release) land while it still settles, at a simulated time that
depends on the wall clock (same-seed runs then part). The robot here is a fake on the mesh that
plays a scripted timeline of states, one state of every part per beat."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from typing import Protocol

import pytest

from archery.mesh.netflags import NetConfig
from archery.mesh.node import Node
from archery.mesh.robot_client import Moved, RobotClient
from archery.protocol.errors import RobotError
from archery.protocol.messages import JointState
from archery.protocol.parts import PARTS
from archery.protocol.robotspec import ROBOT
from archery.services.controller.handlers import move
from tests.fake_parts import FakeRobot

REST = 5.0  # sim s of the robot's rest before the move
TOL = 0.01  # rad: the controller's joint tolerance
STEP = 0.004  # rad: the move's size, within the tolerance (a learner's small step)

# A beat: the sim time, and per part (position offset from rest, motion done).
Beat = tuple[float, dict[str, tuple[float, bool]]]
AT_REST: dict[str, tuple[float, bool]] = {p: (0.0, True) for p in PARTS}


class ScriptedRobot(FakeRobot):
    """Publishes every part's joint state every 10 ms: `before` (by default the rest at `REST`;
    its last beat until a command arrives), then `after_command` (the old rest a few more times
    first, as a robot that has not taken the commands yet), then its last beat for ever."""

    def __init__(
        self, node: Node, after_command: list[Beat], before: list[Beat] | None = None
    ) -> None:
        self.before = before or [(REST, AT_REST)]
        self.beats = [self.before[-1]] * 5 + after_command
        self._stop = threading.Event()
        super().__init__(node)

    def _publish(self) -> None:
        i, j = 0, 0
        while not self._stop.wait(0.01):
            if self.commanded.is_set():
                sim_time, parts = self.beats[min(i, len(self.beats) - 1)]
                i += 1
            else:
                sim_time, parts = self.before[min(j, len(self.before) - 1)]
                j += 1
            for part, pub in self._pubs.items():
                offset, done = parts[part]
                n = len(PARTS[part])
                pub.put(
                    JointState(
                        part=part,
                        names=list(PARTS[part]),
                        position=[offset] * n,
                        velocity=[0.0] * n,
                        motion_done=done,
                        sim_time=sim_time,
                    )
                )

    def close(self) -> None:
        self._stop.set()
        self._join()


class Start(Protocol):
    def __call__(
        self, after_command: list[Beat], before: list[Beat] | None = None
    ) -> tuple[RobotClient, ScriptedRobot]: ...


@pytest.fixture
def link(net: NetConfig) -> Iterator[Start]:
    with Node(ROBOT, net) as robot_node, Node(None, net) as node:
        robots: list[ScriptedRobot] = []

        def start(
            after_command: list[Beat], before: list[Beat] | None = None
        ) -> tuple[RobotClient, ScriptedRobot]:
            robot = ScriptedRobot(robot_node, after_command, before)
            robots.append(robot)
            node.wait_alive([ROBOT], 10)
            client = RobotClient(node, timeout=5.0, reached=TOL)
            for part in PARTS:  # followed and declared from the start, as the controller does
                client.stream(part)
                client.command(part, ())
            return client, robot

        yield start
        for robot in robots:
            robot.close()


def _moved(
    offset: float, done: bool, torso: tuple[float, bool] = (0.0, True)
) -> dict[str, tuple[float, bool]]:
    return {"torso": torso, "left_arm": (offset, done), "right_arm": (offset, done)}


def test_the_old_rest_within_tolerance_of_the_targets_does_not_end_the_move(
    link: Start,
) -> None:
    robot_link, robot = link(
        [(REST + 0.02, _moved(STEP / 2, False)), (REST + 0.04, _moved(STEP, True))]
    )
    targets = {j: STEP for p in ("left_arm", "right_arm") for j in PARTS[p]}
    result = move(robot_link, targets, traj_time=1.0, timeout=10.0)
    assert robot.commanded.is_set() and result.reached, result.reason
    assert result.sim_time == REST + 0.04  # not REST: that state was from before the commands


def test_a_move_ends_only_once_every_part_rests_at_one_simulated_time(
    link: Start,
) -> None:
    # the arms are there at REST + 0.04 while the torso (not moved) still settles from it
    robot_link, _ = link(
        [
            (REST + 0.02, _moved(STEP / 2, False, torso=(0.001, False))),
            (REST + 0.04, _moved(STEP, True, torso=(0.001, False))),
            (REST + 0.06, _moved(STEP, True, torso=(0.0, True))),
        ]
    )
    targets = {j: STEP for p in ("left_arm", "right_arm") for j in PARTS[p]}
    result = move(robot_link, targets, traj_time=1.0, timeout=10.0)
    assert result.reached, result.reason
    assert result.sim_time == REST + 0.06


def test_a_move_starts_from_the_robot_at_rest_not_from_a_state_while_it_settles(
    link: Start,
) -> None:
    # still settling 3 mrad away from where it comes to rest: the speeds come from the rest
    settling = [
        (REST - 0.02 * (9 - k), _moved(0.003, False, torso=(0.003, False))) for k in range(8)
    ]
    robot_link, robot = link(
        [(REST + 0.02, _moved(0.05, True))], before=[*settling, (REST, AT_REST)]
    )
    targets = {j: 0.05 for p in ("left_arm", "right_arm") for j in PARTS[p]}
    result = move(robot_link, targets, traj_time=1.0, timeout=10.0)
    assert result.reached, result.reason
    assert robot.speeds_set["left_arm"][-1] == pytest.approx([0.05] * 7)  # 50 mrad in 1 s


def test_a_part_that_never_rests_fails_the_move_naming_its_key(link: Start) -> None:
    # the torso (not moved) never shows motion done: the move ends unreached at its timeout
    robot_link, _ = link([(REST + 0.02, _moved(STEP, True, torso=(0.001, False)))])
    targets = {j: STEP for p in ("left_arm", "right_arm") for j in PARTS[p]}
    with pytest.raises(RobotError) as unreached:
        move(robot_link, targets, traj_time=1.0, timeout=0.5)
    assert unreached.value.kind == "not_reached"
    result = unreached.value.moved
    assert isinstance(result, Moved) and not result.reached
    assert "torso/state:o (not moved) did not come to rest within 0.5 s" in result.reason
