"""`archery yarp --secure`: the bridge on a mutual-TLS router beside a real robot service, every
YARP connection authenticated with the deployment's YARP key (YARP's AuthHMAC). YARP's own
clients (`remote_controlboard`, `RpcClient`, the `yarp` tool), each in a process of its own with
a configuration folder holding the key or not, and raw TCP callers speaking YARP's text
protocol: only the keyed ones reach a port or the name server; the arm moves for them alone.
A read-only bridge runs as `viewer` and moves nothing; the start ends at --wait whatever the
name server does."""

from __future__ import annotations

import hashlib
import hmac
import math
import os
import re
import select
import shutil
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from archery.apps.up.launcher import Launcher
from archery.apps.yarp.auth import read_key
from archery.apps.yarp.network import stop_group
from archery.mesh.credentials import YARP_AUTH, init_deployment
from archery.mesh.netflags import NetConfig
from archery.mesh.node import Node, open_node
from archery.mesh.router import free_tcp_endpoint
from archery.protocol.messages import JointState, WorldEvent
from tests.conftest import archery
from tests.ros2_sdk import until
from tests.test_yarp import ARM, ELBOW
from tests.yarp_setup import YarpSetup

yarp = pytest.importorskip("yarp", reason="YARP's bindings: `make setup` builds and installs them")

ROBOT = "icubSim"
CHALLENGE = 8 + 32  # what an authenticating YARP port sends first: a nonce and its HMAC-SHA256

#: a lab's YARP client in a process of its own: `board REMOTE LOCAL JOINT DEGREES` (YARP's
#: remote_controlboard, a position move) or `rpc PORT LOCAL TEXT` (an RpcClient's request); its
#: outcome on a line of its own, after "=> "
CLIENT = """
import sys
import time
import yarp

yarp.Network.init()
verb, remote, local = sys.argv[1:4]
if verb == "board":
    options = yarp.Property()
    for name, value in (("device", "remote_controlboard"), ("remote", remote), ("local", local)):
        options.put(name, value)
    driver = yarp.PolyDriver(options)
    if not driver.isValid():
        print("=> refused")
    else:
        moved = driver.viewIPositionControl().positionMove(int(sys.argv[4]), float(sys.argv[5]))
        print("=> moved" if moved else "=> not moved")
        driver.close()
else:
    client = yarp.RpcClient()
    client.open(local)
    if not client.addOutput(remote):
        print("=> refused")
    else:
        replies = []
        for i in range(2 if verb == "idle" else 1):
            if i:  # the connection left idle, as a lab's client between two calls
                time.sleep(float(sys.argv[5]))
            request, reply = yarp.Bottle(), yarp.Bottle()
            request.fromString(sys.argv[4])
            replies.append(reply.toString() if client.write(request, reply) else "no reply")
        print("=>", " | ".join(replies))
    client.close()
"""


class SecureYarp:
    """A secure router and the robot service; an operator bridge with its own name server
    (YARP's yarpserver, run by the bridge with the key) and a read-only bridge registered
    there; YARP configuration folders for a lab's clients, with the key and without."""

    def __init__(self, base: Path) -> None:
        self.base = base
        self.deployment = init_deployment(base / "deploy", robot=ROBOT)
        self.endpoint = free_tcp_endpoint().replace("tcp/", "tls/")
        self.launcher = Launcher(self.endpoint, ROBOT, base / "logs", secure=str(self.deployment))
        self.bridges: list[subprocess.Popen[str]] = []
        self.yarp: YarpSetup | None = None
        self.node: Node | None = None
        try:
            self._begin()
        except BaseException:
            self.close()
            raise

    def _begin(self) -> None:
        self.launcher.up(180, services=["robot"])
        # a user's YARP set-up, its name server without the key: the bridge passes it by
        self.yarp = YarpSetup(yarp, self.base / "yarp")
        ready = self.bridge("/op", "--operator")
        found = re.search(r"on the YARP name server (\S+):(\d+) \(ours", ready)
        assert found, ready
        self.host, self.port = found.group(1), int(found.group(2))
        self.bridge("/ro", "--yarp-server", f"{self.host}:{self.port}")
        self.keyed = self._folder("keyed", key=True)
        self.keyless = self._folder("keyless", key=False)
        net = NetConfig(
            connect=(self.endpoint,), robot=ROBOT, secure=str(self.deployment), identity="viewer"
        )
        self.node = open_node(net, 30)

    def command(self, *flags: str) -> list[str]:
        return [sys.executable, "-m", "archery.apps.cli", "yarp", "--secure", str(self.deployment),
                "--connect", self.endpoint, "--robot", ROBOT, *flags]  # fmt: skip

    def bridge(self, prefix: str, *flags: str) -> str:
        log = self.base / f"bridge{prefix.replace('/', '-')}.log"
        with log.open("w") as err:
            bridge = subprocess.Popen(
                self.command("--prefix", prefix, *flags),
                stdout=subprocess.PIPE,
                stderr=err,
                text=True,
            )
        self.bridges.append(bridge)
        assert bridge.stdout is not None
        ready = bridge.stdout.readline()
        assert ready.startswith("archery yarp: on YARP"), log.read_text()[-600:]
        return ready

    def _folder(self, name: str, *, key: bool) -> Path:
        """A lab client's YARP configuration folder: the bridge's name server, and the key the
        way a user installs it (a copy of DIR/yarp/auth.conf) or not."""
        folder = self.base / name
        folder.mkdir()
        (folder / "yarp.conf").write_text(f"{self.host} {self.port} yarp\n")
        if key:
            shutil.copy(self.deployment / YARP_AUTH, folder / "auth.conf")
        return folder

    def run(self, folder: Path, *argv: str, stdin: str = "") -> str:
        """A YARP client in a process of its own, configured by `folder`: its output."""
        assert self.yarp is not None
        out = subprocess.run(
            argv,
            input=stdin,
            capture_output=True,
            text=True,
            env={**self.yarp.env, "YARP_CONFIG_HOME": str(folder)},
            cwd=folder,
            timeout=60,
        )
        return out.stdout

    def run_all(self, folder: Path, calls: list[tuple[list[str], str]], within: float) -> list[str]:
        """YARP clients at once, each in a process of its own configured by `folder`, each
        stopped if it has not ended `within` s from the start: what each wrote."""
        assert self.yarp is not None
        env = {**self.yarp.env, "YARP_CONFIG_HOME": str(folder)}
        procs = [
            subprocess.Popen(argv, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                             stderr=subprocess.DEVNULL, text=True, env=env, cwd=folder,
                             start_new_session=True)  # YARP's launcher and its tool: one group
            for argv, _ in calls
        ]  # fmt: skip
        deadline = time.monotonic() + within
        said = []
        for proc, (_, stdin) in zip(procs, calls, strict=True):
            try:
                out, _ = proc.communicate(stdin, timeout=max(deadline - time.monotonic(), 0.1))
            except subprocess.TimeoutExpired:
                stop_group(proc)
                out, _ = proc.communicate()
            said.append(out)
        return said

    def client(self, folder: Path, *args: str) -> str:
        """What `CLIENT` says (YARP's own log lines aside)."""
        said = self.run(folder, sys.executable, "-c", CLIENT, *args).splitlines()
        return next((line[3:] for line in said if line.startswith("=> ")), "nothing")

    def tool(self, folder: Path, *args: str, stdin: str = "") -> str:
        assert self.yarp is not None
        return self.run(folder, self.yarp.tool("yarp"), *args, stdin=stdin)

    def where(self, name: str) -> tuple[str, int]:
        """A port's address, as the name server tells a keyed client."""
        said = self.tool(self.keyed, "name", "query", name)
        found = re.search(r"registration name \S+ ip (\S+) port (\d+)", said)
        assert found, said
        return found.group(1), int(found.group(2))

    def elbow(self) -> float:
        assert self.node is not None
        sub = self.node.subscribe(self.node.keys.state(ARM), JointState)
        try:
            return sub.wait_newer(10).position[ELBOW]
        finally:
            self.node.unsubscribe(sub)

    def close(self) -> None:
        if self.node is not None:
            self.node.close()
        for bridge in self.bridges:
            bridge.terminate()
            bridge.communicate(timeout=60)
        if self.yarp is not None:
            self.yarp.close()
        self.launcher.stop_all()
        self.launcher.forget_identities()


@pytest.fixture(scope="module")
def mesh(tmp_path_factory: pytest.TempPathFactory) -> Iterator[SecureYarp]:
    running = SecureYarp(tmp_path_factory.mktemp("yarp-secure"))
    try:
        yield running
    finally:
        running.close()


def _goal(start: float) -> float:
    return math.degrees(start) + (12 if start < 1.0 else -12)


def test_keyed_clients_read_the_viewer_bridge_moves_nothing_the_operator_bridge_moves(
    mesh: SecureYarp,
) -> None:
    start = mesh.elbow()
    said = mesh.client(mesh.keyed, "rpc", "/ro/left_arm/rpc:i", "/lab/ro", "[get] [axes]")
    assert said.startswith("[is] [axes] 7"), said
    assert mesh.client(mesh.keyed, "board", "/ro/left_arm", "/lab/ro/arm", "3", "0") == (
        "not moved"
    )
    goal = _goal(start)
    said = mesh.client(mesh.keyed, "board", "/op/left_arm", "/lab/op/arm", str(ELBOW), str(goal))
    assert said == "moved"
    until(
        lambda: abs(mesh.elbow() - math.radians(goal)) < math.radians(0.5),
        "the operator's move on the mesh",
        timeout=20,
    )
    assert "[ok]" in mesh.tool(mesh.keyed, "rpc", "/op/left_arm/rpc:i", stdin="[get] [axes]\n")


def test_an_authenticated_connection_outlives_an_idle_pause(mesh: SecureYarp) -> None:
    """YARP 3.5's handshake left its 2 s timeouts on the socket: a keyed client's connection
    idle for 2 s failed at its next call (the build's mend clears them)."""
    said = mesh.client(mesh.keyed, "idle", "/ro/left_arm/rpc:i", "/lab/idle", "[get] [axes]", "3")
    first, second = said.split(" | ")
    assert first.startswith("[is] [axes] 7") and second.startswith("[is] [axes] 7"), said


def test_keyless_yarp_clients_reach_neither_a_port_nor_the_name_server(mesh: SecureYarp) -> None:
    """YARP 3.5 drops an unauthenticated connection without closing it: a keyless client gets
    the port's challenge and then nothing, refused or waiting until it is stopped."""
    start = mesh.elbow()
    rpc = mesh.where("/op/archery/rpc:i")
    assert mesh.yarp is not None
    tool = mesh.yarp.tool("yarp")
    client = [sys.executable, "-c", CLIENT]
    calls = [
        ([*client, "board", "/op/left_arm", "/lab/x/arm", "3", "40"], ""),
        ([*client, "rpc", "/op/left_arm/rpc:i", "/lab/x", "[set] [pos] 3 40"], ""),
        ([*client, "rpc", "/op/archery/rpc:i", "/lab/y", "reset"], ""),
        ([tool, "rpc", "/op/left_arm/rpc:i"], f"[set] [pos] {ELBOW} 40\n"),
        ([tool, "name", "query", "/op/left_arm/rpc:i"], ""),
        ([tool, "name", "register", "/op/archery/rpc:i", "tcp", "127.0.0.1", "9"], ""),
    ]  # fmt: skip
    said = mesh.run_all(mesh.keyless, calls, within=20)
    for (argv, _), out in zip(calls, said, strict=True):
        outcome = [line for line in out.splitlines() if line.startswith("=> ")]
        assert outcome in ([], ["=> refused"]), (argv, out)
        assert "[ok]" not in out and "registration name" not in out, (argv, out)
    assert mesh.where("/op/archery/rpc:i") == rpc  # the name is the bridge's still
    assert abs(mesh.elbow() - start) < math.radians(0.5)


def _read_all(conns: list[socket.socket], within: float) -> list[bytes]:
    """What each connection sends until it closes or `within` s have passed, read at once (YARP
    3.5 drops an unauthenticated connection without closing it)."""
    got = {conn: b"" for conn in conns}
    open_ = set(conns)
    deadline = time.monotonic() + within
    while open_ and (left := deadline - time.monotonic()) > 0:
        ready, _, _ = select.select(list(open_), [], [], left)
        for conn in ready:
            try:
                chunk = conn.recv(4096)
            except ConnectionResetError:
                chunk = b""
            if chunk:
                got[conn] += chunk
            else:
                open_.discard(conn)
    return [got[conn] for conn in conns]


def test_raw_tcp_callers_get_the_challenge_and_nothing_else_and_nothing_moves(
    mesh: SecureYarp,
) -> None:
    assert mesh.node is not None
    events = mesh.node.subscribe(mesh.node.keys.world_events(), WorldEvent)
    start = mesh.elbow()
    rpc, command = mesh.where("/op/left_arm/rpc:i"), mesh.where("/op/left_arm/command:i")
    archery_rpc = mesh.where("/op/archery/rpc:i")
    name_server = (mesh.host, mesh.port)
    calls = [
        (rpc, b"CONNECT /foo\nd\n[set] [vels] 50 50 50 50 50 50 50\n"),
        (rpc, b"CONNECT /foo\nd\n[set] [pos] 3 40\nd\n[set] [poss] (0 0 0 40 0 0 0)\n"),
        (command, b"CONNECT /foo\nd\n[set] [dpos] (0 0 0 40 0 0 0)\n" * 20),
        (archery_rpc, b"CONNECT /foo\nd\nreset\nd\nnock\nd\nrelease\n"),
        (archery_rpc, b"CONNECT /foo\na\n[del] /op/left_arm/state:o\na\n[prop] [get]\n"),
        (name_server, b"NAME_SERVER register /op/archery/rpc:i tcp 127.0.0.1 9\n"),
        (name_server, b"CONNECT /foo\nd\nregister /op/left_arm/rpc:i tcp 127.0.0.1 9\n"),
        (rpc, b"GET /data=list HTTP/1.1\r\nHost: x\r\n\r\n"),
    ]
    conns = []
    for address, payload in calls:
        conn = socket.create_connection(address, timeout=5)
        conn.sendall(payload)
        conns.append(conn)
    try:
        got = _read_all(conns, within=4)
    finally:
        for conn in conns:
            conn.close()
    assert [len(g) for g in got] == [CHALLENGE] * len(calls), got
    assert abs(mesh.elbow() - start) < math.radians(0.5)
    assert mesh.where("/op/archery/rpc:i") == archery_rpc
    assert mesh.where("/op/left_arm/rpc:i") == rpc
    try:
        assert events.latest() is None  # no reset, nock or release reached the robot
    finally:
        mesh.node.unsubscribe(events)
    said = mesh.client(mesh.keyed, "rpc", "/op/left_arm/rpc:i", "/lab/after", "[get] [axes]")
    assert said.startswith("[is] [axes] 7"), said


def test_a_secure_bridge_refuses_a_name_server_that_does_not_authenticate(
    mesh: SecureYarp,
) -> None:
    assert mesh.yarp is not None
    out = subprocess.run(
        mesh.command("--prefix", "/plain", "--yarp-server", f"127.0.0.1:{mesh.yarp.port}"),
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 1, out.stderr
    last = out.stderr.strip().splitlines()[-1]
    assert last.startswith("archery yarp: ") and "does not authenticate" in last, last


def test_the_operator_bridge_is_never_started_without_the_key(tmp_path: Path) -> None:
    deployment = init_deployment(tmp_path / "old", robot=ROBOT)
    (deployment / YARP_AUTH).unlink()
    out = archery("yarp", "--secure", str(deployment), "--operator")
    assert out.returncode == 2, out.stderr
    assert out.stderr.count("\n") == 1 and str(deployment / YARP_AUTH) in out.stderr
    assert out.stdout == ""


def test_plain_mode_keeps_yarp_on_loopback() -> None:
    out = archery("yarp", "--yarp-ip", "0.0.0.0")
    assert out.returncode == 2
    assert "--insecure-network" in out.stderr and out.stderr.count("\n") == 1


def test_the_key_is_private_and_yarp_reads_it_as_written(tmp_path: Path) -> None:
    deployment = init_deployment(tmp_path / "d", robot=ROBOT)
    path = deployment / YARP_AUTH
    assert path.stat().st_mode & 0o777 == 0o600 and path.parent.stat().st_mode & 0o777 == 0o700
    config = yarp.Property()
    assert config.fromConfigFile(str(path))
    said = config.findGroup("AUTH").find("key").asString()
    assert said.encode() == read_key(deployment).secret and len(said) % 16 == 0
    assert archery("keys", "yarp", str(deployment)).returncode == 2  # never replaced unasked
    out = archery("keys", "yarp", str(deployment), "--force")
    assert out.returncode == 0 and read_key(deployment).secret != said.encode()


def _acceptor(conn: socket.socket, secret: bytes) -> None:
    """YARP's handshake as the accepting side, as an authenticating name server does it."""

    def mac(*parts: bytes) -> bytes:
        return hmac.new(secret, b"".join(parts), hashlib.sha256).digest()

    n1 = os.urandom(8)
    conn.sendall(n1 + mac(n1))
    answer = b""
    while len(answer) < CHALLENGE:
        chunk = conn.recv(CHALLENGE - len(answer))
        assert chunk, "the bridge closed the handshake"
        answer += chunk
    assert hmac.compare_digest(answer[8:], mac(n1, answer[:8]))
    n3 = os.urandom(8)
    conn.sendall(n3 + mac(n1, answer[:8], n3))


class FakeNameServer:
    """A name server that authenticates with the key and answers the first query as YARP's
    does, then, to every later connection, `garbage` (endless lines) or `silence`."""

    def __init__(self, secret: bytes, then: str) -> None:
        self.secret, self.then = secret, then
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.port = self.listener.getsockname()[1]
        self.stop = threading.Event()
        self.conns: list[socket.socket] = []
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    def _serve(self) -> None:
        self.listener.settimeout(0.2)
        first = True
        while not self.stop.is_set():
            try:
                conn, _ = self.listener.accept()
            except TimeoutError:
                continue
            self.conns.append(conn)
            threading.Thread(target=self._answer, args=(conn, first), daemon=True).start()
            first = False

    def _answer(self, conn: socket.socket, first: bool) -> None:
        try:
            _acceptor(conn, self.secret)
            if first:
                conn.recv(4096)
                conn.sendall(
                    f"registration name /root ip 127.0.0.1 port {self.port} type tcp\n"
                    "*** end of message\n".encode()
                )
            while self.then == "garbage" and not self.stop.is_set():
                conn.sendall(b"not a name server's answer\n" * 64)
            self.stop.wait()
        except OSError:
            return

    def close(self) -> None:
        self.stop.set()
        self.thread.join()
        for conn in self.conns:
            conn.close()
        self.listener.close()


@pytest.mark.parametrize("then", ["garbage", "silence"])
def test_the_start_ends_at_wait_whatever_the_name_server_says(mesh: SecureYarp, then: str) -> None:
    fake = FakeNameServer(read_key(mesh.deployment).secret, then)
    try:
        began = time.monotonic()
        out = subprocess.run(
            mesh.command("--prefix", "/late", "--yarp-server", f"127.0.0.1:{fake.port}",
                         "--wait", "8"),
            capture_output=True,
            text=True,
            timeout=120,
        )  # fmt: skip
        took = time.monotonic() - began
    finally:
        fake.close()
    assert out.returncode == 1, out.stderr
    ours = [line for line in out.stderr.splitlines() if line.startswith("archery yarp: ")]
    assert len(ours) == 1 and "within --wait 8 s" in ours[0], out.stderr
    assert took < 8 + 20, took


def test_the_yarp_body_checks_a_secure_robot_with_its_key_and_reaches_nothing_without(
    mesh: SecureYarp,
) -> None:
    """`archery selfcheck --body yarp` (the YARP body's read side) against the secure bridge's
    robot: with the lab's YARP configured with the key, YARP's own AuthHMAC lets the body in and
    it reads every part; without it, one line says why, exit 2, nothing read."""
    assert mesh.yarp is not None
    argv = [sys.executable, "-m", "archery.apps.cli", "selfcheck", "--body", "yarp",
            "--remote", "/op"]  # fmt: skip
    said = {}
    for name, folder in (("keyed", mesh.keyed), ("keyless", mesh.keyless)):
        said[name] = subprocess.run(
            argv,
            capture_output=True,
            text=True,
            env={**mesh.yarp.env, "YARP_CONFIG_HOME": str(folder)},
            cwd=folder,
            timeout=120,
        )
    keyed, keyless = said["keyed"], said["keyless"]
    assert keyed.returncode == 0, keyed.stderr[-2000:]
    assert keyed.stdout.splitlines()[-1].startswith("ok: 3 parts, ")
    assert keyless.returncode == 2, keyless.stderr[-2000:]
    last = keyless.stderr.strip().splitlines()[-1]
    assert last.startswith("archery selfcheck: the YARP name server at "), last
    assert "AuthHMAC" in last and keyless.stdout == ""
