"""`archery dashboard`: its JSON endpoint (urllib) and the page in a real headless Chromium,
against a fake learner (Rollout messages, `status`) and a fake detector (`frame`: a PNG)."""

from __future__ import annotations

import json
import math
import re
import shutil
import subprocess
import tempfile
import threading
import time
import urllib.error
import urllib.request
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from apps.dashboard.server import Dashboard, bind
from apps.dashboard.watch import MeshWatch
from mesh.netflags import NetConfig
from mesh.node import Node
from mesh.publisher import Publisher
from mesh.router import free_tcp_endpoint
from protocol.journal_records import AbortedRecord, DoneRecord, ProposedRecord, RolloutRecord
from protocol.messages import Image, JointState, Rollout
from protocol.verbs.detector import DETECTOR_VERBS, FrameReply
from protocol.verbs.learner import LEARNER_VERBS, LearnerStatusReply
from tests.rpc import some_verbs
from tests.spawn import spawn

CHROMIUM = "/usr/bin/chromium"
# (r_m, status): two measured rollouts, one aborted, a hit last
SHOTS = [
    ([0.12, -0.08], "done"),
    ([0.0, 0.0], "aborted"),
    ([0.06, 0.03], "done"),
    ([0.01, -0.02], "done"),
]


def _png() -> bytes:
    image = np.zeros((60, 80, 3), np.uint8)
    image[:, :, 1] = 160
    cv2.circle(image, (40, 30), 20, (0, 0, 255), -1)
    ok, data = cv2.imencode(".png", image)
    assert ok
    return data.tobytes()


PNG = _png()


@contextmanager
def fake_services(net: NetConfig) -> Iterator[Publisher[Rollout]]:
    """A fake learner (its rollout publisher is yielded; `status` answers) and a fake detector
    (`frame` answers with PNG), both alive."""
    with Node("learner", net) as learner, Node("detector", net) as detector:
        learner.serve(
            learner.keys.learner_rpc(),
            some_verbs(
                LEARNER_VERBS,
                {"status": lambda _: LearnerStatusReply(state="running", session="s1", rollouts=3)},
            ),
        )
        rollouts = learner.publisher(learner.keys.learner_rollouts(), Rollout, lossless=True)
        learner.ready()
        detector.serve(
            detector.keys.detector_rpc(),
            some_verbs(DETECTOR_VERBS, {"frame": lambda _: FrameReply(png=PNG, status="ok")}),
        )
        detector.ready()
        yield rollouts


def publish_shots(rollouts: Publisher[Rollout]) -> None:
    assert rollouts.wait_matched(30), "the dashboard does not subscribe to the rollouts"
    rollouts.put(Rollout(record=ProposedRecord(session="s1", index=1, theta=[0.1, 0.0, 0.0])))
    for k, (r, status) in enumerate(SHOTS, start=1):
        theta = [0.1, 0.02 * k, 0.0]
        record: RolloutRecord
        if status == "done":
            distance = math.hypot(*r)
            record = DoneRecord(
                session="s1",
                index=k,
                rollout=k,
                theta=theta,
                r_m=r,
                distance_m=distance,
                hit=distance < 0.05,
            )
        else:
            record = AbortedRecord(
                session="s1", index=k, theta=theta, code="no_arrow", cause="", retry_theta=theta
            )
        rollouts.put(Rollout(record=record))


def get(url: str) -> tuple[int, str, bytes]:
    try:
        with urllib.request.urlopen(url, timeout=10) as response:
            return response.status, response.headers["Content-Type"], response.read()
    except urllib.error.HTTPError as exc:
        return exc.code, exc.headers["Content-Type"], exc.read()


def wait_state(url: str, ready: Callable[[dict[str, Any]], bool], timeout: float = 30) -> dict:
    """The dashboard's JSON once `ready(state)` holds (AssertionError after `timeout` s)."""
    deadline = time.monotonic() + timeout
    while True:
        state = json.loads(get(url + "api/state")[2])
        if ready(state):
            return state
        assert time.monotonic() < deadline, state
        time.sleep(0.05)


def settled(state: dict[str, Any]) -> bool:
    alive = {s["name"] for s in state["services"] if s["alive"]}
    return (
        len(state["rollouts"]) == len(SHOTS)
        and state["frame"]["version"] >= 1
        and {"learner", "detector"} <= alive
        and state["learner"].get("state") == "running"
    )


def test_state_endpoint_and_files(net: NetConfig) -> None:
    with fake_services(net) as rollouts, Dashboard(net, bind("127.0.0.1", 0)) as dash:
        publish_shots(rollouts)
        state = wait_state(dash.url, settled)
        assert state["robot"] == net.robot and state["session"] == "s1"
        assert [r["status"] for r in state["rollouts"]] == [s for _, s in SHOTS]
        assert state["rollouts"][0]["distance_m"] == pytest.approx(math.hypot(0.12, -0.08))
        assert state["rollouts"][1]["distance_m"] is None
        assert [r["hit"] for r in state["rollouts"]] == [False, False, False, True]
        services = {s["name"]: s["alive"] for s in state["services"]}
        assert services["robot"] is False and services["camera"] is False
        assert [ring["radius_m"] for ring in state["face"]] == [0.05, 0.10, 0.15, 0.20, 0.25]
        assert state["hit_radius_m"] == 0.05
        keys = {r["key"] for r in state["rates"]}
        assert f"{net.robot}/learner/rollout:o" in keys
        status, ctype, body = get(dash.url + "api/frame.png")
        assert (status, ctype, body) == (200, "image/png", PNG)
        status, ctype, body = get(dash.url)
        assert status == 200 and ctype.startswith("text/html") and b"dashboard.js" in body
        for name in ("dashboard.js", "dashboard.css"):
            assert get(dash.url + "static/" + name)[0] == 200
        assert get(dash.url + "static/..%2Fserver.py")[0] == 404
        assert get(dash.url + "static/server.py")[0] == 404
        assert get(dash.url + "nosuch")[0] == 404
        # a new session starts a fresh face
        done = DoneRecord(
            session="s2",
            index=1,
            rollout=1,
            theta=[0, 0, 0],
            r_m=[0, 0.2],
            distance_m=0.2,
            hit=False,
        )
        rollouts.put(Rollout(record=done))
        state = wait_state(dash.url, lambda s: s["session"] == "s2")
        assert len(state["rollouts"]) == 1


def test_no_frame_yet_is_404(net: NetConfig) -> None:
    with Dashboard(net, bind("127.0.0.1", 0)) as dash:
        assert get(dash.url + "api/frame.png")[0] == 404
        deadline = time.monotonic() + 30  # until the first status and frame calls gave up
        while True:
            state = json.loads(get(dash.url + "api/state")[2])
            if "state" in state["learner"] and state["frame"]["error"]:
                break
            assert time.monotonic() < deadline, state
            time.sleep(0.1)
        assert state["learner"]["state"] == "unreachable" and state["rollouts"] == []
        assert "detector/rpc:i" in state["frame"]["error"]


def _chromium(url: str, profile: Path, *extra: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [
            CHROMIUM,
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--disable-quic",
            "--no-first-run",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
            f"--user-data-dir={profile}",
            "--virtual-time-budget=5000",
            *extra,
            url,
        ],
        capture_output=True,
        text=True,
        timeout=120,
        stdin=subprocess.DEVNULL,
    )


@pytest.mark.slow
@pytest.mark.skipif(
    shutil.which(CHROMIUM) is None, reason=f"no Chromium at {CHROMIUM} (.ci/run installs it)"
)
def test_the_page_in_a_headless_browser(net: NetConfig, tmp_path: Path) -> None:
    flags = ["--connect", net.connect[0], "--robot", net.robot]
    with fake_services(net) as rollouts:
        port = free_tcp_endpoint().rsplit(":", 1)[1]
        proc = spawn("dashboard", "--port", port, *flags, ready="archery dashboard: serving")
        url = f"http://127.0.0.1:{port}/"
        try:
            publish_shots(rollouts)
            wait_state(url, settled)
            with tempfile.TemporaryDirectory() as profile:
                dom = _chromium(url, Path(profile), "--dump-dom")
            assert dom.returncode == 0, dom.stderr
            html = dom.stdout
            shot = tmp_path / "dashboard.png"
            with tempfile.TemporaryDirectory() as profile:
                out = _chromium(
                    url, Path(profile), f"--screenshot={shot}", "--window-size=1280,900"
                )
            assert out.returncode == 0 and shot.stat().st_size > 10_000, out.stderr
        finally:
            proc.terminate()
            proc.wait(timeout=30)
    for name in ("learner", "detector"):
        assert f'data-service="{name}" data-alive="true"' in html, html
    for name in ("robot", "camera", "controller"):
        assert f'data-service="{name}" data-alive="false"' in html
    assert html.count('class="impact"') == 3  # the aborted rollout has no impact
    assert html.count('class="ring"') == 5
    assert html.count('class="distance-point"') == 3
    assert re.search(r'id="latest-distance">2\.2 cm<', html), html  # ‖(0.01, -0.02)‖
    assert re.search(r'<img id="frame"[^>]*src="/api/frame.png\?v=\d+"', html), html
    assert 'id="hit-count">1<' in html
    assert f'data-key="{net.robot}/learner/rollout:o"' in html
    assert 'class="ok"' in html  # the last poll succeeded


def _rates(watch: MeshWatch, ready: Callable[[dict[str, float | None]], bool]) -> dict[str, Any]:
    """The watch's rates {key: Hz} once `ready` holds for them (30 s at most)."""
    deadline = time.monotonic() + 30
    while True:
        rates = {r["key"]: r["hz"] for r in watch.snapshot()["rates"]}
        if ready(rates):
            return rates
        assert time.monotonic() < deadline, rates
        time.sleep(0.05)


def test_rates_come_from_the_publishers_counts_not_from_subscribing(net: NetConfig) -> None:
    # a subscriber would make the camera render and the router forward every message
    stop = threading.Event()
    with Node("camera", net) as camera, Node("robot", net) as robot, Node(None, net) as node:
        frames = camera.publisher(camera.keys.cam_frames(), Image)
        states = robot.publisher(robot.keys.state("torso"), JointState)
        camera.ready()
        robot.ready()
        pixels = np.zeros((2, 2, 3), np.uint8)
        state = JointState(part="torso", names=["a"], position=[0.0], velocity=[0.0])

        robot_lock, robot_gone = threading.Lock(), threading.Event()

        def publish() -> None:
            while not stop.wait(0.01):
                frames.put(Image.from_numpy(pixels))
                with robot_lock:
                    if not robot_gone.is_set():
                        states.put(state)

        thread = threading.Thread(target=publish, daemon=True)
        thread.start()
        watch = MeshWatch(node, status_every=0.1)
        try:
            both = (camera.keys.cam_frames(), robot.keys.state("torso"))
            rates = _rates(watch, lambda r: all((r.get(k) or 0) > 0 for k in both))
            assert all(rates[k] < 200 for k in both), rates  # ~100 Hz each
            assert not frames.matching() and not states.matching()
            with robot_lock:
                robot_gone.set()
                robot.close()  # its publisher is gone: its rate drops to 0
            _rates(watch, lambda r: r.get(robot.keys.state("torso")) == 0)
        finally:
            stop.set()
            thread.join(5)
            watch.close()
