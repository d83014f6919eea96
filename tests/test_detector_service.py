"""The detector service over a real router, with the camera service rendering the world states
the test publishes from a simulated shot: measure, calibrate, the hit stream, bad requests."""

from __future__ import annotations

import math
import threading
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path

import cv2
import numpy as np
import pytest

from archery.mesh.netflags import NetConfig
from archery.mesh.node import Node
from archery.protocol.errors import RpcError
from archery.protocol.messages import Array, Detection, WorldState
from archery.services.camera.config import CameraConfig
from archery.services.camera.service import run as run_camera
from archery.services.detector.config import DetectorConfig
from archery.services.detector.detect import DetectorSettings
from archery.services.detector.service import run as run_detector
from archery.sim.bow import Bow
from archery.sim.geometry import BOW_HAND, TARGET_DISTANCE
from archery.sim.model_build import build_scene
from archery.sim.scene import ScenePhysics
from archery.sim.scene_config import SceneConfig
from archery.sim.world import ArcheryWorld, WorldConfig
from tests.conftest import serving
from tests.postures import archery_posture
from tests.rpc import rpc_call
from tests.world_steps import move_until_done

SCENE = SceneConfig(meshes=False)


@pytest.fixture(scope="module")
def shot() -> tuple[np.ndarray, float, np.ndarray]:
    """(qpos, sim time, true r) of an arrow stuck in the face after a real release."""
    model = build_scene(SCENE)
    world = ArcheryWorld(WorldConfig(scene=SCENE, direction_noise=0.02), model=model)
    length = 0.17
    speed = Bow().launch_speed(np.array([length, 0.0, 0.0]))
    distance = BOW_HAND[0] + TARGET_DISTANCE
    elevation = math.atan2(0.5 * 9.81 * (distance / speed) ** 2, distance)
    theta = length * np.array([math.cos(elevation), 0.0, -math.sin(elevation)])
    world.reset(5)
    for part, values in archery_posture(model, BOW_HAND, BOW_HAND + theta, tolerance=5e-3).items():
        world.set_joint_targets(part, values)
    assert move_until_done(world, 15.0)
    world.nock()
    landing = world.release()
    assert landing.hit and landing.r is not None
    return world.qpos(), world.sim_time, landing.r


def _state(qpos: np.ndarray, sim_time: float) -> WorldState:
    return WorldState(qpos=Array.from_numpy(qpos), phase="stuck", shot=1, sim_time=sim_time)


@contextmanager
def camera_and_detector(net: NetConfig, model_file: Path) -> Iterator[Node]:
    """The camera and the detector (auto-calibrating, saving its model to `model_file`) on
    threads, and a node that has seen both alive."""
    with ExitStack() as stack:
        stack.enter_context(serving(run_camera, CameraConfig(net=net, robot_timeout=0.3)))
        stack.enter_context(serving(run_detector, DetectorConfig(net=net, model=str(model_file))))
        node = stack.enter_context(Node(None, net))
        node.wait_alive(["camera", "detector"], timeout=30)
        yield node


def test_measure_a_landed_arrow_and_stream_the_detection(
    net: NetConfig, shot: tuple[np.ndarray, float, np.ndarray], tmp_path: Path
) -> None:
    qpos, sim_time, truth = shot
    model_file = tmp_path / "model.json"
    with camera_and_detector(net, model_file) as node:
        keys = node.keys
        hits = node.subscribe(keys.detector_hits(), Detection, mode="fifo")
        world = node.publisher(keys.world_state(), WorldState)
        assert world.wait_matched(5)
        # the sim time of the landing: a frame from before it would not show the arrow
        world.put(_state(qpos, sim_time - 0.5))
        threading.Timer(0.3, lambda: world.put(_state(qpos, sim_time))).start()
        reply = rpc_call(
            node, keys.detector_rpc(), "measure", {"after_sim_time": sim_time}, timeout=30
        )
        assert reply["status"] == "ok" and reply["sim_time"] >= sim_time
        assert np.linalg.norm(np.subtract(reply["r_m"], truth)) <= 0.01
        assert reply["target_confidence"] > 0.9 and reply["arrow_confidence"] > 0.5
        assert reply["timing"]["detect_s"] < 0.5 and reply["frame"] >= 1
        streamed = hits.get(timeout=5)
        assert streamed.r_m == reply["r_m"] and streamed.seq == reply["seq"]
        assert model_file.is_file()  # auto-calibrated from the camera's marks, and saved

        status = rpc_call(node, keys.detector_rpc(), "status", timeout=5)
        assert status["calibrated"] and status["measured"] == 1
        assert status["model"]["target"]["components"] > status["model"]["arrow"]["components"]

        png = rpc_call(node, keys.detector_rpc(), "frame", timeout=10)["png"]
        overlay = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
        assert overlay.shape[0] == 720 and overlay.shape[1] > 2 * 1280
        # the same frame by the measurement's seq; one never measured (or dropped): named
        by_seq = {"seq": reply["seq"]}
        assert rpc_call(node, keys.detector_rpc(), "frame", by_seq, timeout=10)["png"] == png
        for args, message in (
            (
                {"seq": reply["seq"] + 1},
                rf"no kept frame of measurement {reply['seq'] + 1}.*last 8",
            ),
            ({"seq": 0}, r"seq must be int >= 1"),
        ):
            with pytest.raises(RpcError, match=message) as bad:
                rpc_call(node, keys.detector_rpc(), "frame", args, timeout=5)
            assert bad.value.code == "bad_request"

        # a landing the camera has not rendered yet: a clear timeout, not a stale frame
        with pytest.raises(RpcError, match="no frame with sim time") as late:
            rpc_call(
                node,
                keys.detector_rpc(),
                "measure",
                {"after_sim_time": sim_time + 10, "timeout": 0.5},
                timeout=10,
            )
        assert late.value.code == "timeout"
        for args, message in (
            ({"after_sim": 1.0}, "unknown field `after_sim`.*after_sim_time, after_stamp"),
            ({"after_stamp": "now"}, r"`\$.after_stamp`.*got `str`.*must be float"),
            ({"timeout": -1}, r"timeout must be float in \(0, 120\]"),
        ):
            with pytest.raises(RpcError, match=message) as bad:
                rpc_call(node, keys.detector_rpc(), "measure", args, timeout=5)
            assert bad.value.code == "bad_request"

        # calibrate again from explicit pixels on the newest frame: a target-only model
        marks = rpc_call(node, keys.cam_rpc(), "calibration", timeout=30)["pixels"]
        summary = rpc_call(
            node,
            keys.detector_rpc(),
            "calibrate",
            {"pixels": {"target": marks["target"]}},
            timeout=30,
        )
        assert summary["arrow"] is None and summary["target_pixels"] > 50
        reply = rpc_call(node, keys.detector_rpc(), "measure", timeout=10)
        assert reply["status"] == "no_arrow" and reply["r_m"] is None
        with pytest.raises(RpcError, match="unknown keys") as bad:
            rpc_call(node, keys.detector_rpc(), "calibrate", {"pixels": {"tip": []}}, timeout=10)
        assert bad.value.code == "bad_calibration"


def test_measure_without_stamps_measures_a_frame_taken_after_it_was_asked(
    net: NetConfig, shot: tuple[np.ndarray, float, np.ndarray], tmp_path: Path
) -> None:
    """Two shots, nobody watching the camera in between: a bare `measure` gets the second."""
    qpos, sim_time, truth = shot
    physics = ScenePhysics(build_scene(SCENE))
    physics.data.qpos[:] = qpos
    physics.forward()
    tip, quat = physics.arrow_pose()
    moved = np.array([0.0, 0.06, 0.05])  # the second arrow 6 cm left and 5 cm above the first
    physics.set_arrow_pose(tip + moved, quat)
    second = physics.qpos()
    with camera_and_detector(net, tmp_path / "model.json") as node:
        keys = node.keys
        world = node.publisher(keys.world_state(), WorldState)
        assert world.wait_matched(5)
        world.put(_state(qpos, sim_time))
        first = rpc_call(
            node, keys.detector_rpc(), "measure", {"after_sim_time": sim_time}, timeout=30
        )
        assert np.linalg.norm(np.subtract(first["r_m"], truth)) <= 0.01
        world.put(_state(second, sim_time + 5.0))
        # the world state reaches the camera asynchronously: a bare measure may, at worst, be of
        # a frame captured after it was asked but before the state arrived; never the cached one
        bare = rpc_call(node, keys.detector_rpc(), "measure", timeout=30)
        while bare["sim_time"] < sim_time + 5.0:
            assert bare["frame"] > first["frame"]  # a new capture, not the kept frame
            bare = rpc_call(node, keys.detector_rpc(), "measure", timeout=30)
        assert bare["frame"] > first["frame"] and bare["status"] == "ok"
        assert np.linalg.norm(np.subtract(bare["r_m"], np.add(truth, moved[1:]))) <= 0.01


def test_without_a_model_or_auto_calibration_measure_says_what_to_do(net: NetConfig) -> None:
    config = DetectorConfig(
        net=net, auto_calibrate=False, settings=DetectorSettings(), camera_timeout=1.0
    )
    with serving(run_detector, config), Node(None, net) as node:
        node.wait_alive(["detector"], timeout=30)
        with pytest.raises(RpcError, match="no colour model yet") as refused:
            rpc_call(node, node.keys.detector_rpc(), "measure", timeout=5)
        assert refused.value.code == "not_calibrated"
        assert rpc_call(node, node.keys.detector_rpc(), "status", timeout=5)["calibrated"] is False
        # no camera on the mesh: calibrating says so
        with pytest.raises(RpcError, match="cam/rpc:i"):
            rpc_call(node, node.keys.detector_rpc(), "calibrate", {"timeout": 0.5}, timeout=10)
