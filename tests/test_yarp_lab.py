"""A lab's robot as the paper shot it, with YARP's own devices on the other side: YARP 3.5's
`fakeMotionControl` arms (16 named axes each) behind `archery robot --body yarp` (a nock
posture that closes the index finger, the release that opens it, no reset posture), a
`folder:` camera that shows what a real camera would (the scene with an older arrow, then the
new arrow in flight and at rest, once the finger opened), the detector telling the landing from
the frames alone, the controller and the learner. The operator confirms the reset the robot
cannot do; an operator who never confirms stops the session, its journal intact, resumable."""

from __future__ import annotations

import math
import os
import signal
import subprocess
import threading
import time
from collections.abc import Iterator
from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from archery.apps.learn.follow import follow
from archery.mesh.netflags import NetConfig
from archery.mesh.node import Node
from archery.protocol.journal_records import DoneRecord, ProposedRecord, StoppedRecord
from archery.protocol.messages import Image, Rollout
from archery.protocol.robotspec import ROBOT
from archery.services.camera.config import CameraConfig
from archery.services.camera.service import run as run_camera
from archery.services.camera.sources import parse_source
from archery.services.controller import service as controller_service
from archery.services.controller.config import ControllerConfig
from archery.services.detector.config import DetectorConfig
from archery.services.detector.service import run as run_detector
from archery.services.learner import service as learner_service
from archery.services.learner.config import LearnerServiceConfig
from archery.services.learner.journal import read_records
from tests.conftest import serving
from tests.ros2_sdk import until
from tests.rpc import rpc_call
from tests.test_detector_landing import NEW_R, Rendered, render_scenes
from tests.test_detector_landing_mesh import Scene
from tests.test_yarp_body import FAKE, Board, Robots, _fake_motion_control
from tests.test_yarp_body_robot import _robot
from tests.yarp_setup import YarpSetup

yarp = pytest.importorskip("yarp", reason="YARP's bindings: `make setup` builds and installs them")

pytestmark = pytest.mark.slow

NOCKED, OPEN = 60.0, 5.0  # deg: the index finger on the string, and open


@dataclass
class Lab:
    net: NetConfig
    tmp: Path
    scene: Scene
    scenes: Rendered
    node: Node
    robots: Robots


@pytest.fixture(scope="module")
def lab(router_endpoint: str, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Lab]:
    if not _fake_motion_control():
        pytest.skip("this YARP has no fakeMotionControl device (tools/yarp_wheel.py builds it)")
    tmp = tmp_path_factory.mktemp("yarp_lab")
    scenes = render_scenes()
    net = NetConfig(connect=(router_endpoint,), robot=f"lab{os.getpid()}")
    with ExitStack() as stack:
        setup = YarpSetup(yarp, tmp / "server")
        stack.callback(setup.close)
        robots = Robots(setup, tmp)
        stack.callback(robots.close)
        hands = tmp / "hands.json"
        hands.write_text(f'{{"nock": {{"r_index_proximal": {NOCKED}}}, "operator": ["nock"]}}')
        log = tmp / "robot.log"
        flags = ("--remote", "/fake", "--hand-postures", str(hands), "--release-open", str(OPEN))
        proc = _robot(net, setup.env, log, *flags)
        stack.callback(_ended, proc, log)
        scene = Scene(tmp)
        scene.show(scenes.old)
        model = tmp / "model.json"
        scenes.detector.model.save(str(model))
        camera = CameraConfig(net=net, source=parse_source(f"folder:{scene.path.parent}"), rate=20)
        stack.enter_context(serving(run_camera, camera))
        detector = DetectorConfig(net=net, model=str(model), auto_calibrate=False)
        stack.enter_context(serving(run_detector, detector))
        stack.enter_context(serving(controller_service.run, ControllerConfig(net=net)))
        node = stack.enter_context(Node(None, net))
        node.wait_alive([ROBOT, "camera", "detector", "controller"], timeout=60)
        yield Lab(net, tmp, scene, scenes, node, robots)


def _ended(proc: subprocess.Popen[bytes], log: Path) -> None:
    signal.signal(signal.SIGCHLD, signal.SIG_DFL)  # YARP's handler reaps children
    proc.terminate()
    assert proc.wait(20) == 0, log.read_text(errors="replace")[-2000:]


def _finger() -> float:
    """The right index finger as fakeMotionControl reads it (deg)."""
    board = Board("/fake/right_arm", "/test/lab/finger")
    try:
        return board.read()[FAKE["right_arm"].index("r_index_proximal")]
    finally:
        board.close()


def _arrows_land(lab: Lab, frames: Any, done: threading.Event) -> None:
    """The world of a session's shots: each release (the finger seen closed, then open) shows
    the new arrow in flight (two frames), then at rest."""
    board = Board("/fake/right_arm", "/test/lab/world")
    axis = FAKE["right_arm"].index("r_index_proximal")

    def finger(opened: bool) -> bool:
        while not done.is_set():
            if (abs(board.read()[axis] - OPEN) < 1e-6) == opened:
                return True
            time.sleep(0.002)  # the finger stays closed for a frame's grab at least
        return False

    try:
        while finger(False) and finger(True):
            shown = lab.scene.show(lab.scenes.moved)
            for _ in range(2):
                shown = frames.wait_newer(10, lambda i, s=shown: i.stamp > s).stamp
            lab.scene.show(lab.scenes.both)
    finally:
        board.close()


def _operator(lab: Lab, done: threading.Event, confirmed: list[str]) -> None:
    """The operator: before each nock clears the target to its older arrow and puts an arrow on
    the string, then confirms; confirms every other request as it comes."""
    key = lab.node.keys.learner_rpc()
    last = 0  # the last request confirmed
    while not done.is_set():
        request = rpc_call(lab.node, key, "status", {}, timeout=10).get("operator")
        if not request or request["request"] == last:
            done.wait(0.05)
            continue
        last = request["request"]
        if request["verb"] == "nock":
            lab.scene.show(lab.scenes.old)
        rpc_call(lab.node, key, "confirm", {"request": request["request"]}, timeout=10)
        confirmed.append(request["verb"])


def _start(node: Node, runs: Path) -> str:
    request = {"algo": "archer", "seed": 0, "rollouts": 1}
    return str(rpc_call(node, node.keys.learner_rpc(), "start", request, timeout=60)["session"])


def _request(node: Node) -> dict[str, Any]:
    """The operator's request the learner shows, once it shows one."""
    status: dict[str, Any] = {}

    def asked() -> bool:
        status.update(rpc_call(node, node.keys.learner_rpc(), "status", {}, timeout=10))
        return bool(status.get("operator"))

    until(asked, "the learner asking the operator", timeout=60)
    request: dict[str, Any] = status["operator"]
    return request


class _Hands:
    """The lab's hands around one session: the world, whose arrows land in the camera's frames
    once the finger opens, and the operator, who confirms what the learner asks (`confirmed`:
    the verbs, in order); each started by the test, both ended by `stop`."""

    def __init__(self, lab: Lab) -> None:
        frames = lab.node.subscribe(lab.node.keys.cam_frames(), Image)
        self.done = threading.Event()
        self.confirmed: list[str] = []
        self.world = threading.Thread(
            target=_arrows_land, args=(lab, frames, self.done), daemon=True
        )
        self.operator = threading.Thread(
            target=_operator, args=(lab, self.done, self.confirmed), daemon=True
        )

    def stop(self) -> None:
        self.done.set()
        self.world.join(timeout=60)
        self.operator.join(timeout=60)


def test_the_shot_with_a_finger_release_and_the_landing_from_the_camera(lab: Lab) -> None:
    node = lab.node
    config = LearnerServiceConfig(net=lab.net, runs=lab.tmp / "runs", start_wait=30)
    hands = _Hands(lab)
    with serving(learner_service.run, config):
        node.wait_alive(["learner"], timeout=30)
        rollouts = node.subscribe(node.keys.learner_rollouts(), Rollout, mode="fifo")
        hands.world.start()
        session = _start(node, config.runs)
        request = _request(node)  # the robot has no reset posture: the operator's hand
        assert request["verb"] == "reset" and "ready the robot" in request["message"]
        key = node.keys.learner_rpc()
        with pytest.raises(Exception, match="is not the one waiting"):
            rpc_call(node, key, "confirm", {"request": request["request"] + 1}, timeout=10)
        hands.operator.start()  # it confirms the reset, then the nock once the arrow is on
        final = follow(node, session, rollouts, lambda m: None)
        hands.stop()
    assert final["state"] == "finished" and final["rollouts"] == 1, final
    assert hands.confirmed == ["reset", "nock"]
    records = read_records(Path(final["journal"]))[0]
    (shot,) = [r for r in records if isinstance(r, DoneRecord)]
    assert math.dist(shot.r_m, NEW_R) < 0.01, shot  # the new arrow, never the older one
    assert shot.truth_r_m is None  # no ground truth is invented
    assert shot.timing is not None and shot.timing["detector_wait_s"] > 0
    assert abs(_finger() - OPEN) < 1e-6


def test_an_operator_who_never_confirms_stops_the_session_resumably(lab: Lab) -> None:
    node = lab.node
    runs = lab.tmp / "runs-absent"
    config = LearnerServiceConfig(net=lab.net, runs=runs, start_wait=30, operator_wait=1.0)
    with serving(learner_service.run, config):
        node.wait_alive(["learner"], timeout=30)
        rollouts = node.subscribe(node.keys.learner_rollouts(), Rollout, mode="fifo")
        session = _start(node, runs)
        final = follow(node, session, rollouts, lambda m: None)
    assert final["state"] == "stopped", final
    assert "the operator did not confirm the reset within 1 s" in final["cause"]
    records = read_records(Path(final["journal"]))[0]
    assert isinstance(records[-1], StoppedRecord) and records[-1].reason == "operator absent"
    assert not [r for r in records if isinstance(r, ProposedRecord | DoneRecord)]  # no shot


def test_an_arm_lost_mid_session_is_waited_for_and_the_session_goes_on(lab: Lab) -> None:
    node = lab.node
    runs = lab.tmp / "runs-lost"
    config = LearnerServiceConfig(net=lab.net, runs=runs, start_wait=30, service_wait=120)
    hands = _Hands(lab)
    with serving(learner_service.run, config):
        node.wait_alive(["learner"], timeout=30)
        rollouts = node.subscribe(node.keys.learner_rollouts(), Rollout, mode="fifo")
        hands.world.start()
        hands.operator.start()
        request = {"algo": "archer", "seed": 0, "rollouts": 3, "scenario": {"reset": False}}
        key = node.keys.learner_rpc()
        session = str(rpc_call(node, key, "start", request, timeout=60)["session"])
        seen: list[Rollout] = []
        until(
            lambda: any(r.record.kind == "done" for r in seen) or seen.append(rollouts.get(5)),
            "the first rollout done",
            timeout=120,
        )
        arm = lab.robots.procs[1]  # /fake/left_arm's yarpdev: killed, as a cable pulled out
        os.killpg(arm.pid, signal.SIGKILL)
        arm.wait()
        until(lambda: ROBOT not in node.alive(), "the robot missing", timeout=30)
        lab.robots._device(lab.tmp, "/fake/left_arm", FAKE["left_arm"])
        until(
            lambda: yarp.Network.exists("/fake/left_arm/stateExt:o", True),
            "the arm back",
            timeout=30,
        )
        board = Board("/fake/left_arm", "/test/lab/pose")
        try:
            board.pose(FAKE["left_arm"])
        finally:
            board.close()
        final = follow(node, session, rollouts, seen.append)
        hands.stop()
    assert final["state"] == "finished" and final["rollouts"] == 3, final
    records = read_records(Path(final["journal"]))[0]
    assert len([r for r in records if isinstance(r, DoneRecord)]) == 3
    said = (lab.tmp / "robot.log").read_text(errors="replace")
    assert "left_arm is lost" in said and "left_arm is back" in said
