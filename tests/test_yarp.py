"""`archery yarp` against YARP's own code: YARP 3.5's `remote_controlboard` device (a
`PolyDriver`), `BufferedPortImageRgb`, `RpcClient` and the `yarp` command-line tool, through
YARP's own `yarpserver`, beside a real mesh (`archery up`). YARP is configured for loopback
only, as its users configure it: `YARP_IP`, and a configuration folder of the test's own."""

from __future__ import annotations

import math
import os
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from archery.apps.yarp.network import stop_group
from archery.mesh.netflags import NetConfig
from archery.mesh.node import Node, open_node
from archery.mesh.router import free_tcp_endpoint
from archery.protocol.journal_records import DoneRecord
from archery.protocol.messages import JointState, WorldEvent
from archery.protocol.parts import PARTS
from archery.protocol.robotspec import SERVICES
from archery.services.learner.journal import read_records
from tests.conftest import archery
from tests.ros2_sdk import until
from tests.yarp_setup import YarpSetup

yarp = pytest.importorskip("yarp", reason="YARP's bindings: `make setup` builds and installs them")

ROBOT = "yarpbot"
ARM = "left_arm"
ELBOW = 3  # the arm's joint the tests move (index in YARP order)


class World:
    """`archery up`, YARP's own name server, a read-only and an operator bridge on it."""

    def __init__(self, tmp: Path) -> None:
        self.tmp = tmp
        self.endpoint = free_tcp_endpoint()
        self.procs: list[subprocess.Popen[str]] = []
        self._node: Node | None = None
        self.yarp: YarpSetup | None = None
        try:
            self._begin(tmp)
        except BaseException:
            self.close()  # what started before the failure stops with it
            raise

    def _begin(self, tmp: Path) -> None:
        self.up = self._start(
            [sys.executable, "-m", "archery.apps.cli", "up", "--listen", self.endpoint,
             "--robot", ROBOT, "--logs", str(tmp / "logs"), "--runs", str(tmp / "runs")],
            "archery up: all alive",
        )  # fmt: skip
        self.net = NetConfig(connect=(self.endpoint,), robot=ROBOT)
        self._node = open_node(self.net, 60)
        self._node.wait_alive(SERVICES, timeout=120)
        # YARP's own name server, on loopback, in a configuration folder of the test's
        self.yarp = YarpSetup(yarp, tmp / "yarp")
        self.yarp_port, self.env = self.yarp.port, self.yarp.env
        bridge = [sys.executable, "-m", "archery.apps.cli", "yarp", "--connect", self.endpoint,
                  "--robot", ROBOT, "--yarp-server", f"127.0.0.1:{self.yarp_port}"]  # fmt: skip
        self.reader = self._start([*bridge, "--prefix", "/icubSim"], "archery yarp: on YARP")
        self.operator = self._start(
            [*bridge, "--prefix", "/op", "--operator"], "archery yarp: on YARP"
        )

    def _start(self, argv: list[str], ready: str) -> subprocess.Popen[str]:
        log = self.tmp / f"{argv[3]}-{len(self.procs)}.log"
        with log.open("w") as err:
            proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=err, text=True)
        self.procs.append(proc)
        assert proc.stdout is not None
        for line in proc.stdout:
            if line.startswith(ready):
                return proc
        tail = log.read_text().splitlines()[-5:]
        raise AssertionError(f"{argv[3]} ended before {ready!r}: status {proc.wait()}: {tail}")

    def yarp_cli(self, *args: str, stdin: str = "", timeout: float = 30) -> str:
        """YARP's own `yarp` tool, as a user configured for this name server runs it."""
        out = subprocess.run(
            [str(Path(sys.executable).parent / "yarp"), *args],
            input=stdin,
            capture_output=True,
            text=True,
            env=self.env,
            timeout=timeout,
        )
        return out.stdout

    def arm(self) -> JointState:
        sub = self.node.subscribe(self.node.keys.state(ARM), JointState)
        try:
            return sub.wait_newer(10)
        finally:
            self.node.unsubscribe(sub)

    @property
    def node(self) -> Node:
        assert self._node is not None
        return self._node

    def close(self) -> None:
        if self._node is not None:
            self._node.close()
        for proc in reversed(self.procs):
            if proc.poll() is None:
                proc.terminate()
                try:
                    proc.communicate(timeout=60)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.communicate()
        if self.yarp is not None:
            self.yarp.close()


@pytest.fixture(scope="module")
def world(tmp_path_factory: pytest.TempPathFactory) -> Iterator[World]:
    running = World(tmp_path_factory.mktemp("yarp"))
    try:
        yield running
    finally:
        running.close()


class Board:
    """YARP's `remote_controlboard` on a bridge's arm."""

    def __init__(self, remote: str, local: str) -> None:
        options = yarp.Property()
        options.put("device", "remote_controlboard")
        options.put("remote", remote)
        options.put("local", local)
        self.driver = yarp.PolyDriver(options)
        assert self.driver.isValid(), f"remote_controlboard did not open {remote}"
        self.encoders = self.driver.viewIEncoders()
        self.position = self.driver.viewIPositionControl()
        self.limits = self.driver.viewIControlLimits()
        self.axes = self.encoders.getAxes()

    def read(self) -> list[float]:
        values = yarp.Vector(self.axes)
        until(lambda: self.encoders.getEncoders(values.data()), "the encoders", timeout=10)
        return [values[i] for i in range(self.axes)]

    def close(self) -> None:
        self.driver.close()


def test_remote_controlboard_reads_the_encoders_and_a_read_only_bridge_moves_nothing(
    world: World,
) -> None:
    board = Board("/icubSim/left_arm", "/test/ro/left_arm")
    try:
        assert board.axes == len(PARTS[ARM])
        state = world.arm()
        np.testing.assert_allclose(board.read(), np.degrees(state.position), atol=0.5)
        low, high = yarp.DVector(1), yarp.DVector(1)
        assert board.limits.getLimits(ELBOW, low, high)
        assert low[0] < math.degrees(state.position[ELBOW]) < high[0]
        before = world.arm().position[ELBOW]
        assert not board.position.positionMove(ELBOW, math.degrees(before) + 10)
        time.sleep(0.3)  # a move would have started by now: the robot steps at 1 kHz
        assert abs(world.arm().position[ELBOW] - before) < 1e-3
    finally:
        board.close()


def test_remote_controlboard_moves_a_joint_the_mesh_sees_in_radians(world: World) -> None:
    board = Board("/op/left_arm", "/test/op/left_arm")
    try:
        start = world.arm().position[ELBOW]
        goal = math.degrees(start) + (15 if start < 1.0 else -15)
        assert board.position.positionMove(ELBOW, goal)
        until(
            lambda: abs(world.arm().position[ELBOW] - math.radians(goal)) < math.radians(0.5),
            "the elbow at its goal on the mesh's state:o",
            timeout=20,
        )
        done = yarp.BVector(1)
        until(lambda: board.position.checkMotionDone(done) and done[0], "motion done", timeout=20)
        assert board.read()[ELBOW] == pytest.approx(goal, abs=0.5)
        # outside the limits: refused, nothing moves
        low, high = yarp.DVector(1), yarp.DVector(1)
        board.limits.getLimits(ELBOW, low, high)
        assert not board.position.positionMove(ELBOW, high[0] + 20)
        assert world.arm().position[ELBOW] == pytest.approx(math.radians(goal), abs=0.01)
    finally:
        board.close()


def test_an_image_port_reads_the_target_camera(world: World) -> None:
    port = yarp.BufferedPortImageRgb()
    assert port.open("/test/frames:i")
    try:
        assert yarp.Network.connect("/icubSim/cam/target:o", "/test/frames:i")
        image = until(lambda: port.read(False), "a frame", timeout=30)
        assert (image.width(), image.height()) == (1280, 720)
        pixels = np.zeros((720, 1280, 3), dtype=np.uint8)
        view = yarp.ImageRgb()
        view.resize(1280, 720)  # YARP copies into the external pixels of an allocated image
        view.setExternal(pixels, 1280, 720)
        view.copy(image)
        assert pixels.std() > 10  # a rendered scene, not a blank frame
    finally:
        port.close()


def _rpc(name: str, *words: str) -> Any:
    client = yarp.RpcClient()
    assert client.open(f"/test/rpc{time.monotonic_ns()}")
    try:
        assert client.addOutput(name)
        request, reply = yarp.Bottle(), yarp.Bottle()
        for word in words:
            request.addString(word)
        assert client.write(request, reply)
        return [reply.get(i).toString() for i in range(reply.size())]
    finally:
        client.close()


def test_an_rpc_client_nocks_and_releases_and_the_landing_is_on_the_mesh(world: World) -> None:
    assert _rpc("/icubSim/archery/rpc:i", "nock")[:2] == ["fail", "read_only"]
    events = world.node.subscribe(world.node.keys.world_events(), WorldEvent, mode="fifo")
    try:
        assert _rpc("/op/archery/rpc:i", "reset")[0] == "ok"
        assert _rpc("/op/archery/rpc:i", "nock")[0] == "ok"
        released = _rpc("/op/archery/rpc:i", "release")
        assert released[0] == "ok", released
        assert "outcome" in released
        deadline = time.monotonic() + 30
        while (event := events.get(max(0.0, deadline - time.monotonic()))).kind not in (
            "landed",
            "missed",
        ):
            pass
        assert event.kind in ("landed", "missed")
        assert _rpc("/op/archery/rpc:i", "fly")[:2] == ["fail", "bad_request"]
    finally:
        world.node.unsubscribe(events)


def test_yarp_cli_lists_reads_and_drives_the_ports(world: World) -> None:
    names = world.yarp_cli("name", "list")
    for part in PARTS:
        for leaf in ("rpc:i", "command:i", "state:o", "stateExt:o"):
            assert f"/icubSim/{part}/{leaf}" in names
    assert "/icubSim/archery/rpc:i" in names
    # `yarp read` prints the state stream: 7 angles in degrees (its own log lines start "[")
    reader = subprocess.Popen(
        [
            str(Path(sys.executable).parent / "yarp"),
            "read",
            "/test/cli:i",
            "/icubSim/left_arm/state:o",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
        env=world.env,
        start_new_session=True,  # the tool's launcher and the tool: stopped together
    )
    try:
        assert reader.stdout is not None
        line = next(line for line in reader.stdout if not line.startswith("["))
        angles = [float(x) for x in line.split()]
        assert len(angles) == len(PARTS[ARM])
        assert angles[ELBOW] == pytest.approx(math.degrees(world.arm().position[ELBOW]), abs=1.0)
    finally:
        stop_group(reader)
    out = world.yarp_cli("rpc", "/op/archery/rpc:i", stdin="status\n")
    assert "Response: ok" in out and "shot" in out


def _raw_rpc(port: str, text: str) -> str:
    """A control board request written as YARP's text bottle, its reply as text."""
    client = yarp.RpcClient()
    assert client.open(f"/test/raw{time.monotonic_ns()}")
    try:
        assert client.addOutput(port)
        request, reply = yarp.Bottle(), yarp.Bottle()
        request.fromString(text)
        assert client.write(request, reply)
        return str(reply.toString())
    finally:
        client.close()


def test_bad_requests_get_a_fail_bottle_and_nothing_moves(world: World) -> None:
    before = world.arm().position[ELBOW]
    for text in (
        "[get]",
        "hello world",
        "[get] [xyzw]",
        "[set] [pos] 99 10.0",
        "[set] [pos] 3 nan",
        "[set] [pos] 3 inf",
        "[set] [pos] 3",
        "[set] [poss] (1.0 2.0)",
        "[set] [posg] 2 (3) (10.0)",
        "[set] [pos] 3 1000.0",
        "[set] [vel] 3 -5.0",
        "[walk] [pos] 3 10.0",
    ):
        assert _raw_rpc("/op/left_arm/rpc:i", text) == "[fail]", text
    time.sleep(0.2)
    assert world.arm().position[ELBOW] == pytest.approx(before, abs=1e-3)
    assert _raw_rpc("/op/left_arm/rpc:i", "[get] [axes]").startswith("[is] [axes] 7")


def _address(name: str) -> tuple[str, int]:
    contact = yarp.Network.queryName(name)
    return contact.getHost(), contact.getPort()


def test_garbage_and_a_hundred_connections_leave_the_bridge_serving(world: World) -> None:
    host, port = _address("/op/left_arm/rpc:i")
    with socket.create_connection((host, port), timeout=5) as raw:
        raw.sendall(b"CONNECT /garbage\n")
        raw.sendall(os.urandom(4096))
    sockets = []
    opened = threading.Barrier(100, timeout=30)

    def connect() -> None:
        s = socket.create_connection((host, port), timeout=10)
        sockets.append(s)
        opened.wait()

    threads = [threading.Thread(target=connect) for _ in range(100)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout=60)
    assert len(sockets) == 100
    for s in sockets:
        s.close()
    assert _raw_rpc("/op/left_arm/rpc:i", "[get] [axes]").startswith("[is] [axes] 7")
    board = Board("/icubSim/right_arm", "/test/after/right_arm")
    try:
        assert len(board.read()) == len(PARTS["right_arm"])
    finally:
        board.close()


def test_a_name_server_that_answers_nonsense_is_an_error_not_a_hang(world: World) -> None:
    listener = socket.socket()
    listener.bind(("127.0.0.1", 0))
    listener.listen(8)
    port = listener.getsockname()[1]
    stop = threading.Event()

    def nonsense() -> None:
        listener.settimeout(0.2)
        while not stop.is_set():
            try:
                conn, _ = listener.accept()
            except TimeoutError:
                continue
            with conn:
                conn.sendall(b"\x00\xffnot a name server\n" * 8)

    thread = threading.Thread(target=nonsense, daemon=True)
    thread.start()
    try:
        out = archery(
            "yarp", "--connect", world.endpoint, "--robot", ROBOT, "--wait", "3",
            "--yarp-server", f"127.0.0.1:{port}", timeout=120,
        )  # fmt: skip
        assert out.returncode != 0
        assert out.stderr.strip().splitlines()[-1].startswith("archery yarp: ")
    finally:
        stop.set()
        thread.join()
        listener.close()


def test_bad_flags_are_bad_input() -> None:
    for flags, why in (
        (["--yarp-server", "nowhere"], "HOST:PORT"),
        (["--yarp-ip", "loopback"], "give an address"),
        (["--prefix", "icubSim"], "a YARP name"),
    ):
        out = archery("yarp", *flags)
        assert out.returncode == 2, out.stderr
        assert why in out.stderr


def test_archery_up_yarp_serves_the_robot_on_the_name_server(world: World, tmp_path: Path) -> None:
    up = subprocess.Popen(
        [sys.executable, "-m", "archery.apps.cli", "up", "--listen", free_tcp_endpoint(),
         "--robot", "upbot", "--logs", str(tmp_path / "logs"), "--runs", str(tmp_path / "runs"),
         "--yarp", f"127.0.0.1:{world.yarp_port}"],
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
    )  # fmt: skip
    try:
        assert up.stdout is not None
        said = next(line for line in up.stdout if line.startswith("archery up: on YARP"))
        assert "as /upbot (read-only)" in said and str(world.yarp_port) in said
        names = world.yarp_cli("name", "list")
        assert "/upbot/left_arm/stateExt:o" in names and "/upbot/archery/rpc:i" in names
    finally:
        up.terminate()
        up.communicate(timeout=120)
    assert "/upbot/left_arm/stateExt:o" not in world.yarp_cli("name", "list")


def _session(endpoint: str, runs: Path) -> list[tuple[list[float], list[float]]]:
    """One 4-rollout ARCHER session of seed 5 on `endpoint`'s robot: (θ, r) of each rollout."""
    before = set(runs.iterdir()) if runs.exists() else set()
    out = archery(
        "learn", "--connect", endpoint, "--robot", "besidebot", "--seed", "5", "--rollouts", "4",
        "--no-until-hit", "--quiet", "--no-film", timeout=300,
    )  # fmt: skip
    assert out.returncode == 0, out.stderr
    (folder,) = set(runs.iterdir()) - before
    done = [r for r in read_records(folder / "journal.jsonl")[0] if isinstance(r, DoneRecord)]
    return [(list(r.theta), list(r.r_m)) for r in done]


def test_beside_a_session_a_reader_sees_every_state_and_the_session_is_unchanged(
    world: World, tmp_path: Path
) -> None:
    endpoint = free_tcp_endpoint()
    up = subprocess.Popen(
        [sys.executable, "-m", "archery.apps.cli", "up", "--listen", endpoint, "--robot",
         "besidebot", "--logs", str(tmp_path / "logs"), "--runs", str(tmp_path / "runs")],
        stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
    )  # fmt: skip
    bridge = None
    try:
        assert up.stdout is not None
        next(line for line in up.stdout if line.startswith("archery up: all alive"))
        alone = _session(endpoint, tmp_path / "runs")
        bridge = subprocess.Popen(
            [sys.executable, "-m", "archery.apps.cli", "yarp", "--connect", endpoint, "--robot",
             "besidebot", "--yarp-server", f"127.0.0.1:{world.yarp_port}"],
            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
        )  # fmt: skip
        assert bridge.stdout is not None
        next(line for line in bridge.stdout if line.startswith("archery yarp: on YARP"))
        node = open_node(NetConfig(connect=(endpoint,), robot="besidebot"), 30)
        counts = {"mesh": 0, "yarp": 0}
        counting = threading.Event()

        def on_mesh(_: JointState) -> None:
            if counting.is_set():
                counts["mesh"] += 1

        sub = node.subscribe(
            node.keys.state("right_arm"), JointState, mode="fifo", callback=on_mesh
        )
        port = yarp.BufferedPortVector()
        port.setStrict(True)  # every state, as a logger reads them (not only the newest)
        assert port.open("/test/beside:i")
        assert yarp.Network.connect("/besidebot/right_arm/state:o", "/test/beside:i")
        stop = threading.Event()
        moved: list[list[float]] = []

        def on_yarp() -> None:
            while not stop.is_set():
                vector = port.read(True)
                if vector is not None and counting.is_set():
                    counts["yarp"] += 1
                    moved.append([vector[i] for i in range(vector.size())])

        reader = threading.Thread(target=on_yarp, daemon=True)
        reader.start()
        counting.set()
        watched = _session(endpoint, tmp_path / "runs")
        time.sleep(0.5)  # the last states through both paths
        counting.clear()
        stop.set()
        port.interrupt()
        reader.join(timeout=10)
        port.close()
        node.unsubscribe(sub)
        node.close()
        assert watched == alone  # the same seed, the same rollouts, with the bridge or without
        assert counts["mesh"] > 50
        assert counts["yarp"] >= 0.95 * counts["mesh"], counts
        spread = np.ptp(np.array(moved), axis=0)
        assert spread.max() > 1, spread  # degrees: the arm moved while the reader read
    finally:
        for proc in (bridge, up):
            if proc is not None:
                proc.terminate()
                proc.communicate(timeout=120)


def test_streamed_position_commands_move_only_through_the_operator_bridge(world: World) -> None:
    for remote, moves in (("/icubSim/left_arm", False), ("/op/left_arm", True)):
        board = Board(remote, f"/test/direct{remote.replace('/', '_')}")
        try:
            direct = board.driver.viewIPositionDirect()
            start = world.arm().position[ELBOW]
            goal = math.degrees(start) + (8 if start < 1.0 else -8)
            for _ in range(5):  # a stream: the first may go before the connection carries it
                direct.setPosition(ELBOW, goal)
                time.sleep(0.05)
            if moves:
                until(
                    lambda goal=goal: abs(world.arm().position[ELBOW] - math.radians(goal)) < 0.01,
                    "the streamed command on the mesh",
                    timeout=20,
                )
            else:
                time.sleep(0.5)
                assert world.arm().position[ELBOW] == pytest.approx(start, abs=1e-3)
        finally:
            board.close()


def test_a_failure_inside_an_answer_is_a_fail_bottle_and_the_port_goes_on(
    caplog: pytest.LogCaptureFixture,
) -> None:
    from archery.apps.yarp.controlboard import serve_rpc

    closing = threading.Event()
    replies: list[str] = []

    class Port:
        """Two requests, then the port closes."""

        def __init__(self) -> None:
            self.left = ["[get] [axes]", "[get] [encs]"]

        def read(self, request: Any, wait: bool) -> bool:
            request.fromString(self.left.pop(0))
            if not self.left:
                closing.set()
            return True

        def reply(self, bottle: Any) -> None:
            replies.append(bottle.toString())

    def respond(request: Any, reply: Any) -> None:
        if request.get(1).asVocab32() == yarp.createVocab32("e", "n", "c", "s"):
            raise RuntimeError("a failure of the answer")
        reply.addString("fine")

    serve_rpc(yarp, Port(), respond, closing, "/test/rpc:i")
    assert replies == ["fine", "[fail]"]
    assert "'[get] [encs]' failed" in caplog.text and "a failure of the answer" in caplog.text


def test_a_read_only_control_board_declares_no_command_path(world: World) -> None:
    """Read-only, a part's control board opens no publisher on the part's `command:i` (the
    operator's does), so no command of YARP's can reach the robot through it."""
    from archery.apps.yarp.controlboard import ControlBoard
    from archery.mesh.robot_client import RobotClient

    for operator in (False, True):
        node = open_node(world.net, 30)
        robot = RobotClient(node, timeout=5.0)
        board = ControlBoard(yarp, robot, ARM, f"/unit{int(operator)}", operator=operator)
        sender = yarp.BufferedPortBottle()
        try:
            command = node.keys.command(ARM)

            def declared(node: Node = node, command: str = command) -> list[Any]:
                return [p for p in node.describe().ports if p.key == command]

            if operator:
                assert until(declared, "the operator's publisher", timeout=10)[0].kind == "pub"
                continue
            # a streamed command refused: the command thread has run past where it would declare
            assert sender.open(f"/test/sender{time.monotonic_ns()}")
            assert yarp.Network.connect(sender.getName(), f"{board.name}/command:i")

            def refusing(sender: Any = sender, counts: dict[str, int] = board.counts) -> bool:
                return _send(sender) and counts["refused"] >= 3

            until(refusing, "refusals", timeout=10)
            assert not declared()
            assert board._threads[1].is_alive()  # the refusals' thread goes on
        finally:
            sender.close()
            board.close()
            robot.close()
            node.close()


def _send(port: Any) -> bool:
    """One streamed position command (`[dpos]` then the values) on `port`; True."""
    message = port.prepare()
    message.clear()
    message.addList().addVocab32(yarp.createVocab32("d", "p", "o", "s"))
    values = message.addList()
    for _ in PARTS[ARM]:
        values.addFloat64(0.0)
    port.write()
    return True
