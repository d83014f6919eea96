"""A hostile YARP client costs the bridge a restart, nothing more: under `archery up --yarp` (the
bridge with a name server of its own), YARP's `CONNECT` + `r` NULL dereference and a 60 KB
bottle of nested lists end at most in a restart that `up` reports, after which the ports answer
again (`remote_controlboard` reads the encoders) on a new name server, the old one gone, while
the robot's services never left the mesh; a YARP reader that never reads does not freeze the
encoders for another reader; SIGTERM ends the bridge within about a second."""

from __future__ import annotations

import contextlib
import os
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import psutil
import pytest
import zenoh

from archery.apps.yarp.controlboard import STALL
from archery.apps.yarp.network import stop_group
from archery.mesh.netflags import NetConfig
from archery.mesh.node import Node, open_node
from archery.mesh.router import free_tcp_endpoint
from archery.protocol.messages import JointState
from archery.protocol.robotspec import SERVICES
from tests.ros2_sdk import until
from tests.yarp_setup import YarpSetup, crash_output_port

yarp = pytest.importorskip("yarp", reason="YARP's bindings: `make setup` builds and installs them")

ROBOT = "crashbot"
ARM = "left_arm"
SERVER = re.compile(r"name server ([\d.]+):(\d+)")
#: crash → ports answering again (s), one per restart, for the report
RECOVERIES: list[float] = []


class Up:
    """`archery up --yarp` on a free endpoint: its report lines as they come, the bridge's
    name server, and this process's YARP pointed at it."""

    def __init__(self, tmp: Path) -> None:
        self.tmp = tmp
        self.endpoint = free_tcp_endpoint()
        self.lines: list[str] = []
        self.cond = threading.Condition()
        self.setup: YarpSetup | None = None
        self.node: Node | None = None
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "archery.apps.cli", "up", "--listen", self.endpoint,
             "--robot", ROBOT, "--logs", str(tmp / "logs"), "--runs", str(tmp / "runs"),
             "--yarp", "--restart-budget", "10"],
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        )  # fmt: skip
        threading.Thread(target=self._read, daemon=True).start()
        try:
            line = self.wait_line("archery up: on YARP", 0, timeout=180)[1]
            self.wait_line("archery up: all alive", 0, timeout=60)
            self.setup = YarpSetup(yarp, tmp / "yarp")  # the test's YARP configuration
            self.point_at(line)
            self.node = open_node(NetConfig(connect=(self.endpoint,), robot=ROBOT), 60)
            self.node.wait_alive(SERVICES, timeout=60)
            self.left: list[str] = []  # services seen leaving the mesh
            self.node.session.liveliness().declare_subscriber(
                self.node.keys.alive_all(), self._on_token
            )
        except BaseException:
            self.close()
            raise

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            with self.cond:
                self.lines.append(line.rstrip("\n"))
                self.cond.notify_all()

    def _on_token(self, sample: zenoh.Sample) -> None:
        if sample.kind == zenoh.SampleKind.DELETE:
            self.left.append(str(sample.key_expr))

    def wait_line(self, start: str, after: int, timeout: float = 60) -> tuple[int, str]:
        """The first line from index `after` that starts with `start`: (its index + 1, it)."""
        with self.cond:
            deadline = time.monotonic() + timeout
            while True:
                for i, line in enumerate(self.lines[after:], start=after):
                    if line.startswith(start):
                        return i + 1, line
                remaining = deadline - time.monotonic()
                assert remaining > 0, f"no {start!r} in {self.lines[after:]}"
                self.cond.wait(remaining)

    def point_at(self, line: str) -> tuple[str, int]:
        """This process's YARP and the test's YARP configuration pointed at the name server
        `line` names (as the line tells a user: `yarp conf HOST PORT`)."""
        found = SERVER.search(line)
        assert found is not None, line
        host, port = found[1], int(found[2])
        assert self.setup is not None
        subprocess.run(
            [self.setup.tool("yarp"), "conf", host, str(port)],
            env=self.setup.env, check=True, capture_output=True, timeout=30,
        )  # fmt: skip
        yarp.Network.setNameServerContact(yarp.Contact("/root", "tcp", host, port))
        self.server = (host, port)
        return self.server

    def bridge(self) -> psutil.Process:
        """The bridge's process (the child of `up` that runs `archery yarp`)."""
        children = psutil.Process(self.proc.pid).children()
        return next(c for c in children if "yarp" in c.cmdline()[3:5])

    def arm(self) -> JointState:
        assert self.node is not None
        sub = self.node.subscribe(self.node.keys.state(ARM), JointState)
        try:
            return sub.wait_newer(10)
        finally:
            self.node.unsubscribe(sub)

    def close(self) -> None:
        if self.node is not None:
            self.node.close()
        if self.proc.poll() is None:
            self.proc.terminate()
            self.proc.wait(120)
        if self.setup is not None:
            self.setup.close()


@pytest.fixture(scope="module")
def up(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Up]:
    running = Up(tmp_path_factory.mktemp("yarp-crash"))
    try:
        yield running
    finally:
        running.close()
        if RECOVERIES:
            print(f"\ncrash → ports again: {', '.join(f'{s:.2f}' for s in RECOVERIES)} s")


def _address(up: Up, name: str) -> tuple[str, int]:
    """Where the port `name` listens, as the bridge's name server tells it."""
    with socket.create_connection(up.server, timeout=5) as conn:
        conn.sendall(f"NAME_SERVER query {name}\n".encode())
        answer = b""
        while b"*** end of message" not in answer:
            chunk = conn.recv(4096)
            assert chunk, answer
            answer += chunk
    words = answer.decode().split()
    return words[words.index("ip") + 1], int(words[words.index("port") + 1])


def _encoders(name: str) -> list[float]:
    """The arm's encoders through YARP's `remote_controlboard` (None until it opens)."""
    options = yarp.Property()
    options.put("device", "remote_controlboard")
    options.put("remote", f"/{ROBOT}/{ARM}")
    options.put("local", name)
    driver = yarp.PolyDriver(options)
    try:
        if not driver.isValid():
            return []
        encoders = driver.viewIEncoders()
        values = yarp.Vector(encoders.getAxes())
        until(lambda: encoders.getEncoders(values.data()), "the encoders", timeout=10)
        return [values[i] for i in range(values.size())]
    finally:
        driver.close()


def _answers(server: tuple[str, int]) -> bool:
    try:
        with socket.create_connection(server, timeout=1):
            return True
    except OSError:
        return False


def _survived(up: Up, attack: Any) -> tuple[bool, float]:
    """Run `attack()` against the bridge; (whether it restarted, s until its ports answered
    again), checking that a restart was reported, its old name server is gone and the services
    never left the mesh."""
    bridge = up.bridge()
    servers = [p for p in bridge.children(recursive=True) if "yarpserver" in " ".join(p.cmdline())]
    assert servers, "the bridge runs its own yarpserver"
    old_server, mark = up.server, len(up.lines)
    started = time.monotonic()
    attack()
    with contextlib.suppress(psutil.TimeoutExpired):  # else it lived on: it cost nothing
        bridge.wait(10)
    restarted = not bridge.is_running()
    if restarted:
        after, _ = up.wait_line("archery up: yarp was killed by signal", mark)
        back = up.wait_line("archery up: yarp is back: on YARP", after, timeout=120)[1]
        for server in servers:  # the old name server and its registrations: gone
            until(lambda s=server: not s.is_running(), "the old yarpserver gone", 10)
        if up.point_at(back) != old_server:  # a new one (on the same port, if it came free)
            assert not _answers(old_server)
    name = f"/test/crash{time.monotonic_ns()}"
    encoders = until(lambda: _encoders(name), "remote_controlboard's encoders", timeout=60)
    took = time.monotonic() - started
    np.testing.assert_allclose(encoders, np.degrees(up.arm().position), atol=0.5)
    assert up.left == [], up.left  # the robot and the services never left the mesh
    return restarted, took


def test_connect_then_r_on_an_output_port_costs_a_restart(up: Up) -> None:
    def attack() -> None:
        address = _address(up, f"/{ROBOT}/{ARM}/state:o")  # where the bridge of now listens
        with socket.create_connection(address, timeout=5) as raw:
            crash_output_port(raw)

    for _ in range(3):  # three times: the median of the recoveries
        restarted, took = _survived(up, attack)
        assert restarted  # YARP 3.5's library dereferences NULL there: a crash, restarted
        RECOVERIES.append(took)


def test_a_bottle_of_nested_lists_costs_at_most_a_restart(up: Up) -> None:
    depth = 30_000  # 60 KB: YARP 3.5's parser recursed once per list

    def attack() -> None:
        with socket.create_connection(_address(up, f"/{ROBOT}/{ARM}/rpc:i"), timeout=5) as raw:
            raw.sendall(b"CONNECT /probe\n")
            raw.sendall(b"d\n" + b"(" * depth + b")" * depth + b"\n")
            raw.settimeout(10)
            with contextlib.suppress(OSError):
                raw.recv(4096)  # a reply, or the end of the connection

    restarted, _ = _survived(up, attack)
    if getattr(yarp, "archery_mends", None):  # built with tools/yarp_wheel.py's mend
        assert not restarted  # the bottle refused, the bridge serving on


def test_a_reader_that_never_reads_does_not_freeze_the_encoders(up: Up) -> None:
    assert up.setup is not None
    state = f"/{ROBOT}/{ARM}/state:o"
    stuck = subprocess.Popen(
        [up.setup.tool("yarp"), "read", "/test/stuck:i", state],
        stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
        env=up.setup.env, start_new_session=True,
    )  # fmt: skip
    port = yarp.BufferedPortVector()
    assert port.open("/test/keeps-up:i")
    got: list[float] = []
    reading = threading.Event()

    def read() -> None:
        while not reading.is_set():
            if port.read(True) is not None:
                got.append(time.monotonic())

    reader = threading.Thread(target=read, daemon=True)
    try:
        assert stuck.stdout is not None
        next(line for line in stuck.stdout if not line.startswith("["))  # it reads
        assert yarp.Network.connect(state, port.getName())
        reader.start()
        until(lambda: len(got) >= 20, "states for the reader that keeps up", timeout=30)
        before = (len(got) - 1) / (got[-1] - got[0])  # the state rate, both readers reading
        os.killpg(stuck.pid, signal.SIGSTOP)  # and now one never reads again
        stalled = time.monotonic()
        # while the stalled connection lasts and after YARP drops it: the state rate goes on
        until(lambda: got[-1] - stalled > 2 * STALL, "states past the stall", 6 * STALL)
        during = [t for t in got if t >= stalled]
        gaps = np.diff([stalled, *during])
        assert gaps.max() < max(0.5, 3 / before), gaps.max()  # never frozen
        assert len(during) / (during[-1] - stalled) > 0.8 * before, (len(during), before)
        name = f"/test/stall{time.monotonic_ns()}"
        np.testing.assert_allclose(_encoders(name), np.degrees(up.arm().position), atol=0.5)
        log = (up.tmp / "logs" / "yarp.log").read_text(errors="replace")
        assert "a connection has taken nothing" in log
    finally:
        reading.set()
        port.interrupt()
        port.close()
        os.killpg(stuck.pid, signal.SIGCONT)
        stop_group(stuck)


def test_sigterm_ends_the_bridge_within_a_second(up: Up) -> None:
    bridge = up.bridge()
    started = time.monotonic()
    bridge.terminate()
    bridge.wait(10)
    assert time.monotonic() - started < 1.5
    up.wait_line("archery up: yarp exited with status 0", 0)  # on-failure: left down
    assert up.left == []
