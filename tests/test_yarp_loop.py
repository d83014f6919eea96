"""The whole learning loop through YARP only: mesh A runs the simulated iCub and its camera
behind `archery yarp --operator` (the robot as a YARP robot, /icubSim, on YARP's own loopback
`yarpserver`); mesh B, another router, runs `archery robot --body yarp --remote /icubSim
--archery-rpc /icubSim/archery/rpc:i`, `archery camera --source yarp:/icubSim/cam/target:o`,
the detector, the controller and the learner, which knows mesh A only through YARP's ports.
ARCHER hits the 5 cm ring within its usual rollouts (posture shot); and again on mesh C, whose
YARP body ignores the robot's landing (`--landing camera`): the detector tells it from the
frames alone (a new arrow, then a still picture), no ground truth reaches the journal."""

from __future__ import annotations

import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from archery.apps.learn.follow import follow
from archery.apps.up.launch_config import SERVICES
from archery.apps.up.launcher import Launcher
from archery.mesh.node import Node
from archery.mesh.robot_client import RobotClient
from archery.mesh.router import free_tcp_endpoint
from archery.protocol.journal_records import DoneRecord
from archery.protocol.messages import Rollout
from archery.protocol.parts import PARTS
from archery.protocol.robotspec import TOLERANCES
from archery.protocol.verbs.camera import CALIBRATION
from archery.services.detector.calibration import fit_from_marks, parse_pixels
from archery.services.learner.journal import read_records
from tests.rpc import rpc_call
from tests.yarp_setup import YarpSetup

yarp = pytest.importorskip("yarp", reason="YARP's bindings: `make setup` builds and installs them")

pytestmark = pytest.mark.slow

PREFIX = "/icubSim"


class Loop:
    """YARP's name server, mesh A (robot, camera, the operator bridge) and mesh B."""

    def __init__(self, tmp: Path) -> None:
        self.tmp = tmp
        self.meshes: list[Launcher] = []
        self.bridge: subprocess.Popen[str] | None = None
        self.yarp: YarpSetup | None = None
        try:
            self._begin()
        except BaseException:
            self.close()
            raise

    def _begin(self) -> None:
        tmp = self.tmp
        self.yarp = YarpSetup(yarp, tmp / "yarp")  # before the launchers: their env names it
        signal.signal(signal.SIGCHLD, signal.SIG_DFL)  # YARP's handler reaps children
        a = Launcher(free_tcp_endpoint(), "meshA", tmp / "logs-a")
        self.meshes.append(a)
        a.up(120, services=["robot", "camera"])
        model = self._calibrate(a)
        argv = [sys.executable, "-m", "archery.apps.cli", "yarp", "--connect", a.endpoint,
                "--robot", "meshA", "--yarp-server", f"127.0.0.1:{self.yarp.port}",
                "--prefix", PREFIX, "--operator"]  # fmt: skip
        log = tmp / "bridge.log"
        with log.open("w") as err:
            self.bridge = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=err, text=True)
        assert self.bridge.stdout is not None
        for line in self.bridge.stdout:
            if line.startswith("archery yarp: on YARP"):
                break
        else:
            raise AssertionError(f"the bridge ended: {log.read_text()[-2000:]}")
        b = Launcher(
            free_tcp_endpoint(),
            "meshB",
            tmp / "logs-b",
            {
                "robot": ["--body", "yarp", "--remote", PREFIX,
                          "--archery-rpc", f"{PREFIX}/archery/rpc:i"],
                "camera": ["--source", f"yarp:{PREFIX}/cam/target:o"],
                "detector": ["--model", str(model)],
                "learner": ["--runs", str(tmp / "runs"), "--service-wait", "60"],
            },
        )  # fmt: skip
        self.meshes.append(b)
        b.up(180)
        self.b = b
        c = Launcher(free_tcp_endpoint(), "meshC", tmp / "logs-c", self._services(model, "c"))
        self.meshes.append(c)
        c.up(180)
        self.c = c

    def _services(self, model: Path, name: str) -> dict[str, list[str]]:
        """Mesh C's flags: mesh B's, the robot's landing ignored."""
        return {
            "robot": ["--body", "yarp", "--remote", PREFIX, "--archery-rpc",
                      f"{PREFIX}/archery/rpc:i", "--landing", "camera"],
            "camera": ["--source", f"yarp:{PREFIX}/cam/target:o"],
            "detector": ["--model", str(model)],
            "learner": ["--runs", str(self.tmp / f"runs-{name}"), "--service-wait", "60"],
        }  # fmt: skip

    def _calibrate(self, a: Launcher) -> Path:
        """The detector's colour model, fitted as a lab fits it for a real camera: on a frame
        of that camera with the target's and the arrow's pixels marked (here the simulated
        camera's own calibration frame and marks, asked on mesh A), saved to a file for the
        detector of mesh B (`--model`), whose YARP camera gives no marks."""
        with Node(None, a.net) as node:
            marks = node.call_typed(node.keys.cam_rpc(), CALIBRATION, timeout=60)
        fitted = fit_from_marks(marks.image.to_numpy(), parse_pixels(marks.pixels, "marks"))
        path = self.tmp / "colour-model.json"
        fitted.model.save(path)
        return path

    def close(self) -> None:
        for mesh in reversed(self.meshes):
            mesh.stop_all()
        if self.bridge is not None and self.bridge.poll() is None:
            self.bridge.terminate()
            try:
                self.bridge.communicate(timeout=60)
            except subprocess.TimeoutExpired:
                self.bridge.kill()
                self.bridge.communicate()
        if self.yarp is not None:
            self.yarp.close()


@pytest.fixture(scope="module")
def loop(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Loop]:
    running = Loop(tmp_path_factory.mktemp("yarploop"))
    try:
        yield running
    finally:
        running.close()


def _session(mesh: Launcher) -> dict[str, Any]:
    """An ARCHER session (seed 0, at most 15 rollouts) on `mesh`, followed to its end."""
    with Node(None, mesh.net) as node:
        rollouts = node.subscribe(node.keys.learner_rollouts(), Rollout, mode="fifo")
        node.wait_alive(SERVICES, timeout=60)
        request = {"algo": "archer", "seed": 0, "rollouts": 15}
        session = str(
            rpc_call(node, node.keys.learner_rpc(), "start", request, timeout=60)["session"]
        )
        final: dict[str, Any] = follow(node, session, rollouts, lambda m: None)
    return final


def test_archer_hits_the_5cm_ring_through_yarp(loop: Loop) -> None:
    final = _session(loop.b)
    assert final["state"] == "finished" and final["ended"] == "hit", final
    assert final["hit_at"] <= 15 and final["final_distance_m"] < 0.05
    done = [r for r in read_records(Path(final["journal"]))[0] if isinstance(r, DoneRecord)]
    assert len(done) == final["rollouts"]
    # The truth: mesh A's world events, forwarded by the YARP body from their bottles (a
    # rollout's event later than the learner's 1 s wait is not journaled). Each measurement is
    # of its own shot's arrow, never of a frame from before its landing.
    told = [r for r in done if r.truth_r_m is not None]
    assert told, "no world event came through YARP"
    for record in told:
        assert record.r_m is not None and record.truth_r_m is not None
        assert np.linalg.norm(np.subtract(record.r_m, record.truth_r_m)) < 0.02, record


def test_archer_hits_with_the_landing_told_by_the_camera_alone(loop: Loop) -> None:
    final = _session(loop.c)
    assert final["state"] == "finished" and final["ended"] == "hit", final
    assert final["hit_at"] <= 15 and final["final_distance_m"] < 0.05
    records = read_records(Path(str(final["journal"])))[0]
    done = [r for r in records if isinstance(r, DoneRecord)]
    assert len(done) == final["rollouts"]
    for record in done:  # the detector waited for each landing; no truth was told
        assert record.truth_r_m is None
        assert record.timing is not None and record.timing["detector_wait_s"] > 0


def test_after_a_reset_through_yarp_the_newest_state_is_of_after_it(loop: Loop) -> None:
    """A mover that plans from the robot at rest right after a reset (the controller's first
    posture of a session) sees the robot where the reset put it, never the states of before it
    that a state stream still carries for a moment."""
    with Node(None, loop.b.net) as node, Node(None, loop.meshes[0].net) as mesh_a:
        client, truth = RobotClient(node, timeout=10), RobotClient(mesh_a, timeout=10)
        try:
            _, upper = client.limits("left_arm")
            k = PARTS["left_arm"].index("l_elbow")
            client.reset()
            home = truth.joints("left_arm").position[k]
            target = home + 0.4 if home + 0.4 < upper[k] - 0.05 else home - 0.4
            for _ in range(3):
                with client.claim(["left_arm"], "probe", speeds=1.0) as held:
                    assert client.move({"l_elbow": target}, claim=held, until="rest").reached
                client.reset()  # the elbow back home, 0.4 rad from where the states had it
                rested = client.rested(5.0)
                assert rested is not None
                assert rested["l_elbow"] == pytest.approx(home, abs=TOLERANCES["passing"])
        finally:
            client.close()
            truth.close()
