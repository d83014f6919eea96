"""A recorded camera stream replayed into a fresh detector reproduces every recorded r, also
across a reset of the simulated clock."""

from __future__ import annotations

import signal
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from archery.apps.topics.recording import CALIBRATION_ATTACHMENT, open_recording
from archery.mesh.netflags import NetConfig
from archery.mesh.node import Node
from archery.protocol.errors import RpcError
from archery.protocol.keys import Keys
from archery.protocol.messages import Detection, WorldState
from archery.services.detector.config import DetectorConfig
from archery.services.detector.service import run as run_detector
from benchmarks.bench_record import remeasure
from tests import test_detector_service
from tests.conftest import serving
from tests.rpc import rpc_call
from tests.spawn import spawn
from tests.test_detector_service import _state, camera_and_detector

shot = test_detector_service.shot  # the landed arrow's fixture, shared


def test_replayed_frames_give_the_recorded_detections(
    net: NetConfig, shot: tuple[np.ndarray, float, np.ndarray], tmp_path: Path
) -> None:
    qpos, sim_time, truth = shot
    model_file, path = tmp_path / "model.json", tmp_path / "camera.mcap"
    flags = ["--connect", net.connect[0]]
    with camera_and_detector(net, model_file) as node:
        keys = node.keys
        recorder = spawn(
            "record",
            "--out",
            str(path),
            keys.cam_frames(),
            keys.detector_hits(),
            "--robot",
            net.robot,
            *flags,
            ready="archery record: recording",
        )
        world = node.publisher(keys.world_state(), WorldState)
        assert world.wait_matched(5)
        measured = []
        # two rollouts' landings of the same arrow; the second after a reset of the simulated
        # clock, so its sim time is below the first's: only the stamp tells their frames apart
        for offset in (0.25, 0.0):
            started = time.time()
            world.put(_state(qpos, sim_time + offset - 0.5))
            later = threading.Timer(0.3, lambda o=offset: world.put(_state(qpos, sim_time + o)))
            later.start()
            reply = rpc_call(
                node,
                keys.detector_rpc(),
                "measure",
                {"after_sim_time": sim_time + offset, "after_stamp": started},
                timeout=30,
            )
            later.join()
            assert reply["status"] == "ok", reply
            assert reply["sim_time"] == sim_time + offset
            measured.append(reply)
        assert np.linalg.norm(np.subtract(measured[0]["r_m"], truth)) <= 0.01
        recorder.send_signal(signal.SIGINT)
        out, err = recorder.communicate(timeout=60)
        assert recorder.returncode == 0, err
    hits = [m for k, m, _ in open_recording(path).messages() if k.endswith("detector/hit:o")]
    assert [h.r_m for h in hits] == [m["r_m"] for m in measured]
    assert all(isinstance(h, Detection) and h.sim_time is not None for h in hits)

    # a fresh detector that was never calibrated (no model file), on another robot prefix;
    # the replay stands in for the camera: grab from the replayed frames, calibration from the
    # calibration frame and marks the recorder took from the camera
    fresh = NetConfig(connect=net.connect, robot=net.robot + "replay")
    replay = spawn(
        "replay",
        str(path),
        "--keys",
        f"{net.robot}/cam/target:o",
        "--serve-grab",
        "--rate",
        "4",
        "--robot",
        fresh.robot,
        *flags,
        ready="archery replay: serving grab on",
    )
    assert open_recording(path).attachment(CALIBRATION_ATTACHMENT) is not None
    config = DetectorConfig(net=fresh)  # calibrates itself from the camera's marks
    try:
        fresh_keys = Keys(fresh.robot)
        with serving(run_detector, config), Node(None, fresh) as node:
            node.wait_alive(["detector"], timeout=30)
            worst, _, absent = remeasure(node, hits)
            assert worst <= 1e-3  # 1 mm
            assert absent == 0  # every measured frame was recorded
            status = rpc_call(node, fresh_keys.detector_rpc(), "status", timeout=10)
            assert status["calibrated"]
            with pytest.raises(RpcError, match="a replay serves the recorded camera frames") as no:
                rpc_call(node, fresh_keys.cam_rpc(), "scene", timeout=10)
            assert no.value.code == "bad_request"
    finally:
        replay.send_signal(signal.SIGINT)
        out, err = replay.communicate(timeout=60)
    assert replay.returncode == 0, err
    assert "archery replay: published" in out
