"""`archery robot --body yarp`: the robot service in front of YARP's own devices (YARP 3.5's
`fakeMotionControl` behind `controlboardwrapper2`, one `yarpdev` per part, on YARP's own
`yarpserver` on loopback; the fixtures of tests/test_yarp_body.py), on a real Zenoh router,
read and moved through the mesh's `RobotClient`."""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from archery.mesh.netflags import NetConfig
from archery.mesh.node import Node
from archery.mesh.robot_client import RobotClient
from archery.protocol.errors import RobotError, RpcError
from archery.protocol.parts import PARTS
from archery.protocol.robotspec import ROBOT, TOLERANCES
from archery.protocol.verbs import robot as rv
from archery.services.robot.yarp_parts import project_limits
from tests.ros2_sdk import until
from tests.test_yarp_body import FAKE, HAND_ANGLE, POSE, Board, Robots, _fake_motion_control
from tests.yarp_setup import YarpSetup

yarp = pytest.importorskip("yarp", reason="YARP's bindings: `make setup` builds and installs them")


@dataclass
class Rig:
    setup: YarpSetup
    robots: Robots
    net: NetConfig
    node: Node
    proc: subprocess.Popen[bytes]
    log: Path


def _robot(net: NetConfig, env: dict[str, str], log: Path, *flags: str) -> subprocess.Popen[bytes]:
    signal.signal(signal.SIGCHLD, signal.SIG_DFL)  # YARP's handler reaps children (see conftest)
    argv = [sys.executable, "-m", "archery.apps.cli", "robot", "--connect", net.connect[0]]
    with log.open("wb") as out:
        return subprocess.Popen(
            [*argv, "--robot", net.robot, "--body", "yarp", *flags],
            env=env,
            stdin=subprocess.DEVNULL,
            stdout=out,
            stderr=subprocess.STDOUT,
        )


@pytest.fixture(scope="module")
def rig(router_endpoint: str, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Rig]:
    if not _fake_motion_control():
        pytest.skip("this YARP has no fakeMotionControl device (tools/yarp_wheel.py builds it)")
    tmp = tmp_path_factory.mktemp("yarp_body_robot")
    setup = YarpSetup(yarp, tmp / "server")
    try:
        robots = Robots(setup, tmp)
        try:
            net = NetConfig(connect=(router_endpoint,), robot=f"yarp{os.getpid()}")
            log = tmp / "robot.log"
            proc = _robot(net, setup.env, log, "--remote", "/fake")
            node = Node(None, net)
            try:
                node.wait_alive([ROBOT], 60)
                yield Rig(setup, robots, net, node, proc, log)
            finally:
                node.close()
                signal.signal(signal.SIGCHLD, signal.SIG_DFL)
                proc.terminate()
                try:
                    status = proc.wait(20)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()
                    raise
                assert status == 0, log.read_text(errors="replace")[-2000:]
        finally:
            robots.close()
    finally:
        setup.close()


def _elbow_degrees(rig: Rig) -> float:
    """The left elbow as fakeMotionControl reads it (deg), through the test's own client."""
    board = Board("/fake/left_arm", "/test/robot/read")
    try:
        return board.read()[FAKE["left_arm"].index("l_elbow")]
    finally:
        board.close()


def test_the_client_reads_the_joints_and_limits(rig: Rig) -> None:
    client = RobotClient(rig.node, timeout=10)
    try:
        limits = project_limits()  # fakeMotionControl's getLimits fails: the project's
        for part, names in PARTS.items():
            lower, upper = client.limits(part)
            assert lower.tolist() == pytest.approx([limits[n][0] for n in names])
            assert upper.tolist() == pytest.approx([limits[n][1] for n in names])
            state = client.joints(part)
            assert state.names == list(names)
            assert state.position == pytest.approx([POSE[n] for n in names], abs=1e-6)
            assert state.motion_done
        stamps = {client.joints(p).sim_time for p in PARTS}
        assert all(s is not None and s > 0 for s in stamps)  # wall s since the start
    finally:
        client.close()


def test_a_claimed_move_reaches_the_elbow_in_yarp_and_another_owner_is_refused(rig: Rig) -> None:
    client, rival = RobotClient(rig.node, timeout=10), RobotClient(rig.node, timeout=10)
    try:
        _, upper = client.limits("left_arm")
        k = PARTS["left_arm"].index("l_elbow")
        now = client.joints("left_arm").position[k]
        target = now + 0.2 if now + 0.2 < upper[k] else now - 0.2
        with client.claim(["left_arm"], "archer", speeds=1.0) as held:
            with pytest.raises(RobotError) as refused:
                rival.move({"l_elbow": target}, owner="rival")
            assert refused.value.kind == "not_owner"
            moved = client.move({"l_elbow": target}, claim=held, until="rest")
        assert moved.reached, moved.reason
        assert moved.measured["l_elbow"] == pytest.approx(target, abs=TOLERANCES["rest"])
        assert _elbow_degrees(rig) == pytest.approx(math.degrees(target), abs=1e-6)
        targets = client.part_call("left_arm", rv.GET_TARGETS)
        assert targets.position[k] == pytest.approx(target)
        # the part is free again: a positionMove a little past the limit is clamped onto it
        args = rv.PositionMoveArgs(position=[float(upper[k]) + 0.01], names=["l_elbow"])
        reply = client.part_call("left_arm", rv.POSITION_MOVE, args)
        assert reply.position[k] == pytest.approx(float(upper[k]))
        until(
            lambda: abs(_elbow_degrees(rig) - math.degrees(upper[k])) < 1e-6,
            "the elbow at its upper limit",
            timeout=10,
        )
        assert client.part_call("left_arm", rv.COUNTERS).clamped == 1
    finally:
        client.close()
        rival.close()


def _finger_degrees(name: str = "r_index_proximal") -> float:
    """A right-hand axis as fakeMotionControl reads it (deg), through the test's own client."""
    board = Board("/fake/right_arm", "/test/robot/finger")
    try:
        return board.read()[FAKE["right_arm"].index(name)]
    finally:
        board.close()


def test_release_opens_the_index_finger_and_a_nock_without_posture_is_the_operators(
    rig: Rig,
) -> None:
    client = RobotClient(rig.node, timeout=10)
    try:
        status = client.status()
        assert status.world["landing"] == "camera"
        assert status.world["release"] == {"joint": "r_index_proximal", "open_deg": 0.0}
        shots = status.shot
        with pytest.raises(RpcError) as asked:
            client.nock()
        assert asked.value.code == "operator_needed"
        assert asked.value.message.endswith(
            "nock: put an arrow on the bow with its nock on the string, in the right hand "
            "(the robot's hand needs the operator's)"
        )
        assert _finger_degrees() == pytest.approx(HAND_ANGLE, abs=1e-6)  # nothing moved
        assert client.nock().shot == shots + 1  # called again once the operator confirmed
        reply = client.release()
        assert (reply.outcome, reply.hit, reply.theta, reply.shot) == (
            "released", False, None, shots + 1
        )  # fmt: skip
        assert _finger_degrees() == pytest.approx(0.0, abs=1e-6)  # fakeMotionControl: at once
        assert _finger_degrees("r_index_distal") == pytest.approx(HAND_ANGLE, abs=1e-6)
        with pytest.raises(RpcError) as reset:
            client.reset()
        assert reset.value.code == "operator_needed"
        assert client.reset().shot == shots + 1
    finally:
        client.close()


def test_hand_postures_nock_and_a_release_to_a_given_angle(rig: Rig, tmp_path: Path) -> None:
    postures = tmp_path / "hands.json"
    postures.write_text(
        '{"nock": {"r_index_proximal": 60, "r_thumb_oppose": 20}, "operator": ["nock"]}'
    )
    net = NetConfig(connect=rig.net.connect, robot=f"hands{os.getpid()}")
    log = tmp_path / "robot.log"
    flags = ("--remote", "/fake", "--hand-postures", str(postures), "--release-open", "12.5")
    proc = _robot(net, rig.setup.env, log, *flags)
    try:
        with Node(None, net) as node:
            node.wait_alive([ROBOT], 60)
            client = RobotClient(node, timeout=10)
            try:
                before = _finger_degrees()
                with pytest.raises(RpcError) as asked:  # the arrow on the string first
                    client.nock()
                assert asked.value.code == "operator_needed"
                assert "the robot then takes its nock posture" in asked.value.message
                assert _finger_degrees() == pytest.approx(before, abs=1e-6)  # not yet
                client.nock()  # confirmed: the fingers close on the string
                assert _finger_degrees() == pytest.approx(60.0, abs=1e-6)
                assert _finger_degrees("r_thumb_oppose") == pytest.approx(20.0, abs=1e-6)
                assert client.status().phase == "nocked"
                assert client.release().outcome == "released"
                assert _finger_degrees() == pytest.approx(12.5, abs=1e-6)
                with pytest.raises(RpcError) as asked:
                    client.grasp()
                assert asked.value.code == "operator_needed"
            finally:
                client.close()
    finally:
        signal.signal(signal.SIGCHLD, signal.SIG_DFL)
        proc.terminate()
        assert proc.wait(20) == 0, log.read_text(errors="replace")[-2000:]


@pytest.mark.parametrize(
    ("flags", "said"),
    [
        (("--release-joint", "r_ring"), "--release-joint 'r_ring': no axis of that name on "),
        (("--hand-postures", "{folder}/nope.json"), "--hand-postures "),
        (("--hand-postures", "{folder}/bad.json"), "'wave' is not one of grasp, nock, reset"),
    ],
)
def test_a_release_joint_or_posture_the_robot_lacks_is_one_line_exit_2(
    rig: Rig, tmp_path: Path, flags: tuple[str, ...], said: str
) -> None:
    (tmp_path / "bad.json").write_text('{"wave": {"r_index_proximal": 10}}')
    log = tmp_path / "robot.log"
    net = NetConfig(connect=rig.net.connect, robot=f"lacks{os.getpid()}")
    given = [flag.format(folder=tmp_path) for flag in flags]
    proc = _robot(net, rig.setup.env, log, "--remote", "/fake", *given)
    assert proc.wait(60) == 2
    last = log.read_text().splitlines()[-1]
    assert last.startswith("archery robot: ") and said in last, last


def test_a_remote_that_does_not_exist_is_one_line_exit_2(rig: Rig, tmp_path: Path) -> None:
    net = NetConfig(connect=rig.net.connect, robot=f"nothere{os.getpid()}")
    log = tmp_path / "robot.log"
    proc = _robot(net, rig.setup.env, log, "--remote", "/nothere")
    assert proc.wait(60) == 2
    lines = log.read_text().splitlines()
    assert lines[-1].startswith("archery robot: no control board at /nothere/torso, ")
    assert "/nothere/torso" in lines[-1] and "\n" not in lines[-1]


def test_a_remote_that_is_not_a_yarp_name_is_refused_before_any_work(
    rig: Rig, tmp_path: Path
) -> None:
    log = tmp_path / "robot.log"
    proc = _robot(rig.net, rig.setup.env, log, "--remote", "icub")
    assert proc.wait(60) == 2
    assert log.read_text().splitlines() == [
        "archery robot: --remote 'icub': give the robot's YARP name, e.g. /icub"
    ]


def _elbow_path(client: RobotClient, step: float) -> tuple[int, float, list[float]]:
    """The left elbow's index, where it is now (rad), and three waypoints `step` rad apart
    towards the side of its range with room."""
    _, upper = client.limits("left_arm")
    k = PARTS["left_arm"].index("l_elbow")
    now = client.joints("left_arm").position[k]
    sign = 1.0 if now + 3 * step < upper[k] - 0.01 else -1.0
    return k, now, [now + sign * step * i for i in (1, 2, 3)]


def test_a_part_trajectory_plays_its_waypoints_in_order_at_their_times(rig: Rig) -> None:
    client = RobotClient(rig.node, timeout=10)
    seen: list[tuple[float, float]] = []  # (wall s since the start, elbow rad), from the mesh
    k, _, waypoints = _elbow_path(client, 0.15)
    sub = client.follow_joints("left_arm", lambda s: seen.append((s.sim_time, s.position[k])))
    try:
        with client.claim(["left_arm"], "archer") as held:
            args = rv.PartTrajectoryArgs(
                times=[0.5, 1.0, 1.5],
                positions=[[w] for w in waypoints],
                names=["l_elbow"],
                lease=held.leases["left_arm"],
            )
            reply = client.part_call("left_arm", rv.FOLLOW_PART_TRAJECTORY, args, timeout=20)
        assert reply.parts == ["left_arm"]
        assert reply.ended - reply.started >= 1.5  # wall s: the last waypoint's time at least
        assert reply.goal_error <= TOLERANCES["rest"]
        assert reply.path_error < args.path_tolerance
        assert _elbow_degrees(rig) == pytest.approx(math.degrees(waypoints[-1]), abs=1e-6)
        during = [(t, q) for t, q in seen if reply.started <= t <= reply.ended]
        reached = [next(t for t, q in during if abs(q - w) < 0.02) for w in waypoints]
        assert reached == sorted(reached)  # in order
        for at, due in zip(reached, (0.5, 1.0, 1.5), strict=True):  # near their times (wall s)
            assert abs(at - reply.started - due) < 0.25, (reached, reply.started)
        assert client.part_call("left_arm", rv.CHECK_MOTION_DONE).done
    finally:
        rig.node.unsubscribe(sub)
        sub.close()
        client.close()


def test_a_trajectory_past_the_speed_bound_or_under_another_lease_is_refused(rig: Rig) -> None:
    client, rival = RobotClient(rig.node, timeout=10), RobotClient(rig.node, timeout=10)
    try:
        _, _, waypoints = _elbow_path(client, 0.3)
        before = _elbow_degrees(rig)
        fast = rv.PartTrajectoryArgs(times=[0.1], positions=[[waypoints[0]]], names=["l_elbow"])
        with pytest.raises(RpcError) as refused:
            client.part_call("left_arm", rv.FOLLOW_PART_TRAJECTORY, fast)
        assert refused.value.code == "bad_trajectory"
        assert "over the maximum joint speed" in refused.value.message
        slow = rv.PartTrajectoryArgs(times=[1.0], positions=[[waypoints[0]]], names=["l_elbow"])
        with client.claim(["left_arm"], "archer"):
            with pytest.raises(RpcError) as taken:
                rival.part_call("left_arm", rv.FOLLOW_PART_TRAJECTORY, slow)
            assert taken.value.code == "not_owner"
        assert _elbow_degrees(rig) == pytest.approx(before, abs=1e-6)  # nothing moved
    finally:
        client.close()
        rival.close()


def test_followtrajectory_plays_without_actions_and_refuses_them_without_archery_rpc(
    rig: Rig,
) -> None:
    client = RobotClient(rig.node, timeout=10)
    try:
        _, _, waypoints = _elbow_path(client, 0.1)
        part = rv.TrajectoryPart(part="left_arm", names=["l_elbow"])
        plain = rv.TrajectoryArgs(parts=[part], times=[0.5], positions=[[waypoints[0]]])
        reply = client.call(rv.FOLLOW_TRAJECTORY, plain, timeout=20)
        assert reply.goal_error <= TOLERANCES["rest"] and reply.actions == {}
        grasp = (rv.TrajectoryAction(t=0.5, verb="grasp"),)
        acting = rv.TrajectoryArgs(
            parts=[part], times=[0.5], positions=[[waypoints[1]]], actions=grasp
        )
        with pytest.raises(RpcError) as refused:
            client.call(rv.FOLLOW_TRAJECTORY, acting)
        assert refused.value.code == "unsupported"
        assert "--archery-rpc" in refused.value.message
        assert _elbow_degrees(rig) == pytest.approx(math.degrees(waypoints[0]), abs=1e-6)
    finally:
        client.close()


def test_a_yarp_with_no_name_server_configured_is_one_line_exit_2(tmp_path: Path) -> None:
    """A user whose YARP names no name server (a fresh account: no yarp.conf)."""
    env = {"PATH": os.environ["PATH"], "HOME": str(tmp_path)}
    argv = [sys.executable, "-m", "archery.apps.cli", "robot", "--body", "yarp", "--remote",
            "/icub", "--connect", "tcp/127.0.0.1:9"]  # fmt: skip
    done = subprocess.run(argv, env=env, capture_output=True, text=True, timeout=60, cwd=tmp_path)
    assert done.returncode == 2, done.stderr
    assert done.stderr.strip().splitlines()[-1] == (
        "archery robot: no YARP name server is configured: name the robot's with `yarp conf "
        "HOST PORT` (or a yarp.conf in YARP_CONFIG_HOME)"
    )
