"""`archery robot` over a real router: streams, commands, controlboard and archery RPC, events,
determinism, and a clean exit on SIGTERM."""

from __future__ import annotations

import contextlib
import math
import subprocess
import sys
import threading
from collections.abc import Callable, Iterator
from typing import Any

import msgspec
import mujoco
import numpy as np
import pytest

from archery.mesh.netflags import NetConfig
from archery.mesh.node import Node
from archery.mesh.subscription import Subscription
from archery.protocol.errors import RpcError
from archery.protocol.messages import JointCommand, JointState, WorldEvent, WorldState
from archery.protocol.parts import PARTS
from archery.protocol.robotspec import ROBOT
from archery.services.robot.config import RobotConfig
from archery.services.robot.service import run
from archery.sim.geometry import BOW_HAND, START_THETA
from archery.sim.model_build import build_scene
from archery.sim.scene_config import SceneConfig
from archery.sim.world import WorldConfig
from tests.conftest import archery
from tests.postures import archery_posture
from tests.rpc import rpc_call

WORLD = WorldConfig(scene=SceneConfig(meshes=False))
Joints = dict[str, np.ndarray]  # joint positions (rad) per part


@pytest.fixture(scope="module")
def aim_joints() -> Joints:
    model: mujoco.MjModel = build_scene(WORLD.scene)
    return archery_posture(model, BOW_HAND, BOW_HAND + START_THETA, tolerance=5e-3)


class Client:
    """A test's node on the mesh with the robot's streams subscribed."""

    def __init__(self, node: Node) -> None:
        self.node = node
        self.keys = node.keys
        self.states: dict[str, Subscription[JointState]] = {
            p: node.subscribe(self.keys.state(p), JointState) for p in PARTS
        }
        self.world = node.subscribe(self.keys.world_state(), WorldState)
        self.events = node.subscribe(self.keys.world_events(), WorldEvent, mode="fifo")
        self.commands = {p: node.publisher(self.keys.command(p), JointCommand) for p in PARTS}
        for pub in self.commands.values():
            assert pub.wait_matched(10)

    def part(self, part: str, verb: str, args: dict[str, Any] | None = None) -> Any:
        return rpc_call(self.node, self.keys.part_rpc(part), verb, args, timeout=10)

    def archery(self, verb: str, args: dict[str, Any] | None = None) -> Any:
        return rpc_call(self.node, self.keys.archery_rpc(), verb, args, timeout=20)

    def command(self, targets: Joints) -> None:
        for part, values in targets.items():
            self.commands[part].put(  # one batch: the parts start at one sim time
                JointCommand(part=part, position=np.asarray(values).tolist(), batch=len(targets))
            )

    def settle(self) -> dict[str, int]:
        """Sequence numbers of states showing the robot now (at rest, its sim time stands still),
        so that older messages still in flight cannot pass for a later one."""
        now = self.archery("status")["sim_time"]
        return {
            p: sub.wait_newer(10, lambda m: m.sim_time == now, after_seq=0).seq
            for p, sub in self.states.items()
        }

    def wait_reached(
        self, targets: Joints, after: dict[str, int], tolerance: float = 2e-3, timeout: float = 20
    ) -> None:
        for part, values in targets.items():
            wanted = np.asarray(values)

            def there(msg: JointState, wanted: np.ndarray = wanted) -> bool:
                error = np.max(np.abs(np.asarray(msg.position) - wanted))
                return msg.motion_done and error < tolerance

            self.states[part].wait_newer(timeout, there, after_seq=after[part])

    def move(self, targets: Joints, reached: Joints | None = None) -> None:
        """Command `targets` on command:i and wait for the states to show `reached` (default:
        the targets), motion done."""
        after = self.settle()
        self.command(targets)
        self.wait_reached(targets if reached is None else reached, after)

    def event(self, timeout: float = 20) -> WorldEvent:
        return self.events.get(timeout)


@pytest.fixture
def robot(net: NetConfig) -> Iterator[Callable[..., Client]]:
    """start(**config) runs the robot service in a thread and returns a connected client."""
    with robot_threads(net, WORLD) as start:
        yield start


@contextlib.contextmanager
def robot_threads(net: NetConfig, world: WorldConfig) -> Iterator[Callable[..., Client]]:
    """start(world=`world`, **config) runs a robot service in a thread and returns a connected
    client; every one started is stopped when the block ends."""
    stops: list[tuple[threading.Event, threading.Thread, Node]] = []

    def start(world: WorldConfig = world, **overrides: Any) -> Client:
        config = RobotConfig(net=net, world=world, **overrides)
        stop = threading.Event()
        thread = threading.Thread(target=run, args=(config, stop), daemon=True)
        thread.start()
        node = Node(None, net)
        stops.append((stop, thread, node))
        node.wait_alive([ROBOT], 30)
        return Client(node)

    yield start
    for stop, thread, node in stops:
        node.close()
        stop.set()
        thread.join(10)
        assert not thread.is_alive()


def test_state_streams_carry_each_part_s_joints(robot: Callable[..., Client]) -> None:
    client = robot()
    for part, names in PARTS.items():
        msg = client.states[part].wait_newer(10, after_seq=0)
        assert msg.part == part and msg.names == list(names)
        assert len(msg.position) == len(msg.velocity) == len(names)
        assert msg.motion_done and msg.sim_time == 0.0
        assert client.part(part, "getJointNames") == {"names": list(names)}
    world = client.world.wait_newer(10, after_seq=0)
    assert world.phase == "idle" and world.qpos.to_numpy().shape == (24,)


def test_commanded_joint_positions_are_reached(
    robot: Callable[..., Client], aim_joints: Joints
) -> None:
    client = robot()
    client.move(aim_joints)
    for part, values in aim_joints.items():
        assert client.part(part, "checkMotionDone") == {"done": True}
        np.testing.assert_allclose(client.part(part, "getTargets")["position"], values)
        np.testing.assert_allclose(client.part(part, "getPositions")["position"], values, atol=1e-3)
    assert client.archery("status")["sim_time"] > 0.5


def test_targets_beyond_a_limit_by_less_than_the_tolerance_are_clamped(
    robot: Callable[..., Client],
) -> None:
    client = robot(limit_tolerance=0.02)
    limits = {p: client.part(p, "getLimits") for p in PARTS}
    urdf_margin = WORLD.scene.limit_margin
    seen: list[JointState] = []  # every state message, not only the latest
    for part in PARTS:
        client.node.subscribe(client.keys.state(part), JointState, callback=seen.append)
    for side in ("max", "min"):
        beyond = {
            p: np.asarray(lim[side]) + (0.015 if side == "max" else -0.015)
            for p, lim in limits.items()
        }
        client.move(beyond, {p: np.asarray(lim[side]) for p, lim in limits.items()})
    for msg in seen:
        lim = limits[msg.part]
        q = np.asarray(msg.position)
        assert np.all(q >= np.asarray(lim["min"]) - urdf_margin), (msg.part, q)
        assert np.all(q <= np.asarray(lim["max"]) + urdf_margin), (msg.part, q)
    for part in PARTS:
        counters = client.part(part, "counters")
        assert counters["accepted"] == counters["clamped"] == 2
        assert counters["rejected"] == 0


def test_bad_commands_are_rejected_counted_and_the_sim_keeps_running(
    robot: Callable[..., Client], aim_joints: Joints
) -> None:
    client = robot()
    arm = client.commands["left_arm"]
    key = client.keys.command("left_arm")
    bad = [
        JointCommand(part="left_arm", position=[3.5] * 7),  # out of range
        JointCommand(part="left_arm", position=[0.0] * 5),  # wrong length
        JointCommand(part="left_arm", position=[0.1], names=["r_elbow"]),  # unknown joint
        JointCommand(part="torso", position=[0.0] * 7),  # wrong part
    ]
    for msg in bad:
        arm.put(msg)
    nan = {"type": "JointCommand", "schema": 1, "part": "left_arm", "position": [math.nan] * 7}
    client.node.session.put(key, msgspec.msgpack.encode(nan))
    client.move(aim_joints)  # the good command still goes through
    counters = client.part("left_arm", "counters")
    by_reason = counters["rejected_by_reason"]
    assert counters["rejected"] == 4 and counters["accepted"] == 1
    assert by_reason["out_of_range"] == by_reason["wrong_length"] == 1
    assert by_reason["unknown_joint"] == by_reason["wrong_part"] == 1
    assert counters["undecodable"] == 1  # NaN never decodes
    assert "wrong_part" not in counters["last_rejection"] and "torso" in counters["last_rejection"]
    np.testing.assert_allclose(
        client.part("left_arm", "getTargets")["position"], aim_joints["left_arm"]
    )


def test_position_move_validates_like_the_stream(robot: Callable[..., Client]) -> None:
    client = robot()
    with pytest.raises(RpcError, match="outside its limits") as info:
        client.part("torso", "positionMove", {"position": [0.0, 0.0, 3.0]})
    assert info.value.code == "bad_request"
    with pytest.raises(RpcError, match=r"unknown field `pos`.*arguments of positionMove: position"):
        client.part("torso", "positionMove", {"pos": [0.0, 0.0, 0.1]})
    with pytest.raises(RpcError, match="missing required field `position`") as info:
        client.part("torso", "positionMove", {})
    assert info.value.code == "bad_request"
    with pytest.raises(RpcError, match=r"`\$.speeds\[2\]`.*speeds must be float in \(0, 2\]"):
        client.part("torso", "setRefSpeeds", {"speeds": [0.5, 0.5, -1.0]})
    assert client.part("torso", "setRefSpeeds", {"speeds": 1.5})["speeds"] == [1.5] * 3
    after = client.settle()
    moved = client.part("torso", "positionMove", {"position": [0.1], "names": ["torso_pitch"]})
    assert moved["position"] == [0.0, 0.0, 0.1]
    client.wait_reached({"torso": np.array([0.0, 0.0, 0.1])}, after)
    assert client.part("torso", "counters")["rejected_by_reason"]["out_of_range"] == 1


def test_release_without_an_arrow_is_an_error_reply(robot: Callable[..., Client]) -> None:
    client = robot()
    with pytest.raises(RpcError, match="no arrow is nocked") as info:
        client.archery("release")
    assert info.value.code == "bad_state"
    with pytest.raises(RpcError, match=r"`\$.seed`.*got `str`.*seed must be int in \[0, "):
        client.archery("reset", {"seed": "seven"})


def test_a_shot_gives_events_with_the_ground_truth(
    robot: Callable[..., Client], aim_joints: Joints
) -> None:
    client = robot()
    client.move(aim_joints)
    assert client.archery("nock")["shot"] == 1
    reply = client.archery("release")
    assert not {"r", "point", "impact_m"} & set(reply)
    nocked, released, landed = client.event(), client.event(), client.event()
    assert (nocked.kind, released.kind) == ("nocked", "released")
    assert landed.kind == ("landed" if reply["hit"] else "missed")
    assert nocked.shot == released.shot == landed.shot == reply["shot"] == 1
    assert landed.sim_time == reply["sim_time"] and landed.reason == reply["reason"]
    assert landed.impact_m is not None and len(landed.impact_m) == 2  # crossed the plane
    np.testing.assert_allclose(reply["theta"], START_THETA, atol=6e-3)
    world = client.world.wait_newer(10, lambda m: m.sim_time >= reply["sim_time"], after_seq=0)
    assert world.phase in ("stuck", "missed") and world.shot == 1
    status = client.archery("status")
    assert status["shot"] == 1 and status["arrow"] == "landed"
    assert WorldConfig.from_dict(status["world"]) == WORLD  # a camera can rebuild the scene
    assert status["scene"] == WORLD.scene.to_dict() | {"camera_pos": list(WORLD.scene.camera_pos)}


def shoot(client: Client, aim_joints: Joints, seed: int) -> list[float]:
    """The true impact (m, on the target plane) of a shot with launch noise seeded by `seed`,
    checking the events on the way: reset, nocked, released, then the landing."""
    client.archery("reset", {"seed": seed})
    client.move(aim_joints)
    client.archery("nock")
    client.archery("release")
    events = [client.event() for _ in range(4)]
    assert [e.kind for e in events[:3]] == ["reset", "nocked", "released"]
    assert events[3].impact_m is not None
    return list(events[3].impact_m)


def test_the_same_seed_gives_the_same_impact(
    robot: Callable[..., Client], aim_joints: Joints
) -> None:
    client = robot()
    impacts = [shoot(client, aim_joints, seed) for seed in (5, 5, 6)]
    assert impacts[0] == impacts[1]  # bit for bit
    assert impacts[2] != impacts[0]  # another seed, other launch noise


def test_reset_waits_for_a_flight_to_land(robot: Callable[..., Client]) -> None:
    client = robot(rtf=1.0)
    client.archery("nock")  # from the home joint positions: a 0.38 s flight sideways to the ground
    replies: dict[str, Any] = {}
    thread = threading.Thread(target=lambda: replies.update(release=client.archery("release")))
    thread.start()
    assert [client.event().kind, client.event().kind] == ["nocked", "released"]
    reset = client.archery("reset", {"seed": 2})  # queued behind the release on archery/rpc:i
    thread.join(10)
    assert replies["release"]["outcome"] == "ground" and reset["sim_time"] == 0.0
    assert [client.event().kind, client.event().kind] == ["missed", "reset"]


def test_sigterm_ends_the_robot_process_cleanly(net: NetConfig) -> None:
    argv = [sys.executable, "-m", "archery.apps.cli", "robot", "--connect", net.connect[0]]
    proc = subprocess.Popen([*argv, "--robot", net.robot, "--rtf", "1"], stdin=subprocess.DEVNULL)
    try:
        with Node(None, net) as node:
            node.wait_alive([ROBOT], 60)
            assert rpc_call(node, node.keys.archery_rpc(), "status")["rtf"] == 1.0
            proc.terminate()
            assert proc.wait(20) == 0
            node.wait_gone(ROBOT, 10)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


@pytest.mark.parametrize(
    ("flags", "message"),
    [
        (["--rtf", "-1"], "--rtf must be in"),
        (["--wind", "1,2"], "--wind must be a finite 3-vector"),
        (["--bow-stiffness", "0"], "--bow-stiffness"),
        (["--drag", "20"], "drag must be in"),
    ],
)
def test_bad_flags_exit_2_naming_the_flag(flags: list[str], message: str) -> None:
    result = archery("robot", *flags, timeout=60)
    assert result.returncode == 2 and message in result.stderr
