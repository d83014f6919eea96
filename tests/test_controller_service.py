"""`archery controller` over a real router with the real robot service: archery postures,
askForPose / goToPose / getPose, settings, bad input, an absent robot, SIGTERM."""

from __future__ import annotations

import math
import subprocess
import sys
import threading
from collections.abc import Callable, Iterator
from typing import Any

import msgspec
import numpy as np
import pytest

from archery.mesh.netflags import NetConfig
from archery.mesh.node import Node
from archery.protocol.errors import RpcError
from archery.protocol.parts import PARTS
from archery.services.controller import service as controller_service
from archery.services.controller.config import ControllerConfig
from archery.services.robot import service as robot_service
from archery.services.robot.config import RobotConfig
from archery.sim.scene_config import SceneConfig
from archery.sim.world import WorldConfig
from tests.conftest import archery
from tests.rpc import rpc_call

WORLD = WorldConfig(scene=SceneConfig(meshes=False))
THETAS = ([0.17, 0.03, -0.03], [0.22, 0.0, -0.06], [0.13, 0.05, 0.0])


class Mesh:
    """A test client: calls the controller's and the robot's RPC."""

    def __init__(self, node: Node) -> None:
        self.node = node
        self.keys = node.keys

    def arm(self, arm: str, verb: str, args: dict[str, Any] | None = None) -> Any:
        return rpc_call(self.node, self.keys.cartesian_rpc(arm), verb, args, timeout=30)

    def archery(self, verb: str, args: dict[str, Any] | None = None) -> Any:
        return rpc_call(self.node, self.keys.cartesian_rpc("archery"), verb, args, timeout=30)

    def robot(self, part: str, verb: str, args: dict[str, Any] | None = None) -> Any:
        return rpc_call(self.node, self.keys.part_rpc(part), verb, args, timeout=10)

    def sim_time(self) -> float:
        return float(rpc_call(self.node, self.keys.archery_rpc(), "status", timeout=10)["sim_time"])

    def raw(self, key: str, verb: str, args: dict[str, Any]) -> Any:
        """Send a request that the client-side codec would refuse (e.g. NaN arguments)."""
        payload = msgspec.msgpack.encode(
            {"type": "RpcRequest", "schema": 1, "verb": verb, "args": args}
        )
        return self.node.request(key, payload, verb=verb, timeout=10)


@pytest.fixture
def services(net: NetConfig) -> Iterator[Callable[..., Mesh]]:
    """start(robot=True, **controller config) runs the services in threads; returns a client."""
    running: list[tuple[threading.Event, list[threading.Thread], Node]] = []

    def start(robot: bool = True, **overrides: Any) -> Mesh:
        stop = threading.Event()
        threads = [
            threading.Thread(
                target=controller_service.run,
                args=(ControllerConfig(net=net, **overrides), stop),
                daemon=True,
            )
        ]
        if robot:
            config = RobotConfig(net=net, world=WORLD)
            threads.append(
                threading.Thread(target=robot_service.run, args=(config, stop), daemon=True)
            )
        for thread in threads:
            thread.start()
        node = Node(None, net)
        running.append((stop, threads, node))
        node.wait_alive(["controller", "robot"] if robot else ["controller"], 60)
        return Mesh(node)

    yield start
    for stop, threads, node in running:
        node.close()
        stop.set()
        for thread in threads:
            thread.join(10)
            assert not thread.is_alive()


def test_postures_are_reached_and_measured_within_a_millimetre(
    services: Callable[..., Mesh],
) -> None:
    mesh = services()
    limits = {p: mesh.robot(p, "getLimits") for p in PARTS}
    for theta in THETAS:
        reply = mesh.archery("posture", {"theta": theta})
        assert reply["reached"] and reply["reachable"] and reply["reason"] == ""
        np.testing.assert_allclose(reply["theta_achieved"], theta, atol=1e-4)
        np.testing.assert_allclose(reply["theta_measured"], theta, atol=1e-3)
        assert reply["measured_error_m"] < 1e-3
        for part, lim in limits.items():
            q = np.array([reply["q"][j] for j in PARTS[part]])
            assert np.all(q >= np.array(lim["min"])) and np.all(q <= np.array(lim["max"]))
            np.testing.assert_allclose(mesh.robot(part, "getTargets")["position"], q)
    for part in PARTS:  # never a target the robot had to clamp or refuse
        counters = mesh.robot(part, "counters")
        assert counters["accepted"] == len(THETAS)
        assert counters["clamped"] == counters["rejected"] == counters["watchdog_trips"] == 0


def test_the_same_theta_gives_the_same_targets_whatever_came_before(
    services: Callable[..., Mesh],
) -> None:
    mesh = services()
    first = mesh.archery("posture", {"theta": THETAS[0]})
    mesh.archery("posture", {"theta": THETAS[1]})
    again = mesh.archery("posture", {"theta": THETAS[0]})
    assert again["q"] == first["q"]


def test_trajectory_time_sets_how_long_a_move_takes(services: Callable[..., Mesh]) -> None:
    mesh = services()
    mesh.archery("posture", {"theta": THETAS[0]})
    for traj_time in (0.5, 2.0):
        assert mesh.archery("setTrajTime", {"time": traj_time}) == {"time": traj_time}
        start = mesh.sim_time()
        theta = THETAS[1] if traj_time == 0.5 else THETAS[0]
        reply = mesh.archery("posture", {"theta": theta})
        took = reply["sim_time"] - start
        assert traj_time <= took < traj_time + 0.6, (traj_time, took)
    assert mesh.archery("getTrajTime") == {"time": 2.0}
    with pytest.raises(RpcError, match=r"`\$.time`.*time must be float in \[0.05, 60\] \(s"):
        mesh.archery("setTrajTime", {"time": 0.0})


BAD_POSTURES = [
    ({"theta": [0.5, 0.0, 0.0]}, r"outside the configured box \[0.12, -0.02, -0.07\]"),
    ({"theta": [0.17, 0.03]}, r"length >= 3; theta must be list\[finite float\] length 3"),
    ({"theta": "far"}, r"Expected `array`, got `str`.*theta must be list\[finite float\] length 3"),
    ({"theta": [0.17, 0.03, -0.03], "speed": 1}, "unknown field `speed`.*: theta, timeout"),
    ({}, "missing required field `theta`"),
    ({"theta": [0.17, 0.03, -0.03], "timeout": -1}, r"timeout must be float in \[0.1, 3600\]"),
]


def test_a_whole_shot_asked_of_a_posture_robot_is_refused_naming_its_shot(
    services: Callable[..., Mesh],
) -> None:
    mesh = services()
    with pytest.raises(RpcError, match="the robot runs the 'posture' shot") as info:
        mesh.archery("posture", {"theta": [0.17, 0.03, -0.03], "shot": "whole"})
    assert info.value.code == "bad_state"
    assert mesh.robot("torso", "counters")["accepted"] == 0


def test_bad_posture_requests_are_refused(services: Callable[..., Mesh]) -> None:
    mesh = services()
    for args, match in BAD_POSTURES:
        with pytest.raises(RpcError, match=match) as info:
            mesh.archery("posture", args)
        assert info.value.code == "bad_request"
    assert mesh.robot("torso", "counters")["accepted"] == 0


def test_nan_arguments_never_reach_a_handler(services: Callable[..., Mesh]) -> None:
    mesh = services()
    for arm, verb, args in (
        ("archery", "posture", {"theta": [math.nan, 0.0, 0.0]}),
        ("left_arm", "askForPose", {"xd": [-0.3, math.inf, 0.1]}),
    ):
        reply = mesh.raw(mesh.keys.cartesian_rpc(arm), verb, args)
        assert not reply.ok and reply.code == "bad_request" and "finite" in reply.message
        assert f"`$.{next(iter(args))}[" in reply.message  # names the field
    assert mesh.robot("torso", "counters")["accepted"] == 0


def test_ask_then_go_to_a_pose_and_read_it_back(services: Callable[..., Mesh]) -> None:
    mesh = services()
    mesh.arm("left_arm", "getPose")  # the controller has seen the robot's states
    xd = [-0.28, -0.16, 0.06]
    asked = mesh.arm("left_arm", "askForPose", {"xd": xd})
    assert asked["reachable"] and asked["warm_start"] == "robot"
    assert asked["position_error_m"] < 1e-3
    np.testing.assert_allclose(asked["x"], xd, atol=1e-3)
    assert set(asked["q"]) == set(PARTS["torso"] + PARTS["left_arm"])
    assert mesh.robot("left_arm", "counters")["accepted"] == 0  # asking does not move
    went = mesh.arm("left_arm", "goToPose", {"xd": xd})
    assert went["reached"] and went["reachable"]
    assert went["position_error_measured_m"] < 2e-3
    pose = mesh.arm("left_arm", "getPose")
    # The arm settles on within the robot's position tolerance after reporting done.
    np.testing.assert_allclose(pose["x"], went["x_measured"], atol=2e-4)
    np.testing.assert_allclose(pose["x"], xd, atol=2e-3)
    axis, angle = np.array(pose["o"][:3]), pose["o"][3]
    assert abs(np.linalg.norm(axis) - 1) < 1e-9 and 0 <= angle <= math.pi


def test_an_orientation_is_followed_as_far_as_the_arm_allows(
    services: Callable[..., Mesh],
) -> None:
    mesh = services()
    xd = [-0.25, 0.15, 0.05]
    free = mesh.arm("right_arm", "askForPose", {"xd": xd})
    od = free["o"]  # an orientation the arm reaches at xd: ask for it explicitly
    reply = mesh.arm("right_arm", "goToPose", {"xd": xd, "od": od})
    assert reply["reached"] and reply["orientation_error_rad"] < 0.05
    got = mesh.arm("right_arm", "getPose")["o"]
    rotvec = lambda o: np.array(o[:3]) * o[3]  # noqa: E731
    assert np.linalg.norm(rotvec(got) - rotvec(od)) < 0.05


def test_an_unreachable_target_returns_the_closest_pose(services: Callable[..., Mesh]) -> None:
    mesh = services()
    xd = [-1.5, -0.1, 0.1]  # 1.5 m in front of the robot
    reply = mesh.arm("left_arm", "askForPose", {"xd": xd})
    assert not reply["reachable"]
    gap = float(np.linalg.norm(np.array(reply["x"]) - xd))
    assert reply["position_error_m"] == pytest.approx(gap) and gap > 0.8
    assert reply["x"][0] < -0.3  # stretched toward the target


BAD_POSES = [
    ({"xd": [0.1, 0.2]}, r"xd must be list\[float\] length 3"),
    ({"xd": ["a", "b", "c"]}, r"`\$.xd\[0\]`.*xd must be list\[float\] length 3"),
    ({"xd": 0.3}, r"Expected `array`.*xd must be list\[float\] length 3"),
    ({"xd": [-0.3, -0.1, 0.1], "od": [0, 0, 1]}, r"od must be list\[float\] length 4"),
    ({"xd": [-0.3, -0.1, 0.1], "od": [0, 0, 0, 1.0]}, "zero axis"),
    ({"xd": [-0.3, -0.1, 0.1], "q0": []}, "unknown field `q0`"),
    ({"od": [0, 0, 1, 0.0]}, "missing required field `xd`"),
]


def test_bad_pose_requests_are_refused(services: Callable[..., Mesh]) -> None:
    mesh = services()
    for args, match in BAD_POSES:
        for verb in ("askForPose", "goToPose"):
            with pytest.raises(RpcError, match=match) as info:
                mesh.arm("left_arm", verb, args)
            assert info.value.code == "bad_request"
    assert mesh.robot("left_arm", "counters")["accepted"] == 0


def test_settings_tolerance_trajectory_time_and_torso(services: Callable[..., Mesh]) -> None:
    mesh = services()
    assert mesh.arm("left_arm", "setTolerance", {"tolerance": 0.002}) == {"tolerance": 0.002}
    assert mesh.arm("left_arm", "getTolerance") == {"tolerance": 0.002}
    assert mesh.arm("right_arm", "getTolerance")["tolerance"] == 1e-4  # per arm
    with pytest.raises(RpcError, match=r"tolerance must be float in \[1e-06, 0.1\] \(m\)"):
        mesh.arm("left_arm", "setTolerance", {"tolerance": 1.0})
    assert mesh.arm("left_arm", "setTrajTime", {"time": 0.5}) == {"time": 0.5}
    assert mesh.arm("left_arm", "getTrajTime") == {"time": 0.5}
    dof = mesh.arm("left_arm", "setDOF", {"torso": False})
    assert dof == {"torso": False, "joints": list(PARTS["left_arm"])}
    with pytest.raises(RpcError, match=r"got `str`.*torso must be bool"):
        mesh.arm("left_arm", "setDOF", {"torso": "no"})
    torso = mesh.robot("torso", "getTargets")["position"]
    reply = mesh.arm("left_arm", "goToPose", {"xd": [-0.3, -0.12, 0.02]})
    assert reply["reached"] and reply["position_error_measured_m"] < 2e-3
    assert mesh.robot("torso", "getTargets")["position"] == torso  # held, never commanded
    assert mesh.robot("torso", "counters")["accepted"] == 0
    assert mesh.robot("left_arm", "counters")["accepted"] == 1


def test_an_absent_robot_is_a_clear_error_naming_its_key(services: Callable[..., Mesh]) -> None:
    mesh = services(robot=False, robot_timeout=0.3)
    state_key = mesh.keys.state("torso")
    # a posture first asks the robot which shot it runs
    archery_key = mesh.keys.archery_rpc()
    for call, named in (
        (lambda: mesh.archery("posture", {"theta": THETAS[0]}), f"no service serves {archery_key}"),
        (lambda: mesh.arm("left_arm", "goToPose", {"xd": [-0.3, -0.1, 0.1]}), state_key),
        (lambda: mesh.arm("left_arm", "getPose"), state_key),
    ):
        with pytest.raises(RpcError, match=f"{named}|no joint state on {state_key}") as info:
            call()
        assert info.value.code == "timeout"
    asked = mesh.arm("left_arm", "askForPose", {"xd": [-0.3, -0.1, 0.1]})
    assert asked["reachable"] and asked["warm_start"] == "home"


def test_sigterm_ends_the_controller_process_cleanly(net: NetConfig) -> None:
    argv = [sys.executable, "-m", "archery.apps.cli", "controller", "--connect", net.connect[0]]
    proc = subprocess.Popen([*argv, "--robot", net.robot], stdin=subprocess.DEVNULL)
    try:
        with Node(None, net) as node:
            node.wait_alive(["controller"], 60)
            status = rpc_call(node, node.keys.cartesian_rpc("archery"), "status", timeout=10)
            assert status["theta_box"] == {"low": [0.12, -0.02, -0.07], "high": [0.24, 0.06, 0.01]}
            proc.terminate()
            assert proc.wait(20) == 0
            node.wait_gone("controller", 10)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


@pytest.mark.parametrize(
    ("flags", "message"),
    [
        (["--traj-time", "0"], "--traj-time must be in"),
        (["--tolerance", "-1"], "position_tolerance must be"),
        (["--limit-margin", "0.5"], "limit_margin must be"),
    ],
)
def test_bad_flags_exit_2_naming_the_setting(flags: list[str], message: str) -> None:
    result = archery("controller", *flags, timeout=60)
    assert result.returncode == 2 and message in result.stderr
