"""`archery robot --shot whole` over a real router: the scripted whole shot driven on the
parts' `command:i` ports and the archery verbs (grasp, nock, release), and its failures as
error replies with their codes."""

from __future__ import annotations

import argparse
import dataclasses
import json
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import mujoco
import numpy as np
import pytest

from archery.apps.demonstrate import Recorder
from archery.apps.demonstrate import main as demonstrate
from archery.apps.imitate import main as imitate
from archery.apps.shot_plan import ShotStep, plan_whole_shot
from archery.apps.teacher import Teacher
from archery.mesh.netflags import NetConfig
from archery.mesh.node import Node
from archery.protocol.demonstration import MIN_SAMPLES, encode_demonstration
from archery.protocol.errors import ConfigError, RpcError
from archery.protocol.messages import Image
from archery.protocol.robotspec import BOW_ARM, STRING_ARM, THETA0
from archery.protocol.theta import THETA_BOX
from archery.services.camera.config import CameraConfig
from archery.services.camera.service import run as camera
from archery.services.controller.config import ControllerConfig
from archery.services.controller.demonstration_file import SHIPPED_DEMONSTRATION
from archery.services.controller.service import run as controller
from archery.services.learner.abort_policy import after_abort
from archery.services.learner.rig import MeshRig
from archery.services.learner.rollout_step import Failed, shoot
from archery.services.robot.config import add_arguments, make_config
from archery.sim.geometry import BOW_HAND, START_THETA
from archery.sim.model_build import build_scene
from archery.sim.scene_config import SceneConfig
from archery.sim.world import ArcheryWorld, WorldConfig
from tests.conftest import archery, serving
from tests.postures import archery_posture
from tests.ros2_sdk import until
from tests.rpc import rpc_call
from tests.test_robot_service import Client, robot_threads

WHOLE = WorldConfig(scene=SceneConfig(meshes=False, shot="whole"))
SHIPPED = SHIPPED_DEMONSTRATION
Joints = dict[str, np.ndarray]


@pytest.fixture(scope="module")
def model() -> mujoco.MjModel:
    return build_scene(WHOLE.scene)


@pytest.fixture(scope="module")
def aim(model: mujoco.MjModel) -> Joints:
    return archery_posture(model, BOW_HAND, BOW_HAND + START_THETA, tolerance=5e-3)


@pytest.fixture
def robot(net: NetConfig) -> Iterator[Callable[..., Client]]:
    """start(world, **config) runs the robot service in a thread and returns a connected
    client."""
    with robot_threads(net, WHOLE) as start:
        yield start


def _plan(model: mujoco.MjModel, aim: Joints, **offsets: Any) -> list[ShotStep]:
    """The script, planned on a world of the same scene standing in the archery posture."""
    world = ArcheryWorld(WHOLE, model=model)
    for part, values in aim.items():
        world.physics.set_joint_positions(part, values)
    return plan_whole_shot(world, START_THETA, **offsets)


def _arms(step: ShotStep) -> Joints:
    arms = {STRING_ARM: step.right_arm}
    if step.left_arm is not None:
        arms[BOW_ARM] = step.left_arm
    return arms


def _drive(client: Client, steps: list[ShotStep], until: str) -> None:
    """Move the arms on command:i through the steps and call their actions, up to the action
    of step `until`."""
    for step in steps:
        client.move(_arms(step))
        if step.name == until:
            return
        if step.action is not None:
            client.archery(step.action)


def test_the_whole_shot_over_the_mesh(
    robot: Callable[..., Client], model: mujoco.MjModel, aim: Joints
) -> None:
    client = robot()
    assert client.archery("status")["scene"]["shot"] == "whole"
    client.move(aim)
    steps = _plan(model, aim)
    _drive(client, steps, until="reach")
    grasped = client.archery("grasp")
    assert grasped["arrow"] == "grasped" and grasped["distance"] <= grasped["tolerance"]
    client.move(_arms(steps[2]))  # lift
    client.move(_arms(steps[3]))  # carry
    assert client.archery("nock")["arrow"] == "nocked"
    client.move(_arms(steps[4]))  # draw
    released = client.archery("release")
    assert released["flight_time"] > 0.05
    assert released["outcome"] in {"target", "outside_face", "ground"}
    assert client.archery("status")["arrow"] == "landed"


def test_a_grasp_off_the_shaft_is_refused_and_the_arrow_stays(
    robot: Callable[..., Client], model: mujoco.MjModel, aim: Joints
) -> None:
    client = robot()
    client.move(aim)
    tolerance = WHOLE.grasp_tolerance
    steps = _plan(model, aim, grasp_offset=np.array([0.0, 0.0, 1.5 * tolerance]))
    _drive(client, steps, until="reach")
    with pytest.raises(RpcError) as missed:
        client.archery("grasp")
    assert missed.value.code == "grasp_missed"
    assert client.archery("status")["arrow"] == "stowed"


def test_a_missed_nock_and_a_dropped_arrow_are_error_replies(
    robot: Callable[..., Client], model: mujoco.MjModel, aim: Joints
) -> None:
    client = robot()
    client.move(aim)
    offset = np.array([0.0, 0.0, 1.5 * WHOLE.nock_tolerance])
    _drive(client, _plan(model, aim, nock_offset=offset), until="carry")
    with pytest.raises(RpcError) as missed:
        client.archery("nock")
    assert missed.value.code == "nock_missed"
    assert client.archery("status")["arrow"] == "grasped"
    with pytest.raises(RpcError) as dropped:
        client.archery("release")
    assert dropped.value.code == "arrow_dropped"
    assert client.archery("status")["arrow"] == "dropped"


def test_grasp_is_refused_under_the_posture_shot(robot: Callable[..., Client]) -> None:
    client = robot(WorldConfig(scene=SceneConfig(meshes=False)))
    with pytest.raises(RpcError) as refused:
        client.archery("grasp")
    assert refused.value.code == "bad_state"
    assert client.archery("nock")["arrow"] == "nocked"  # the posture shot as before


def test_the_shot_flag_picks_the_scene() -> None:
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    for flags, shot in (([], "posture"), (["--shot", "whole"], "whole")):
        config = make_config(parser.parse_args(flags), NetConfig())
        assert config.world.scene.shot == shot
    result = archery("robot", "--shot", "bow", timeout=60)
    assert result.returncode == 2 and "--shot" in result.stderr


def test_a_demonstration_is_recorded_while_the_arms_are_driven(
    robot: Callable[..., Client], model: mujoco.MjModel, aim: Joints, tmp_path: Path
) -> None:
    # at rtf 0 the state:o streams are paced per wall second too: the recorder reads the robot's
    # history, every joint-state period of simulated time (50 Hz)
    client = robot()
    client.move(aim)
    recorder = Recorder(client.node, "whole", made="the scripted whole shot of apps.shot_plan")
    try:
        assert recorder.wait_started(10)
        _drive(client, _plan(model, aim), until="")  # every step and its action
        assert recorder.wait_ended(30)
        demo = recorder.demonstration()
    finally:
        recorder.close()
    kinds = [event.kind for event in demo.events]
    assert kinds[:3] == ["grasped", "nocked", "released"] and kinds[3] in {"landed", "missed"}
    assert len(demo.samples) >= MIN_SAMPLES
    intervals = np.diff([sample.t for sample in demo.samples])
    np.testing.assert_allclose(intervals, 1 / 50, atol=1e-9)  # every grid point, none skipped
    final = demo.samples[-1]
    assert final.t >= demo.events[2].t  # the arms until the landing
    moved = np.abs(np.asarray(final.right_arm) - np.asarray(demo.samples[0].right_arm))
    assert np.max(moved) > 0.1  # the right arm drew
    path = tmp_path / "demo.json"
    path.write_bytes(encode_demonstration(demo))
    assert demonstrate(["--check", str(path)]) == 0


def test_the_teacher_drives_the_whole_shot(robot: Callable[..., Client]) -> None:
    client = robot()
    teacher = Teacher(client.node, timeout=20)
    try:
        teacher.teach(START_THETA)
    finally:
        teacher.close()
    assert client.archery("status")["arrow"] == "landed"


def test_the_teacher_refuses_a_posture_robot(robot: Callable[..., Client]) -> None:
    client = robot(WorldConfig(scene=SceneConfig(meshes=False)))
    teacher = Teacher(client.node, timeout=20)
    try:
        with pytest.raises(ConfigError, match="--shot whole"):
            teacher.teach(START_THETA)
    finally:
        teacher.close()


def _net_flags(net: NetConfig) -> list[str]:
    return ["--connect", net.connect[0], "--robot", net.robot]


def test_imitate_draws_the_dmps_movement_for_theta(
    robot: Callable[..., Client], net: NetConfig, capsys: pytest.CaptureFixture[str]
) -> None:
    client = robot()
    theta = np.array([0.19, 0.03, -0.035])
    flags = ["--theta", ",".join(str(v) for v in theta), *_net_flags(net)]
    assert imitate([str(SHIPPED), *flags]) == 0
    reply = json.loads(capsys.readouterr().out)
    np.testing.assert_allclose(reply["theta"], theta, atol=5e-3)  # the arrow's θ at the release
    assert reply["flight_time"] > 0.05
    assert client.archery("status")["arrow"] == "landed"


def test_imitate_refuses_a_theta_outside_the_box_and_nothing_moves(
    robot: Callable[..., Client], net: NetConfig, capsys: pytest.CaptureFixture[str]
) -> None:
    client = robot()
    before = client.part(STRING_ARM, "getPositions")
    assert imitate([str(SHIPPED), "--theta", "0.4,0,0", *_net_flags(net)]) == 2
    said = [line for line in capsys.readouterr().err.splitlines() if "archery imitate" in line]
    assert len(said) == 1 and "outside the θ box" in said[0], said  # the robot logs too
    after = client.part(STRING_ARM, "getPositions")
    assert after["position"] == before["position"] and after["sim_time"] == before["sim_time"]


@pytest.mark.parametrize(
    ("tolerances", "code"),
    [({"grasp_tolerance": 1e-4}, "grasp_missed"), ({"nock_tolerance": 1e-4}, "nock_missed")],
)
def test_a_learner_rollout_whose_grasp_or_nock_fails_is_an_abort_retried_on_a_reset_robot(
    robot: Callable[..., Client], net: NetConfig, tolerances: dict[str, float], code: str
) -> None:
    client = robot(dataclasses.replace(WHOLE, **tolerances))
    theta = np.array([0.19, 0.03, -0.035])
    with serving(controller, ControllerConfig(net=net)), Node(None, net) as node:
        node.wait_alive(["controller"], timeout=30)
        rig = MeshRig(node, timeout=30)
        rig.services = ("robot", "controller")  # only these run: the others are not lost
        try:
            assert rig.follow_shot() == "whole"
            failed = shoot(rig, theta)
        finally:
            rig.close()
    assert isinstance(failed, Failed) and failed.code == code, failed
    # the robot was reset: home, a fresh arrow in the holder, the arms' leases dropped
    status = client.archery("status")
    assert status["arrow"] == "stowed" and status["sim_time"] < 1.0
    # the controller drops its leases in the background once the movement has ended
    until(lambda: client.part(STRING_ARM, "getClaim")["held"] is False, "the lease dropped")
    # the abort rules re-run the same θ
    decision = after_abort(failed.code, theta, best_theta=None, theta0=THETA0, bounds=THETA_BOX)
    assert decision.failure is None and np.allclose(decision.retry_theta, theta)


def test_the_controller_refuses_a_bad_demonstration_in_one_line(tmp_path: Path) -> None:
    short = tmp_path / "short.json"
    short.write_text('{"format": 1}')
    for path, said in ((tmp_path / "none.json", "cannot read it"), (short, str(short))):
        result = archery("controller", "--demonstration", str(path), "--connect", "tcp/127.0.0.1:9")
        assert result.returncode == 2, result.stderr
        lines = result.stderr.strip().splitlines()
        assert len(lines) == 1 and "--demonstration" in lines[0] and said in lines[0], lines


def test_the_camera_and_so_the_dashboard_s_view_render_the_whole_shot_s_scene(
    robot: Callable[..., Client], net: NetConfig
) -> None:
    """The camera builds its scene from the robot's status: the holder, the fingers and the
    string's nocking point are in the detector's frames and the third-person view (`scene`,
    the dashboard's robot panel) of a whole-shot robot."""
    client = robot()
    with serving(camera, CameraConfig(net=net, robot_timeout=10.0)), Node(None, net) as node:
        node.wait_alive(["camera"], timeout=30)
        status = rpc_call(node, node.keys.cam_rpc(), "status", timeout=10)
        assert status["scene_from"] == "robot" and status["scene"]["shot"] == "whole", status
        client.archery("status")  # the robot still answers beside the camera


@pytest.mark.parametrize("shot", ["posture", "whole"])
def test_a_camera_started_before_the_robot_renders_its_scene_once_it_answers(
    robot: Callable[..., Client], net: NetConfig, shot: str
) -> None:
    """The camera renders the default scene until the robot answers, then rebuilds the robot's
    for its frames and its scene view: a scene of the same joints (rebuilt on the robot's
    answer) and the whole shot's (rebuilt on its world state's size)."""
    posture = WorldConfig(scene=SceneConfig(meshes=False, target_distance=3.0))
    with serving(camera, CameraConfig(net=net, robot_timeout=0.5)), Node(None, net) as node:
        node.wait_alive(["camera"], timeout=30)
        key = node.keys.cam_rpc()
        assert rpc_call(node, key, "status", timeout=10)["scene_from"] == "default"
        robot(posture if shot == "posture" else WHOLE)
        # a watcher of the frames: the camera renders the robot's states, asking it again
        node.subscribe(node.keys.cam_frames(), Image)

        def rebuilt() -> bool:
            status = rpc_call(node, key, "status", timeout=10)
            return status["scene_from"] == "robot" and status["scene"]["shot"] == shot

        until(rebuilt, f"the camera rebuilt the robot's {shot} scene")
        until(
            lambda: rpc_call(node, key, "scene", timeout=10)["status"] == "ok",
            f"a scene view of the robot's {shot} scene",
        )


def test_the_learner_asks_the_controller_for_the_robot_s_shot(
    robot: Callable[..., Client], net: NetConfig
) -> None:
    """The learner only reads the robot's shot; a posture asked for the other shot is refused
    by the controller with `bad_state` naming the robot's, and nothing moves."""
    client = robot()
    before = client.part(STRING_ARM, "getPositions")
    with serving(controller, ControllerConfig(net=net)), Node(None, net) as node:
        node.wait_alive(["controller"], timeout=30)
        rig = MeshRig(node, timeout=30)
        try:
            assert rig.follow_shot() == "whole" and rig.shot == "whole"
            key = node.keys.cartesian_rpc("archery")
            with pytest.raises(RpcError, match="runs the 'whole' shot") as refused:
                rpc_call(node, key, "posture", {"theta": list(THETA0)}, timeout=30)
            assert refused.value.code == "bad_state"
        finally:
            rig.close()
    after = client.part(STRING_ARM, "getPositions")
    assert after["position"] == before["position"]
