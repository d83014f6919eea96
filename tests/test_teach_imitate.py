"""Teach, check, imitate as a user runs them: `archery up --shot whole`, then `archery demonstrate
--out d.json --teach`, `archery demonstrate --check d.json` and `archery imitate d.json`, each the
real CLI in its own process over a real router and MuJoCo at rtf 0. The recording holds the arms
at every joint-state period of simulated time (the robot's `getHistory`, whatever its rtf) and
its imitation grasps, nocks and releases the arrow; after that shot `--teach` names the reset it
needs, which then lets it teach again. Also, quickly: `--check` (and `imitate`) refuse a recording
too sparse to imitate in one line naming the rate, and the robot's history itself."""

from __future__ import annotations

import json
import re
import signal
import subprocess
import sys
import threading
from collections.abc import Callable, Iterator
from pathlib import Path

import msgspec
import numpy as np
import pytest

from archery.apps.demonstrate import main as demonstrate
from archery.apps.imitate import main as imitate
from archery.apps.teacher import Teacher
from archery.mesh.netflags import NetConfig
from archery.mesh.node import Node
from archery.mesh.router import free_tcp_endpoint
from archery.protocol.demonstration import MAX_DT, encode_demonstration, parse_demonstration
from archery.protocol.exit_status import BAD_INPUT, FAILURE, OK
from archery.protocol.messages import WorldEvent
from archery.protocol.robotspec import NOMINAL_THETA, STRING_ARM, home_of
from archery.services.controller.demonstration_file import SHIPPED_DEMONSTRATION
from archery.services.robot.history import StateHistory
from archery.sim.scene_config import SceneConfig
from archery.sim.world import WorldConfig
from tests.ros2_sdk import until
from tests.test_robot_service import Client, robot_threads

STATE_RATE = 50.0  # Hz of simulated time: the robot's default --state-rate
SHOT_ENDS = {"landed", "missed"}


def _cli(cwd: Path, *args: str, timeout: float = 300.0) -> subprocess.CompletedProcess[str]:
    """`archery ARGS` run from the folder `cwd`, as a user runs it in a shell there."""
    return subprocess.run(
        [sys.executable, "-m", "archery.apps.cli", *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=timeout,
        stdin=subprocess.DEVNULL,
    )


def _wait_for_line(proc: subprocess.Popen[str], text: str) -> None:
    """Read `proc`'s stdout until a line holds `text` (the test's timeout bounds the wait)."""
    assert proc.stdout is not None
    seen = ""
    for line in proc.stdout:
        seen += line
        if text in line:
            return
    raise AssertionError(f"archery up ended before {text!r}:\n{seen}")


class Events:
    """The robot's world events, as they come."""

    def __init__(self, node: Node) -> None:
        self._lock = threading.Lock()
        self.seen: list[WorldEvent] = []
        self._sub = node.subscribe(
            node.keys.world_events(), WorldEvent, mode="fifo", callback=self._add
        )

    def _add(self, msg: WorldEvent) -> None:
        with self._lock:
            self.seen.append(msg)

    def kinds(self, shot: int) -> list[str]:
        with self._lock:
            return [e.kind for e in self.seen if e.shot == shot]


@pytest.mark.slow
def test_teach_check_imitate_as_a_user_runs_them(tmp_path: Path) -> None:
    endpoint = free_tcp_endpoint()
    net = ("--connect", endpoint)
    folders = ["--logs", str(tmp_path / "logs"), "--runs", str(tmp_path / "runs")]
    command = ["up", "--shot", "whole", "--listen", endpoint, *folders]
    up = subprocess.Popen(
        [sys.executable, "-m", "archery.apps.cli", *command],
        cwd=tmp_path,
        stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        _wait_for_line(up, "all alive")
        with Node(None, NetConfig(connect=(endpoint,))) as node:
            events = Events(node)

            taught = _cli(tmp_path, "demonstrate", "--out", "d.json", "--teach", *net)
            assert taught.returncode == OK, taught.stderr
            summary = json.loads(taught.stdout)
            assert summary["events"][:3] == ["grasped", "nocked", "released"], summary
            assert summary["events"][3] in SHOT_ENDS, summary
            # every joint-state period of simulated time, although state:o is paced per wall s
            assert summary["samples"] >= summary["duration_s"] * STATE_RATE, summary
            demo = parse_demonstration((tmp_path / "d.json").read_bytes())
            intervals = np.diff([s.t for s in demo.samples])
            np.testing.assert_allclose(intervals, 1 / STATE_RATE, atol=1e-9)

            checked = _cli(tmp_path, "demonstrate", "--check", "d.json")
            assert checked.returncode == OK, checked.stderr
            assert json.loads(checked.stdout) == summary

            imitated = _cli(tmp_path, "imitate", "d.json", *net)
            assert imitated.returncode == OK, imitated.stderr
            release = json.loads(imitated.stdout)  # the release's reply: the arrow flew
            assert release["outcome"] in {"target", "outside_face", "ground"}, release
            assert release["flight_time"] > 0.05, release
            np.testing.assert_allclose(release["theta"], NOMINAL_THETA, atol=0.01)
            shot = release["shot"]
            kinds = until(
                lambda: (k := events.kinds(shot)) and SHOT_ENDS & set(k) and k,
                "the imitated shot's events",
            )
            assert kinds[:3] == ["grasped", "nocked", "released"], kinds  # grasp and nock held

            # after that shot the teacher does not plan from where the arms are: it names the
            # reset, nothing recorded
            again = _cli(tmp_path, "demonstrate", "--out", "again.json", "--teach", *net)
            assert again.returncode == FAILURE, again
            assert again.stderr.count("\n") == 1, again.stderr
            assert "not at its starting posture" in again.stderr, again.stderr
            assert not (tmp_path / "again.json").exists()
            advice = re.search(r"`archery (rpc [^`]+)`", again.stderr)
            assert advice is not None, again.stderr
            reset = _cli(tmp_path, *advice.group(1).split(), *net)
            assert reset.returncode == OK, reset.stderr
            retaught = _cli(tmp_path, "demonstrate", "--out", "again.json", "--teach", *net)
            assert retaught.returncode == OK, retaught.stderr
            assert json.loads(retaught.stdout)["samples"] == summary["samples"]  # rtf 0: alike
    finally:
        up.send_signal(signal.SIGINT)
        try:
            out, err = up.communicate(timeout=90)
        except subprocess.TimeoutExpired:
            up.kill()
            out, err = up.communicate()
    assert up.returncode == 0, err[-4000:]
    assert "all stopped cleanly" in out, out[-2000:]


def _thinned(every: int) -> bytes:
    """The shipped demonstration (50 Hz) with every `every`-th sample, and its last."""
    demo = parse_demonstration(SHIPPED_DEMONSTRATION.read_bytes())
    keep = list(range(0, len(demo.samples), every))
    if keep[-1] != len(demo.samples) - 1:
        keep.append(len(demo.samples) - 1)
    samples = [demo.samples[i] for i in keep]
    return encode_demonstration(msgspec.structs.replace(demo, samples=samples))


def test_check_refuses_a_recording_too_sparse_to_imitate(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    sparse = tmp_path / "sparse.json"
    sparse.write_bytes(_thinned(20))  # 2.5 Hz: 33 samples, as state:o gave at rtf 0
    refused = _cli(tmp_path, "demonstrate", "--check", str(sparse), timeout=60)
    assert refused.returncode == BAD_INPUT and refused.stdout == "", refused
    assert refused.stderr.count("\n") == 1, refused.stderr
    assert "too sparse to imitate: 0.400 s between samples" in refused.stderr, refused.stderr
    assert f"({1 / MAX_DT:g} Hz of simulated time)" in refused.stderr, refused.stderr
    assert "--state-rate" in refused.stderr, refused.stderr
    assert imitate([str(sparse)]) == BAD_INPUT  # refused before a robot is asked
    assert "too sparse to imitate" in capsys.readouterr().err
    dense = tmp_path / "dense.json"
    dense.write_bytes(_thinned(round(MAX_DT * STATE_RATE)))  # the sparsest that imitates
    assert _cli(tmp_path, "demonstrate", "--check", str(dense), timeout=60).returncode == OK


@pytest.fixture
def robot(net: NetConfig) -> Iterator[Callable[..., Client]]:
    with robot_threads(net, WorldConfig(scene=SceneConfig(meshes=False, shot="whole"))) as start:
        yield start


def test_teach_names_the_reset_a_robot_away_from_its_start_needs(
    robot: Callable[..., Client], net: NetConfig, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    client = robot()
    away = np.array(home_of(STRING_ARM)) + np.array([0.3, 0.2, 0.0, 0.2, 0.0, 0.0, 0.0])
    client.move({STRING_ARM: away})
    out = tmp_path / "d.json"
    flags = ["--connect", net.connect[0], "--robot", net.robot]
    assert demonstrate(["--out", str(out), "--teach", *flags]) == FAILURE
    said = [line for line in capsys.readouterr().err.splitlines() if "archery demonstrate" in line]
    assert len(said) == 1, said
    assert "the robot is not at its starting posture (right_arm 0.30 rad from home)" in said[0]
    assert f"reset it with `archery rpc {net.robot}/archery/rpc:i reset`" in said[0], said
    assert not out.exists()
    assert client.archery("status")["shot"] == 0  # nothing moved, no shot
    client.archery("reset")
    teacher = Teacher(client.node, timeout=20)
    try:
        teacher.check_start()  # as reset leaves it: the teacher starts
    finally:
        teacher.close()


def test_the_history_keeps_each_grid_point_once_for_its_span() -> None:
    history = StateHistory({"a": 1, "b": 2}, period=0.5, span=2.0)  # 5 rows
    for i in range(8):
        history.add(0.5 * i, np.array([i, 10 * i, 100 * i], dtype=float))
        history.add(0.5 * i, np.zeros(3))  # the same time again (at rest): not kept
    times, positions = history.since("b", 0.0)
    assert times == [1.5, 2.0, 2.5, 3.0, 3.5] and positions[0] == [30.0, 300.0]
    assert history.since("a", 3.0) == ([3.0, 3.5], [[6.0], [7.0]])
    history.clear()
    assert history.since("a", 0.0) == ([], [])
