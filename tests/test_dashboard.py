"""`archery dashboard`: its JSON endpoints (urllib) and the page in the system's headless
Chromium (driven by Playwright: screenshots at rollouts 1, 10 and 60, what each panel shows,
measured in the page), against a fake learner (Rollout messages, `status`), a fake detector
(`frame`: a PNG) and the real camera service (the scene view of the whole robot)."""

from __future__ import annotations

import dataclasses
import itertools
import json
import math
import re
import shutil
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

from archery.apps.dashboard.server import Dashboard, bind
from archery.apps.dashboard.watch import SCENE_INTEREST, MeshWatch
from archery.mesh.netflags import NetConfig
from archery.mesh.node import Node
from archery.mesh.publisher import Publisher
from archery.protocol.journal_records import (
    AbortedRecord,
    DoneRecord,
    ProposedRecord,
    RolloutRecord,
)
from archery.protocol.messages import Array, Image, JointState, Rollout, WorldState
from archery.protocol.verbs.camera import CAMERA_VERBS, SceneReply
from archery.protocol.verbs.detector import DETECTOR_VERBS, FrameReply
from archery.protocol.verbs.learner import LEARNER_VERBS, LearnerStatusReply
from tests.rpc import some_verbs

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
    with (
        fake_learner(net, "s1", 10, png=PNG) as rollouts,
        Dashboard(net, bind("127.0.0.1", 0)) as dash,
    ):
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
        assert get(dash.url + "api/nosuch")[0] == 404
        assert get(dash.url + "api/scene.jpg")[0] == 404  # no page asked for the scene view
        # a robot name the keys refuse: one clear error, and no watch of it
        status, ctype, body = get(dash.url + "api/state?robot=no%20such")
        assert (status, ctype) == (400, "application/json")
        assert "invalid robot name 'no such'" in json.loads(body)["error"]
        robots = json.loads(get(dash.url + "api/robots")[2])
        assert robots == {"default": net.robot, "robots": [net.robot]}
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


ROUND = re.compile(r"^-?\d+$")


def _round_steps(labels: list[str]) -> None:
    """Tick labels are whole numbers a constant step of 1, 2 or 5 × 10^k apart."""
    assert labels and all(ROUND.match(t) for t in labels), labels
    values = [int(t) for t in labels]
    steps = {b - a for a, b in itertools.pairwise(values)}
    assert len(steps) <= 1, values
    for step in steps:
        mantissa = step / 10 ** math.floor(math.log10(step))
        assert mantissa in (1, 2, 5), values


def _shot(k: int) -> tuple[list[float], bool]:
    """Rollout k's r (m), spiralling in to the centre, and whether it hits."""
    radius = 0.30 * math.exp(-k / 14) + 0.004
    r = [radius * math.cos(1.3 * k), radius * math.sin(1.3 * k)]
    return r, math.hypot(*r) < 0.05


def _done(session: str, k: int) -> DoneRecord:
    r, hit = _shot(k)
    theta = [0.17 + 0.001 * k, 0.002 * k, -0.01]
    return DoneRecord(
        session=session,
        index=k,
        rollout=k,
        theta=theta,
        r_m=r,
        distance_m=math.hypot(*r),
        hit=hit,
    )


def _frame_png() -> bytes:
    """A 1280×720 frame with an overlay text as the detector draws it."""
    image = np.full((720, 1280, 3), (60, 140, 60), np.uint8)
    cv2.circle(image, (640, 360), 200, (0, 220, 255), -1)
    cv2.putText(image, "target", (600, 365), cv2.FONT_HERSHEY_SIMPLEX, 1.0, (0, 0, 0), 2)
    ok, data = cv2.imencode(".png", image)
    assert ok
    return data.tobytes()


@contextmanager
def fake_learner(
    net: NetConfig, session: str, budget: int, png: bytes | None = None
) -> Iterator[Publisher[Rollout]]:
    """A learner that publishes what is put on the yielded publisher and answers `status`
    (running `session` of `budget` rollouts), and a detector whose `frame` is `png` (default a
    1280×720 frame), both alive under `net.robot`."""
    png = png or _frame_png()
    with Node("learner", net) as learner, Node("detector", net) as detector:
        status = LearnerStatusReply(state="running", session=session, rollouts=0, budget=budget)
        learner.serve(
            learner.keys.learner_rpc(), some_verbs(LEARNER_VERBS, {"status": lambda _: status})
        )
        rollouts = learner.publisher(learner.keys.learner_rollouts(), Rollout, lossless=True)
        learner.ready()
        detector.serve(
            detector.keys.detector_rpc(),
            some_verbs(DETECTOR_VERBS, {"frame": lambda _: FrameReply(png=png, status="ok")}),
        )
        detector.ready()
        yield rollouts


@contextmanager
def real_camera(net: NetConfig) -> Iterator[None]:
    """The camera service, rendering the scene view of the robot's initial pose (a world state
    as the robot publishes it)."""
    from archery.services.camera.config import CameraConfig
    from archery.services.camera.service import run
    from archery.sim.model_build import build_scene
    from archery.sim.scene import ScenePhysics
    from archery.sim.scene_config import SceneConfig
    from tests.conftest import serving

    physics = ScenePhysics(build_scene(SceneConfig(meshes=False)))
    physics.reset()
    physics.forward()
    state = WorldState(qpos=Array.from_numpy(physics.qpos()), phase="idle", sim_time=0.5)
    with (
        serving(run, CameraConfig(net=net, rate=1.0, robot_timeout=0.3)),
        Node("robot", net) as robot,
    ):
        world = robot.publisher(robot.keys.world_state(), WorldState, lossless=True)
        robot.ready()
        assert world.wait_matched(30), "the camera does not follow the world states"
        world.put(state)
        yield


@contextmanager
def browser() -> Iterator[Any]:
    """A page of a headless Chromium (the system's) driven by Playwright, 1280×900; the test is
    skipped where the system has none (`.ci/run` installs it)."""
    if shutil.which(CHROMIUM) is None:
        pytest.skip(f"no Chromium at {CHROMIUM} (.ci/run installs it)")
    sync_api = pytest.importorskip("playwright.sync_api")
    with sync_api.sync_playwright() as playwright:
        chromium = playwright.chromium.launch(
            executable_path=CHROMIUM, args=["--no-sandbox", "--disable-gpu"]
        )
        try:
            yield chromium.new_page(viewport={"width": 1280, "height": 900})
        finally:
            chromium.close()


# What each panel shows, measured in the page (CSS px and each SVG's own units).
PANELS_JS = """() => {
  const box = (e) => { const r = e.getBoundingClientRect();
    return {x: r.x, y: r.y, w: r.width, h: r.height}; };
  const frame = document.getElementById("frame");
  const caption = document.getElementById("frame-caption");
  const scene = document.getElementById("scene");
  const plot = document.querySelector("#curve .plot-area").getBBox();
  const texts = (id) => [...document.querySelectorAll(`#${id} text`)].map((t) => {
    const b = t.getBBox(); return {text: t.textContent, cls: t.getAttribute("class"),
      x: b.x, y: b.y, w: b.width, h: b.height}; });
  const points = [...document.querySelectorAll("#curve .distance-point")].map((c) => ({
    x: +c.getAttribute("cx"), y: +c.getAttribute("cy"), r: +c.getAttribute("r")}));
  const bar = document.querySelector("#colourbar .colourbar").getBBox();
  const impacts = [...document.querySelectorAll("#face .impact")].map((c) => ({
    index: +c.dataset.index, fill: c.getAttribute("fill")}));
  const cells = [...document.querySelectorAll("main > section")].map(box);
  return {
    viewport: window.innerWidth,
    frame: {...box(frame), natural: frame.naturalWidth, rollout: frame.dataset.rollout},
    caption: {...box(caption), text: caption.textContent, hidden: caption.hidden,
      font: parseFloat(getComputedStyle(caption).fontSize)},
    scene: {...box(scene), natural: scene.naturalWidth,
      note: document.getElementById("scene-note").textContent},
    plot: {x: plot.x, y: plot.y, w: plot.width, h: plot.height},
    curveTexts: texts("curve"), faceTexts: texts("face"), barTexts: texts("colourbar"),
    bar: {x: bar.x, y: bar.y, w: bar.width, h: bar.height},
    points, impacts, cells,
    robots: [...document.querySelectorAll("#robot-select option")].map((o) => o.value),
    robot: document.getElementById("robot").textContent,
    session: document.getElementById("session").textContent,
  };
}"""


def _apart(a: dict[str, float], b: dict[str, float]) -> bool:
    """Whether two boxes {x, y, w, h} do not overlap."""
    return (
        a["x"] + a["w"] <= b["x"]
        or b["x"] + b["w"] <= a["x"]
        or (a["y"] + a["h"] <= b["y"] or b["y"] + b["h"] <= a["y"])
    )


def _check_panels(page: Any, n: int, budget: int) -> dict[str, Any]:
    """What the page shows after rollout `n`, checked panel by panel."""
    shown = page.evaluate(PANELS_JS)
    width = shown["viewport"]
    # the frame of rollout n at full width, its caption readable over it
    frame, caption = shown["frame"], shown["caption"]
    assert frame["natural"] == 1280 and frame["rollout"] == str(n)
    assert frame["w"] >= 0.9 * width, (frame, width)
    assert not caption["hidden"] and caption["font"] >= 16
    assert caption["text"].startswith(f"rollout {n} · θ (") and "‖r‖" in caption["text"]
    assert caption["y"] >= frame["y"] and caption["y"] + caption["h"] <= frame["y"] + frame["h"]
    assert caption["w"] >= 0.9 * frame["w"]
    # the scene view: the camera's render of the whole robot
    scene = shown["scene"]
    assert scene["natural"] == 640 and scene["w"] >= 300, scene
    assert "side camera" in scene["note"]
    # the face: one impact per rollout, coloured by rollout on the colour bar's scale
    impacts = shown["impacts"]
    assert [i["index"] for i in impacts] == list(range(1, n + 1))
    if n > 1:
        assert impacts[0]["fill"] != impacts[-1]["fill"]
    assert not shown["faceTexts"]  # no label on the face: the colour bar tells the order
    bar_labels = [t["text"] for t in shown["barTexts"] if t["cls"] == "colour-tick"]
    _round_steps(bar_labels)
    assert int(bar_labels[-1]) <= budget and int(bar_labels[-1]) > budget / 2
    for text in shown["barTexts"]:
        assert _apart(text, shown["bar"]), text
    # the curve: round ticks, every label outside the plot area, one point per rollout
    texts = shown["curveTexts"]
    _round_steps([t["text"] for t in texts if t["cls"] == "y-tick"])
    _round_steps([t["text"] for t in texts if t["cls"] == "x-tick"])
    assert any(t["cls"] == "hit-label" and t["text"] == "5 cm ring" for t in texts)
    for text in texts:
        assert _apart(text, shown["plot"]), text
    assert len(shown["points"]) == n
    for text in texts:
        for p in shown["points"]:
            disc = {"x": p["x"] - p["r"], "y": p["y"] - p["r"], "w": 2 * p["r"], "h": 2 * p["r"]}
            assert _apart(text, disc), (text, p)
    # no empty grid cell: the panels tile the page's two columns
    cells = shown["cells"]
    assert len(cells) == 6 and all(c["w"] > 0 and c["h"] > 0 for c in cells)
    return shown


def _wait_rollout(page: Any, n: int) -> None:
    page.wait_for_function(
        """n => {
          const f = document.getElementById("frame"), s = document.getElementById("scene");
          return f.dataset.rollout === String(n) && f.complete && f.naturalWidth > 0
            && s.complete && s.naturalWidth > 0
            && document.querySelectorAll("#face .impact").length === n;
        }""",
        arg=n,
        timeout=90_000,
    )


@pytest.mark.slow
@pytest.mark.skipif(
    shutil.which(CHROMIUM) is None, reason=f"no Chromium at {CHROMIUM} (.ci/run installs it)"
)
def test_the_page_at_rollouts_1_10_and_60(
    net: NetConfig, tmp_path: Path, record_property: Callable[[str, object], None]
) -> None:
    """Screenshots at rollouts 1, 10 and 60 (printed and attached as test properties), and what
    each panel shows then."""
    budget = 60
    with (
        fake_learner(net, "s1", budget) as rollouts,
        real_camera(net),
        Dashboard(net, bind("127.0.0.1", 0)) as dash,
        browser() as page,
    ):
        assert rollouts.wait_matched(30), "the dashboard does not subscribe to the rollouts"
        page.goto(dash.url)
        published = 0
        for n in (1, 10, 60):
            while published < n:
                published += 1
                rollouts.put(Rollout(record=_done("s1", published)))
            _wait_rollout(page, n)
            shot = tmp_path / f"dashboard-rollout-{n:02d}.png"
            page.screenshot(path=str(shot), full_page=True)
            print(f"screenshot at rollout {n}: {shot}")
            record_property(f"screenshot_rollout_{n}", str(shot))
            assert shot.stat().st_size > 50_000
            _check_panels(page, n, budget)
        html = page.content()
    for name in ("learner", "detector", "camera", "robot"):
        assert f'data-service="{name}" data-alive="true"' in html, html
    assert 'data-service="controller" data-alive="false"' in html
    assert f'data-key="{net.robot}/learner/rollout:o"' in html
    assert 'class="ok"' in html  # the last poll succeeded


@pytest.mark.slow
@pytest.mark.skipif(
    shutil.which(CHROMIUM) is None, reason=f"no Chromium at {CHROMIUM} (.ci/run installs it)"
)
def test_the_robot_selector_switches_between_the_robots_of_a_fleet(net: NetConfig) -> None:
    other = dataclasses.replace(net, robot=net.robot + "b")
    with (
        fake_learner(net, "first", 20) as first,
        fake_learner(other, "second", 20) as second,
        Dashboard(net, bind("127.0.0.1", 0)) as dash,
        browser() as page,
    ):
        assert first.wait_matched(30)
        first.put(Rollout(record=_done("first", 1)))
        page.goto(dash.url)
        page.wait_for_function(
            "n => document.querySelectorAll('#robot-select option').length === n",
            arg=2,
            timeout=60_000,
        )
        options = page.eval_on_selector_all("#robot-select option", "os => os.map(o => o.value)")
        assert options == sorted([net.robot, other.robot])
        assert page.input_value("#robot-select") == net.robot
        page.wait_for_function(
            "() => document.getElementById('session').textContent === 'session first'",
            timeout=30_000,
        )
        page.select_option("#robot-select", other.robot)
        assert second.wait_matched(30), "the dashboard does not follow the second robot"
        for k in (1, 2):
            second.put(Rollout(record=_done("second", k)))
        page.wait_for_function(
            """r => document.getElementById('robot').textContent === r
              && document.getElementById('session').textContent === 'session second'
              && document.querySelectorAll('#face .impact').length === 2""",
            arg=other.robot,
            timeout=30_000,
        )


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


def test_the_frame_is_fetched_after_every_rollout(net: NetConfig) -> None:
    with fake_learner(net, "s1", 10) as rollouts, Node(None, net) as node:
        watch = MeshWatch(node)
        try:
            assert rollouts.wait_matched(30)
            for k in range(1, 6):
                rollouts.put(Rollout(record=_done("s1", k)))
                deadline = time.monotonic() + 30
                while watch.snapshot()["frame"]["rollout"] != k:
                    assert time.monotonic() < deadline, watch.snapshot()["frame"]
                    time.sleep(0.02)
            assert watch.frame()[1] >= 5
        finally:
            watch.close()


def test_the_scene_view_is_asked_for_only_while_a_page_wants_it(net: NetConfig) -> None:
    calls: list[float] = []
    jpeg = cv2.imencode(".jpg", np.zeros((36, 64, 3), np.uint8))[1].tobytes()

    def scene(_: object) -> SceneReply:
        calls.append(time.monotonic())
        image = Image(width=64, height=36, encoding="jpeg", data=jpeg, sim_time=1.0)
        return SceneReply(status="ok", image=image, period=0.2, renders=1, render_ms=1.0)

    with Node("camera", net) as camera, Node(None, net) as node:
        camera.serve(camera.keys.cam_rpc(), some_verbs(CAMERA_VERBS, {"scene": scene}))
        camera.ready()
        node.wait_alive(["camera"], timeout=30)
        watch = MeshWatch(node, status_every=0.1)
        try:
            deadline = time.monotonic() + 2.0  # the status polls run; nobody wants the scene
            while time.monotonic() < deadline:
                time.sleep(0.1)
            assert not calls and watch.snapshot()["scene"]["status"] == "off"
            watch.want_scene()  # a page shows the panel
            deadline = time.monotonic() + 30
            while watch.scene()[0] != jpeg:
                assert time.monotonic() < deadline
                time.sleep(0.02)
            assert watch.snapshot()["scene"] | {"version": 1} == {
                "version": 1,
                "status": "ok",
                "error": "",
                "sim_time": 1.0,
                "width": 64,
                "height": 36,
            }
            # nobody asks again: the calls stop once SCENE_INTEREST s have passed
            deadline = time.monotonic() + SCENE_INTEREST + 30
            while watch.snapshot()["scene"]["status"] != "off":
                assert time.monotonic() < deadline
                time.sleep(0.05)
            stopped = len(calls)
            assert stopped >= 2  # at the camera's period while wanted
            assert all(b - a >= 0.19 for a, b in itertools.pairwise(calls))
            settle = time.monotonic() + 1.0
            while time.monotonic() < settle:
                time.sleep(0.1)
            assert len(calls) == stopped
        finally:
            watch.close()
