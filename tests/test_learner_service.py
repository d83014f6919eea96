"""`archery learner` over a real router with the real robot and controller and stand-ins for the
camera and detector (the detector reports the robot's landing with noise): sessions through RPC,
rollouts on `learner/rollout:o`, the report, bad requests, a missing service, `archery learn`."""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from archery.apps.learn.follow import follow
from archery.mesh.netflags import NetConfig
from archery.mesh.node import Node
from archery.protocol.errors import ArcheryError, RpcError
from archery.protocol.journal_records import AbortedRecord, DoneRecord, ProposedRecord
from archery.protocol.messages import Rollout, WorldEvent
from archery.protocol.verbs import detector as dv
from archery.services.controller import service as controller_service
from archery.services.controller.config import ControllerConfig
from archery.services.learner import service as learner_service
from archery.services.learner.config import LearnerServiceConfig
from archery.services.learner.journal import read_records
from archery.services.robot import service as robot_service
from archery.services.robot.config import RobotConfig
from archery.sim.scene_config import SceneConfig
from archery.sim.world import WorldConfig
from tests.conftest import archery
from tests.rpc import rpc_call

WORLD = WorldConfig(scene=SceneConfig(meshes=False))


def run_fake_sensors(net: NetConfig, stop: threading.Event, noise_m: float = 0.003) -> None:
    """A camera that only shows up alive and a detector whose `measure` reports the robot's true
    impact (from `world/events:o`) plus Gaussian noise, or no_arrow after a miss."""
    rng = np.random.default_rng(0)
    with Node("camera", net) as camera, Node("detector", net) as detector:
        events: list[WorldEvent] = []
        cond = threading.Condition()

        def on_event(event: WorldEvent) -> None:
            if event.kind in ("landed", "missed"):
                with cond:
                    events.append(event)
                    cond.notify_all()

        detector.subscribe(detector.keys.world_events(), WorldEvent, mode="fifo", callback=on_event)

        def measure(args: dv.MeasureArgs) -> dv.MeasureReply:
            assert args.after_sim_time is not None
            after = args.after_sim_time
            with cond:
                cond.wait_for(lambda: events and events[-1].sim_time >= after, timeout=5)
                event = events[-1]
            found: dict[str, Any] = {"status": "no_arrow", "r_m": None}
            if event.impact_m is not None and event.kind != "missed":
                r = np.array(event.impact_m) + rng.normal(0, noise_m, 2)
                found = {"status": "ok", "r_m": r.tolist()}
            return dv.MeasureReply(
                type="Detection",
                schema=1,
                seq=0,
                stamp=time.time(),
                sim_time=event.sim_time,
                frame_stamp=time.time(),
                target_px=None,
                arrow_px=None,
                target_confidence=1.0,
                arrow_confidence=1.0,
                frame=0,
                timing={"detect_s": 0.001},
                **found,
            )

        def frame(args: dv.FrameArgs) -> dv.FrameReply:
            assert args == dv.FrameArgs(overlay=True)
            png = cv2.imencode(".png", np.zeros((8, 8, 3), np.uint8))[1].tobytes()
            return dv.FrameReply(png=png, status="ok")

        def absent(args: Any) -> Any:
            raise ArcheryError("the fake detector has no such verb", code="unsupported")

        verbs = {
            "measure": measure,
            "frame": frame,
            "baseline": absent,
            "calibrate": absent,
            "status": absent,
        }
        detector.serve(detector.keys.detector_rpc(), dv.DETECTOR_VERBS.bind_names(verbs))
        camera.ready()
        detector.ready()
        stop.wait()


@pytest.fixture
def mesh(net: NetConfig, tmp_path: Path) -> Iterator[Node]:
    """Robot, controller, fake sensors and the learner in threads; a client node."""
    stop = threading.Event()
    runs = [
        (robot_service.run, RobotConfig(net=net, world=WORLD, seed=7)),
        (controller_service.run, ControllerConfig(net=net)),
        (run_fake_sensors, net),
        (learner_service.run, LearnerServiceConfig(net=net, runs=tmp_path, start_wait=20)),
    ]
    threads = [threading.Thread(target=f, args=(c, stop), daemon=True) for f, c in runs]
    for thread in threads:
        thread.start()
    with Node(None, net) as node:
        node.wait_alive(["robot", "controller", "camera", "detector", "learner"], timeout=60)
        yield node
    stop.set()
    for thread in threads:
        thread.join(timeout=30)


def test_archer_session_over_the_mesh(mesh: Node, tmp_path: Path) -> None:
    keys = mesh.keys
    rollouts = mesh.subscribe(keys.learner_rollouts(), Rollout, mode="fifo")
    status = rpc_call(mesh, keys.learner_rpc(), "start", {"algo": "archer", "seed": 1}, timeout=30)
    session = status["session"]
    assert status["journal"] == str(tmp_path / session / "journal.jsonl")
    with pytest.raises(RpcError, match="is running") as busy:
        rpc_call(mesh, keys.learner_rpc(), "start", {"algo": "power"}, timeout=10)
    assert busy.value.code == "busy"
    seen: list[Rollout] = []
    final = follow(mesh, session, rollouts, seen.append)
    assert final["state"] == "finished" and final["ended"] == "hit"
    assert final["hit_at"] <= 10
    assert final["report"] == str(tmp_path / session / "report.png")
    assert Path(final["report"]).stat().st_size > 10_000
    assert Path(final["hit_frame"]).read_bytes().startswith(b"\x89PNG")
    records = read_records(Path(final["journal"]))[0]
    rollout_records = [
        r for r in records if isinstance(r, ProposedRecord | DoneRecord | AbortedRecord)
    ]
    assert [(m.record.index, m.record.kind) for m in seen] == [
        (r.index, r.kind) for r in rollout_records
    ]
    done = [r for r in records if isinstance(r, DoneRecord)]
    for record in done:
        # The learner was told the detector's r; the robot's truth is only logged beside it.
        assert record.truth_r_m is not None
        assert np.linalg.norm(np.subtract(record.r_m, record.truth_r_m)) < 0.02
        assert np.linalg.norm(np.subtract(record.theta, record.theta_measured)) < 1e-3
        # the θ the arrow left with, as the robot's release reply told it
        assert isinstance(record.theta_launched, list)
        assert np.linalg.norm(np.subtract(record.theta_launched, record.theta_measured)) < 5e-3
        assert record.timing["posture_s"] > 0 and record.timing["detector_detect_s"] > 0
    assert done[-1].hit and done[-1].distance_m < 0.05
    idle = rpc_call(mesh, keys.learner_rpc(), "status", timeout=10)
    assert idle["session"] == session and idle["state"] == "finished"


@pytest.mark.parametrize(
    ("args", "code", "message"),
    [
        ({"algo": "nope"}, "bad_request", "valid algorithms: archer"),
        ({"scenario": {"theta0": [0.5, 0.0, 0.0]}}, "bad_request", "outside the θ box"),
        (
            {"scenario": {"hit_radius": "big"}},
            "bad_request",
            r"`\$.scenario.hit_radius`: Expected `float`, got `str`; scenario.hit_radius must be "
            r"float in \[0.001, 0.25\]",
        ),
        ({"options": {"explore_std": -1}}, "bad_request", "explore_std"),
        ({"resume": "nonexistent/journal.jsonl"}, "bad_journal", "cannot read journal"),
        ({"resume": 3}, "bad_request", r"`\$.resume`.*resume must be str.*\(journal path\)"),
    ],
)
def test_bad_start(
    mesh: Node, tmp_path: Path, args: dict[str, Any], code: str, message: str
) -> None:
    with pytest.raises(RpcError, match=message) as error:
        rpc_call(mesh, mesh.keys.learner_rpc(), "start", args, timeout=30)
    assert error.value.code == code
    assert list(tmp_path.iterdir()) == []
    assert rpc_call(mesh, mesh.keys.learner_rpc(), "status", timeout=10) == {"state": "idle"}


def test_missing_services_at_start(net: NetConfig, tmp_path: Path) -> None:
    stop = threading.Event()
    config = LearnerServiceConfig(net=net, runs=tmp_path, start_wait=0.5)
    thread = threading.Thread(target=learner_service.run, args=(config, stop), daemon=True)
    thread.start()
    try:
        with Node(None, net) as node:
            node.wait_alive(["learner"], timeout=30)
            with pytest.raises(
                RpcError, match="services not alive: camera, controller, detector, robot"
            ) as error:
                rpc_call(node, node.keys.learner_rpc(), "start", {}, timeout=30)
            assert error.value.code == "service_missing"
        assert list(tmp_path.iterdir()) == []
    finally:
        stop.set()
        thread.join(timeout=30)


def test_stop_and_resume_over_the_mesh(mesh: Node, tmp_path: Path, net: NetConfig) -> None:
    keys = mesh.keys
    rollouts = mesh.subscribe(keys.learner_rollouts(), Rollout, mode="fifo")
    request = {"algo": "power", "seed": 2, "rollouts": 4, "until_hit": False}
    session = rpc_call(mesh, keys.learner_rpc(), "start", request, timeout=30)["session"]
    first = rollouts.get(timeout=30)
    assert isinstance(first.record, ProposedRecord) and first.record.session == session
    stopping = rpc_call(mesh, keys.learner_rpc(), "stop", timeout=10)
    assert stopping["stopping"] is True
    stopped = follow(mesh, session, rollouts, lambda m: None)
    assert stopped["state"] == "stopped" and stopped["rollouts"] < 4
    # `archery learn --resume` finishes it and prints the JSON line.
    result = archery(
        "learn",
        "--resume",
        stopped["journal"],
        "--connect",
        net.connect[0],
        "--robot",
        net.robot,
        timeout=120,
    )
    assert result.returncode == 0, result.stderr
    line = json.loads(result.stdout.strip().splitlines()[-1])
    assert line["session"] == session and line["rollouts"] == 4 and line["status"] == "finished"
    assert set(line) >= {"session", "rollouts", "hit_at", "final_distance_m", "journal"}
    records = read_records(Path(line["journal"]))[0]
    proposed = [r.index for r in records if isinstance(r, ProposedRecord)]
    assert proposed == list(range(1, len(proposed) + 1))
    assert "θ (" in result.stderr
