"""`archery foxglove` against Foxglove's own client (`@foxglove/ws-protocol`, run with Node from
tests/foxglove_client) beside a real mesh (`archery up` on a free loopback port)."""

from __future__ import annotations

import base64
import hashlib
import json
import math
import re
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import mujoco
import numpy as np
import psutil
import pytest
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from foxglove_schemas_protobuf.ImageAnnotations_pb2 import ImageAnnotations
from foxglove_schemas_protobuf.JointStates_pb2 import JointStates
from foxglove_schemas_protobuf.Log_pb2 import Log
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from scipy.spatial.transform import Rotation

from archery.apps.foxglove.bridge import asset
from archery.apps.foxglove.channels import TOPICS
from archery.apps.foxglove.command import check_listen
from archery.apps.foxglove.marks import image_marks
from archery.apps.foxglove.operator import Operator
from archery.mesh.netflags import NetConfig
from archery.mesh.node import open_node
from archery.mesh.router import free_tcp_endpoint
from archery.protocol.errors import ConfigError
from archery.protocol.messages import Detection, JointState, WorldEvent, WorldState
from archery.protocol.parts import PARTS
from archery.protocol.robotspec import SERVICES
from archery.protocol.verbs.robot import ARCHERY_STATUS
from archery.sim.model_build import build_scene
from archery.sim.scene_config import TARGET_CAMERA, SceneConfig
from archery.sim.urdf import mesh_root, urdf_text
from tests.conftest import archery

CLIENT = Path(__file__).parent / "foxglove_client"
ROBOT = "fox"
pytestmark = pytest.mark.skipif(shutil.which("node") is None, reason="Node is not installed")


def _client(url: str, *args: str, timeout: float = 60.0) -> list[dict[str, Any]]:
    """Run Foxglove's client against `url`; its JSON lines."""
    if not (CLIENT / "node_modules" / "@foxglove" / "ws-protocol").is_dir():
        subprocess.run(["npm", "ci", "--no-audit", "--no-fund"], cwd=CLIENT, check=True)
    done = subprocess.run(
        ["node", str(CLIENT / "client.mjs"), url, *args, "--timeout", str(timeout)],
        capture_output=True,
        text=True,
        timeout=timeout + 30,
    )
    lines = [json.loads(line) for line in done.stdout.splitlines() if line.strip()]
    assert done.returncode == 0, (lines[-3:], done.stderr[-2000:])
    return lines


def _of(lines: list[dict[str, Any]], kind: str) -> list[Any]:
    return [line[kind] for line in lines if kind in line]


class Mesh:
    """`archery up` on a free port, a node on it and bridges beside it."""

    def __init__(self, tmp: Path) -> None:
        self.endpoint = free_tcp_endpoint()
        self.tmp = tmp
        self.up = subprocess.Popen(
            [sys.executable, "-m", "archery.apps.cli", "up", "--listen", self.endpoint,
             "--robot", ROBOT, "--logs", str(tmp / "logs"), "--runs", str(tmp / "runs")],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )  # fmt: skip
        net = NetConfig(connect=(self.endpoint,), robot=ROBOT)
        self.node = open_node(net, 60)
        self.node.wait_alive(SERVICES, timeout=120)
        self.bridges: list[subprocess.Popen[str]] = []

    def bridge(self, *extra: str) -> tuple[subprocess.Popen[str], str]:
        """An `archery foxglove` on a free port, once it serves; (process, its ws:// URL)."""
        proc = subprocess.Popen(
            [sys.executable, "-m", "archery.apps.cli", "foxglove", "--connect", self.endpoint,
             "--robot", ROBOT, "--port", "0", *extra],
            stdout=subprocess.PIPE,
            stderr=(self.tmp / f"bridge-{len(self.bridges)}.err").open("w"),
            text=True,
        )  # fmt: skip
        self.bridges.append(proc)
        assert proc.stdout is not None
        line = proc.stdout.readline()
        err = self.tmp / f"bridge-{len(self.bridges) - 1}.err"
        assert line.startswith("archery foxglove: serving"), (line, err.read_text())
        return proc, line.split(" on ", 1)[1].split()[0]

    def learn(self, rollouts: int) -> None:
        done = archery(
            "learn", "--connect", self.endpoint, "--robot", ROBOT, "--rollouts", str(rollouts),
            "--no-until-hit", "--seed", "3", "--quiet", timeout=300,
        )  # fmt: skip
        assert done.returncode == 0, done.stderr[-2000:]

    def close(self) -> None:
        for proc in self.bridges:
            proc.terminate()
            proc.communicate(timeout=30)
        self.node.close()
        self.up.terminate()
        self.up.wait(60)


def _client_while_learning(mesh: Mesh, url: str, *args: str) -> list[dict[str, Any]]:
    """Run Foxglove's client against `url` while the mesh learns, session after session, until
    the client has all it wants; its JSON lines."""
    lines: list[dict[str, Any]] = []
    failed: list[BaseException] = []

    def watch() -> None:
        try:
            lines.extend(_client(url, *args, timeout=120))
        except BaseException as exc:  # re-raised below, in the test's thread
            failed.append(exc)

    watcher = threading.Thread(target=watch)
    watcher.start()
    while watcher.is_alive():
        mesh.learn(1)
        watcher.join(timeout=0.1)
    if failed:
        raise failed[0]
    return lines


@pytest.fixture(scope="module")
def mesh(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Mesh]:
    running = Mesh(tmp_path_factory.mktemp("foxglove"))
    try:
        yield running
    finally:
        running.close()


def _compose(transforms: FrameTransforms, frame: str) -> np.ndarray:
    """`frame`'s position in `world` (m), composing the message's parent → child transforms."""
    parent = {t.child_frame_id: t for t in transforms.transforms}
    chain = []
    while frame != "world":
        chain.append(parent[frame])
        frame = parent[frame].parent_frame_id
    position, rotation = np.zeros(3), Rotation.identity()
    for t in reversed(chain):
        position = position + rotation.apply([t.translation.x, t.translation.y, t.translation.z])
        q = t.rotation
        rotation = rotation * Rotation.from_quat([q.x, q.y, q.z, q.w])
    return position


def test_a_client_sees_every_channel_and_decodes_a_message_on_each(mesh: Mesh) -> None:
    _, url = mesh.bridge()
    states: dict[int, JointState] = {}
    worlds: dict[int, WorldState] = {}
    subs = [
        mesh.node.subscribe(
            mesh.node.keys.state(part),
            JointState,
            mode="fifo",
            callback=lambda m: states.__setitem__(round(m.stamp * 1e9), m),
        )
        for part in PARTS
    ]
    subs.append(
        mesh.node.subscribe(
            mesh.node.keys.world_state(),
            WorldState,
            mode="fifo",
            callback=lambda m: worlds.__setitem__(round(m.stamp * 1e9), m),
        )
    )
    wants = [arg for topic in TOPICS for arg in ("--want", topic.name)]
    try:
        lines = _client_while_learning(mesh, url, *wants)
    finally:
        for sub in subs:
            sub.close()
    info = _of(lines, "serverInfo")[0]
    assert "read-only" in info["name"] and "services" not in info["capabilities"]
    advertised = {c["topic"]: c for c in _of(lines, "channels")[0]}
    for topic in TOPICS:
        assert advertised[topic.name]["schemaName"] == topic.schema
        assert advertised[topic.name]["encoding"] == ("protobuf" if topic.protobuf else "json")
    data = {m["topic"]: base64.b64decode(m["data"]) for m in _of(lines, "message")}
    assert set(data) == {topic.name for topic in TOPICS}

    joints = JointStates.FromString(data["/joint_states"])
    sent = states[joints.timestamp.seconds * 10**9 + joints.timestamp.nanos]
    assert [j.name for j in joints.joints] == list(sent.names)
    assert [j.position for j in joints.joints] == list(sent.position)

    transforms = FrameTransforms.FromString(data["/tf"])
    stamp = transforms.transforms[0].timestamp
    world = worlds[stamp.seconds * 10**9 + stamp.nanos]
    status = mesh.node.call_typed(mesh.node.keys.archery_rpc(), ARCHERY_STATUS)
    model = build_scene(SceneConfig.of(status.scene))
    sim = mujoco.MjData(model)
    sim.qpos[:] = world.qpos.to_numpy()
    mujoco.mj_kinematics(model, sim)
    for body in ("r_hand", "l_hand", "arrow"):
        if mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, body) < 0:
            continue
        expected = sim.body(body).xpos - sim.body(0).xpos
        assert np.linalg.norm(_compose(transforms, body) - expected) < 1e-3, body

    assert "<robot" in json.loads(data["/robot_description"])["data"]
    scene = SceneUpdate.FromString(data["/scene"])
    assert any(e.models for e in scene.entities) and len(scene.entities) > 10
    image = RawImage.FromString(data["/camera/image"])
    assert (image.width, image.height, image.encoding) == (1280, 720, "rgb8")
    assert len(image.data) == 1280 * 720 * 3
    marks = ImageAnnotations.FromString(data["/camera/annotations"])
    assert marks.texts and "target" in marks.texts[0].text
    rollout = json.loads(data["/learner/rollouts"])
    assert rollout["rollout"] >= 1 and math.isclose(
        rollout["distance"], math.hypot(*rollout["r"][:2]), rel_tol=1e-6
    )
    assert Log.FromString(data["/world/events"]).message
    services = json.loads(data["/mesh/services"])
    assert set(services["alive"]) >= set(SERVICES)


def test_an_operator_resets_the_world_and_a_read_only_server_refuses(mesh: Mesh) -> None:
    _, operator = mesh.bridge("--operator")
    events: list[WorldEvent] = []
    sub = mesh.node.subscribe(
        mesh.node.keys.world_events(), WorldEvent, mode="fifo", callback=events.append
    )
    try:
        lines = _client(operator, "--call", "/robot/reset", json.dumps({"seed": 5}))
        assert "operator" in _of(lines, "serverInfo")[0]["name"]
        assert set(_of(lines, "services")[0]) == {
            "/learner/status", "/learner/start", "/learner/stop", "/robot/reset",
        }  # fmt: skip
        reply = json.loads(_of(lines, "response")[0])
        assert reply["sim_time"] == 0.0
        status = mesh.node.call_typed(mesh.node.keys.archery_rpc(), ARCHERY_STATUS)
        assert status.seed == 5 and status.phase == "idle"
    finally:
        sub.close()
    assert any(event.kind == "reset" for event in events)

    # a malformed body: the client hears why, the server goes on
    bad = _client(operator, "--call", "/learner/start", json.dumps({"rollouts": -1}))
    assert "rollouts" in _of(bad, "failure")[0]
    bad = _client(operator, "--call", "/learner/status", "not json")
    assert "not JSON" in _of(bad, "failure")[0]

    _, viewer = mesh.bridge()
    refused = _client(viewer, "--call-unadvertised", "{}", "--want", "/mesh/services")
    assert not _of(refused, "services") and not _of(refused, "response")
    assert any(
        "service" in str(s).lower() for s in _of(refused, "status") + _of(refused, "failure")
    )


def test_the_wind_parameter_is_checked_and_set_through_the_robot(mesh: Mesh) -> None:
    _, url = mesh.bridge("--operator")
    lines = _client(url, "--set-wind", "1.5,0,-0.5")
    assert _of(lines, "parameters")[-1] == [
        {"name": "wind", "type": "float64_array", "value": [1.5, 0, -0.5]}
    ]
    for wrong, why in (("1,2", "3 numbers"), ("99,0,0", "within")):
        lines = _client(url, "--set-wind", wrong)
        assert any(why in s["message"] for s in _of(lines, "status")), lines
        assert _of(lines, "parameters")[-1][0]["value"] == [1.5, 0, -0.5]  # unchanged


def test_garbage_and_a_hundred_clients_leak_nothing(mesh: Mesh) -> None:
    proc, url = mesh.bridge("--max-clients", "128")
    host, port = url.removeprefix("ws://").rstrip("/").split(":")
    bridge = psutil.Process(proc.pid)
    _client(url, "--want", "/mesh/services", "--want", "/scene")
    before = bridge.num_threads()
    with socket.create_connection((host, int(port))) as raw:
        raw.sendall(b"\x00\xffGET nonsense\r\n\r\n" + bytes(range(256)))
    rss = []
    for _ in range(4):  # the allocator's pools grow to what 100 clients take, and stay…
        # (the camera's frames and the scene queued, up to 4 messages per client, are bounded and
        # measured by benchmarks/bench_foxglove_clients.py; here: what connections leave)
        _client(url, "--crowd", "100", "--crowd-skip", "/camera/image", "--crowd-skip", "/scene")
        rss.append(bridge.memory_info().rss)
    lines = _client(url, "--want", "/mesh/services", "--want", "/scene")
    assert {m["topic"] for m in _of(lines, "message")} == {"/mesh/services", "/scene"}
    deadline = time.monotonic() + 30  # the server's connection threads end as they close
    while bridge.num_threads() > before and time.monotonic() < deadline:
        time.sleep(0.2)
    assert bridge.num_threads() <= before
    assert max(rss[2:]) < max(rss[:2]) + (64 << 20), rss  # …where a leak would grow on
    assert proc.poll() is None


def test_where_it_cannot_listen_or_no_mesh_is_there(tmp_path: Path) -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        with pytest.raises(ConfigError, match="already in use"):
            check_listen("127.0.0.1", port)
        done = archery("foxglove", "--port", str(port))
        assert done.returncode == 2 and "already in use" in done.stderr
        assert len(done.stderr.strip().splitlines()) == 1
    done = archery("foxglove", "--host", "192.0.2.7", "--port", "0", "--insecure-network")
    assert done.returncode == 2 and "not an address of this machine" in done.stderr
    done = archery("foxglove", "--host", "192.0.2.7", "--port", "0")
    assert done.returncode == 2 and "or give --insecure-network" in done.stderr
    done = archery("foxglove", "--connect", free_tcp_endpoint(), "--port", "0", "--wait", "1")
    assert done.returncode == 1
    assert "archery foxglove: waiting up to 1 s for the router" in done.stderr


def test_the_layout_and_the_marks(tmp_path: Path) -> None:
    out = tmp_path / "layout.json"
    done = archery("foxglove", "--layout", str(out))
    assert done.returncode == 0, done.stderr
    text = out.read_text()
    for panel in ("ThreeDee", "Image", "Plot", "Log"):
        assert f'"panelType":"{panel}"' in text.replace(" ", "")
    assert archery("foxglove", "--layout", str(tmp_path / "x.txt")).returncode == 2

    detection = Detection(
        frame_stamp=12.5,
        status="ok",
        target_px=[640.0, 360.0],
        arrow_px=[650.0, 350.0],
        target_confidence=0.9,
        arrow_confidence=0.8,
        r_m=[0.01, 0.02],
        rings=[[640.0, 360.0, 100.0, 90.0, 10.0], [640.0, 360.0, 200.0, 180.0, 10.0]],
    )
    marks = ImageAnnotations.FromString(image_marks(detection))
    assert len(marks.points) == 2 and len(marks.circles) == 2
    assert (
        marks.circles[0].timestamp.seconds == 12 and marks.circles[0].timestamp.nanos == 500_000_000
    )
    xs = [p.x for p in marks.points[1].points]
    width = 2 * math.hypot(100 * math.cos(math.radians(10)), 90 * math.sin(math.radians(10)))
    assert max(xs) - min(xs) == pytest.approx(width, abs=0.5)  # axes 200 and 180 px, at 10°
    assert "r = (+0.010, +0.020) m" in marks.texts[0].text

    root = tmp_path / "share"
    (root / "meshes").mkdir(parents=True)
    (root / "meshes" / "a.stl").write_bytes(b"solid")
    (tmp_path / "secret").write_bytes(b"no")
    assert asset(root, "package://iCub/meshes/a.stl") == b"solid"
    assert asset(root, "package://iCub/../secret") is None
    assert asset(root, "file:///etc/passwd") is None


def test_the_wind_is_checked_before_the_robot_is_asked() -> None:
    operator = Operator.__new__(Operator)  # the checks run before any call
    for value, why in (
        ([1, 2], "3 numbers"),
        ([1, "a", 2], "3 numbers"),
        ([float("nan"), 0, 0], "within"),
        ([0, 0, 51], "within"),
    ):
        with pytest.raises(ValueError, match=why):
            operator.set_wind(value)


def test_up_serves_foxglove_beside_the_services(tmp_path: Path) -> None:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    up = subprocess.Popen(
        [sys.executable, "-m", "archery.apps.cli", "up", "--listen", free_tcp_endpoint(), "--robot",
         "foxup", "--logs", str(tmp_path / "logs"), "--runs", str(tmp_path / "runs"),
         "--foxglove", str(port)],
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
    )  # fmt: skip
    try:
        assert up.stdout is not None
        lines = [up.stdout.readline() for _ in range(3)]
        serving = f"archery up: serving Foxglove on ws://127.0.0.1:{port}"
        assert any(line.startswith(serving) for line in lines), lines
        seen = _client(f"ws://127.0.0.1:{port}", "--want", "/mesh/services")
        assert "foxup" in _of(seen, "serverInfo")[0]["name"]
    finally:
        up.send_signal(2)  # Ctrl-C
        up.communicate(timeout=60)
    assert up.returncode == 0


def test_jpeg_frames_decode_to_the_camera_size(mesh: Mesh) -> None:
    _, url = mesh.bridge("--jpeg")
    lines = _client_while_learning(mesh, url, "--want", "/camera/image")
    channel = next(c for c in _of(lines, "channels")[0] if c["topic"] == "/camera/image")
    assert channel["schemaName"] == "foxglove.CompressedImage"
    image = CompressedImage.FromString(base64.b64decode(_of(lines, "message")[0]["data"]))
    assert image.format == "jpeg"
    pixels = cv2.imdecode(np.frombuffer(image.data, np.uint8), cv2.IMREAD_COLOR)
    assert pixels.shape == (720, 1280, 3)


def test_in_secure_mode_only_the_operator_identity_operates(tmp_path: Path) -> None:
    deployment = tmp_path / "secrets"
    made = archery("keys", "init", str(deployment))
    assert made.returncode == 0, made.stderr
    done = archery(
        "foxglove", "--secure", str(deployment), "--identity", "viewer", "--operator",
        "--connect", "tls/127.0.0.1:9", "--port", "0",
    )  # fmt: skip
    assert done.returncode == 2
    assert "--operator in secure mode runs as identity 'operator', not 'viewer'" in done.stderr


def test_every_mesh_the_description_names_is_served_at_once_while_frames_stream(
    mesh: Mesh,
) -> None:
    """The 3D panel's burst: a client subscribed to the streams asks for every mesh of the
    robot description at once (39; the SDK's server dropped a client after ~4)."""
    proc, url = mesh.bridge()
    streams = ("/robot_description", "/tf", "/joint_states", "/camera/image")
    wants = [arg for topic in streams for arg in ("--want", topic)]
    lines = _client_while_learning(mesh, url, *wants, "--assets")
    named = set(re.findall(r"package://iCub/[^\"'<>\s]+", urdf_text()))
    answers = {a["uri"]: a for a in _of(lines, "asset")}
    assert set(answers) == named and len(named) >= 39
    for uri, answer in answers.items():
        data = (mesh_root() / uri.removeprefix("package://iCub/")).read_bytes()
        assert answer["status"] == "success", answer
        assert (answer["bytes"], answer["sha256"]) == (len(data), hashlib.sha256(data).hexdigest())
    fetched = _of(lines, "fetched")[0]
    assert fetched["assets"] == len(named) and fetched["seconds"] < 30, fetched
    assert not [s for s in _of(lines, "status") if "backlog" in s["message"]]
    assert proc.poll() is None
    err = (mesh.tmp / f"bridge-{mesh.bridges.index(proc)}.err").read_text()
    assert "dropped" not in err, err[-2000:]


def test_a_client_that_stops_reading_is_dropped_and_logged_once(mesh: Mesh) -> None:
    proc, url = mesh.bridge()
    err = mesh.tmp / f"bridge-{mesh.bridges.index(proc)}.err"
    stalled = subprocess.Popen(
        ["node", str(CLIENT / "client.mjs"), url, "--stall", "1", "--want", "/camera/image",
         "--want", "/tf"],
        stdout=subprocess.PIPE,
        text=True,
    )  # fmt: skip
    try:
        assert stalled.stdout is not None
        port = json.loads(stalled.stdout.readline())["ports"][0]
        name = f"127.0.0.1:{port}: dropped"
        deadline = time.monotonic() + 240
        while name not in err.read_text() and time.monotonic() < deadline:
            mesh.learn(1)  # the camera sends 10 frames/s while the view moves (1/s at rest)
        # the server goes on serving; the dropped client is not named again
        lines = _client(url, "--want", "/mesh/services")
        assert _of(lines, "message")
    finally:
        stalled.send_signal(signal.SIGTERM)
        stalled.communicate(timeout=30)
    drops = [line for line in err.read_text().splitlines() if name in line]
    assert len(drops) == 1 and "read nothing" in drops[0], err.read_text()[-2000:]
    assert proc.poll() is None


def test_the_camera_is_on_tf_with_its_calibration(mesh: Mesh) -> None:
    _, url = mesh.bridge()
    lines = _client_while_learning(
        mesh, url, "--want", "/tf", "--want", "/camera/calibration", "--want", "/camera/image"
    )
    data = {m["topic"]: base64.b64decode(m["data"]) for m in _of(lines, "message")}
    status = mesh.node.call_typed(mesh.node.keys.archery_rpc(), ARCHERY_STATUS)
    model = build_scene(SceneConfig.of(status.scene))
    sim = mujoco.MjData(model)
    mujoco.mj_forward(model, sim)
    cam = model.camera(TARGET_CAMERA).id

    transforms = FrameTransforms.FromString(data["/tf"])
    camera = [t for t in transforms.transforms if t.child_frame_id == "target_camera"]
    assert len(camera) == 1 and camera[0].parent_frame_id == "world"
    t, q = camera[0].translation, camera[0].rotation
    assert np.allclose([t.x, t.y, t.z], sim.cam_xpos[cam], atol=1e-6)
    optical = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()
    # MuJoCo's camera looks along its -z, y up; the optical frame along +z, y down
    mujoco_axes = sim.cam_xmat[cam].reshape(3, 3)
    assert np.allclose(optical[:, 2], -mujoco_axes[:, 2], atol=1e-6)
    assert np.allclose(optical[:, 1], -mujoco_axes[:, 1], atol=1e-6)
    assert np.allclose(optical[:, 0], mujoco_axes[:, 0], atol=1e-6)
    target = sim.geom("target_ring_0").xpos - sim.cam_xpos[cam]
    assert optical[:, 2] @ target / np.linalg.norm(target) > 0.99  # it looks at the target

    calibration = CameraCalibration.FromString(data["/camera/calibration"])
    image = RawImage.FromString(data["/camera/image"])
    assert calibration.frame_id == image.frame_id == "target_camera"
    assert (calibration.width, calibration.height) == (image.width, image.height) == (1280, 720)
    fy = 360 / math.tan(math.radians(model.cam_fovy[cam]) / 2)
    assert list(calibration.K) == pytest.approx([fy, 0, 640, 0, fy, 360, 0, 0, 1])
    assert list(calibration.P) == pytest.approx([fy, 0, 640, 0, 0, fy, 360, 0, 0, 0, 1, 0])
    assert list(calibration.R) == pytest.approx(list(np.eye(3).reshape(-1)))
    assert calibration.distortion_model == "plumb_bob" and not any(calibration.D)
