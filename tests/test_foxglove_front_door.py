"""`archery foxglove`'s front door and bounds, tried as a hostile web page and a hostile client
would: raw WebSocket upgrades with foreign `Host` and `Origin` headers, an operator's server
without its token, one message naming 20,000 parameters, more connections than the cap,
clients that subscribe to the camera and never read, and a stop after thousands of
subscribe/unsubscribe cycles. Clients are Foxglove's own (`@foxglove/ws-protocol`, run with
Node from tests/foxglove_client) where a client is needed, raw sockets for the upgrades."""

from __future__ import annotations

import base64
import os
import re
import shutil
import signal
import socket
import subprocess
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import psutil
import pytest
from foxglove.websocket import Parameter, ParameterType

from archery.apps.foxglove.bridge import MAX_PARAMETERS, Bridge
from archery.apps.foxglove.upgrade import UpgradeRules, parse_head
from archery.protocol.errors import ConfigError
from archery.protocol.messages import Image
from tests.conftest import archery
from tests.ros2_sdk import until
from tests.test_foxglove import CLIENT, Mesh, _client, _of

pytestmark = pytest.mark.skipif(shutil.which("node") is None, reason="Node is not installed")


@pytest.fixture(scope="module")
def mesh(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Mesh]:
    running = Mesh(tmp_path_factory.mktemp("front_door"))
    try:
        yield running
    finally:
        running.close()


def _port(url: str) -> int:
    match = re.match(r"ws://127\.0\.0\.1:(\d+)/", url)
    assert match, url
    return int(match.group(1))


def _head(
    port: int, *, host: str | None = None, origin: str | None = None, path: str = "/"
) -> bytes:
    lines = [
        f"GET {path} HTTP/1.1",
        f"Host: {host if host is not None else f'127.0.0.1:{port}'}",
        "Upgrade: websocket",
        "Connection: Upgrade",
        f"Sec-WebSocket-Key: {base64.b64encode(os.urandom(16)).decode()}",
        "Sec-WebSocket-Version: 13",
        "Sec-WebSocket-Protocol: foxglove.sdk.v1",
    ]
    if origin is not None:
        lines.append(f"Origin: {origin}")
    return ("\r\n".join(lines) + "\r\n\r\n").encode()


def _open(port: int, **head: Any) -> tuple[socket.socket, int, str]:
    """A connection that sent an upgrade: (the socket, the answer's status, its text)."""
    sock = socket.create_connection(("127.0.0.1", port), timeout=10)
    sock.sendall(_head(port, **head))
    answer = b""
    while b"\r\n\r\n" not in answer:
        chunk = sock.recv(4096)
        if not chunk:
            break
        answer += chunk
    text = answer.decode("latin-1")
    status = int(text.split(" ", 2)[1]) if text.startswith("HTTP/1.1 ") else 0
    return sock, status, text


def _status(port: int, **head: Any) -> tuple[int, str]:
    sock, status, text = _open(port, **head)
    sock.close()
    return status, text


def test_foreign_host_and_origin_are_refused_read_only_and_operator(mesh: Mesh) -> None:
    _, viewer = mesh.bridge()
    _, operator = mesh.bridge("--operator")
    token = operator.split("?token=", 1)[1]
    assert len(token) >= 32
    for url, path in ((viewer, "/"), (operator, f"/?token={token}")):
        port = _port(url)
        for host in ("evil.example", f"evil.example:{port}", "127.0.0.1:1", "localhost.evil:80"):
            status, text = _status(port, host=host, path=path)
            assert status == 421 and "is not this server" in text, (host, text)
        for origin in ("http://evil.example", "https://app.foxglove.dev.evil.example", "null"):
            status, text = _status(port, origin=origin, path=path)
            assert status == 403 and "may not connect" in text, (origin, text)
        for host, origin in (
            (f"localhost:{port}", None),
            (f"127.0.0.1:{port}", "https://app.foxglove.dev"),
            (f"[::1]:{port}", "http://localhost:3000"),
            (f"127.0.0.1:{port}", "file://"),
        ):
            status, text = _status(port, host=host, origin=origin, path=path)
            assert status == 101, (host, origin, text)

    # a page the user names is let in, and only that one
    _, allowed = mesh.bridge("--allow-origin", "https://viewer.example.org")
    port = _port(allowed)
    assert _status(port, origin="https://viewer.example.org")[0] == 101
    assert _status(port, origin="https://other.example.org")[0] == 403
    done = archery("foxglove", "--allow-origin", "viewer.example.org", "--port", "0")
    assert done.returncode == 2 and "give an origin" in done.stderr


def test_operator_rights_need_the_token_printed_at_start(mesh: Mesh) -> None:
    _, operator = mesh.bridge("--operator")
    base, token = operator.split("?token=", 1)
    port = _port(operator)
    for path in ("/", "/?token=", f"/?token={token[:-1]}", f"/?token={token}x",
                 f"/?token={token}&token={token}"):  # fmt: skip
        status, text = _status(port, path=path)
        assert status == 403 and "token" in text, (path, text)
    # Foxglove's own client: refused without the token, served with it
    done = subprocess.run(
        ["node", str(CLIENT / "client.mjs"), base, "--want", "/mesh/services", "--timeout", "20"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 1 and "serverInfo" not in done.stdout
    lines = _client(operator, "--call", "/learner/status", "{}")
    assert "operator" in _of(lines, "serverInfo")[0]["name"] and _of(lines, "response")


def test_twenty_thousand_parameters_are_one_refusal_answered_at_once(mesh: Mesh) -> None:
    _, url = mesh.bridge("--operator")
    _client(url, "--set-wind", "0.5,0,0")
    started = time.monotonic()
    lines = _client(url, "--set-wind", "1,2,3", "--times", "20000", timeout=30)
    took = time.monotonic() - started
    statuses = [s["message"] for s in _of(lines, "status")]
    assert any("20000 parameters (at most 16)" in s for s in statuses), statuses
    assert took < 15, took  # 20,000 calls in turn took 24 s
    # nothing was set, and a new client is served at once
    lines = _client(url, "--set-wind", "0.5,0,0", timeout=30)
    assert _of(lines, "parameters")[-1][0]["value"] == [0.5, 0, 0]


class _Operator:
    """Counts the wind's settings (the checks of the bridge's parameters, without a robot)."""

    def __init__(self) -> None:
        self.set: list[Any] = []

    def set_wind(self, value: Any) -> list[float]:
        self.set.append(value)
        return [float(v) for v in value]

    def wind(self) -> list[float]:
        return [0.0, 0.0, 0.0]


class _Server:
    def __init__(self) -> None:
        self.statuses: list[str] = []

    def publish_status(self, message: str, level: Any) -> None:
        self.statuses.append(message)


def _wind(x: float) -> Parameter:
    return Parameter("wind", value=[x, 0.0, 0.0], type=ParameterType.Float64Array)


def test_one_message_sets_the_wind_once_and_names_at_most_sixteen_parameters() -> None:
    bridge = Bridge.__new__(Bridge)  # the parameters' checks run before any call
    operator, server = _Operator(), _Server()
    bridge.operator = operator  # type: ignore[assignment]
    bridge.server = server  # type: ignore[assignment]
    client: Any = None
    out = bridge.on_set_parameters(client, [_wind(float(i)) for i in range(MAX_PARAMETERS)])
    assert operator.set == [[15.0, 0.0, 0.0]]  # the last of the repeated name, set once
    assert [p.get_value() for p in out] == [[15.0, 0.0, 0.0]]
    unknown = [Parameter(f"x{i}\nforged", value=1.0) for i in range(3)] + [_wind(1.0)]
    bridge.on_set_parameters(client, unknown)
    assert len(server.statuses) == 1 and "\n" not in server.statuses[0]
    assert len(operator.set) == 2
    assert bridge.on_set_parameters(client, [_wind(2.0)] * (MAX_PARAMETERS + 1)) == []
    assert len(operator.set) == 2 and "nothing set" in server.statuses[-1]
    assert bridge.on_get_parameters(client, ["wind"] * (MAX_PARAMETERS + 1)) == []
    assert "at most 16" in server.statuses[-1]


def test_the_connections_are_capped_and_a_silent_one_is_closed(mesh: Mesh) -> None:
    _, url = mesh.bridge()
    port = _port(url)
    with socket.create_connection(("127.0.0.1", port), timeout=15) as silent:
        started = time.monotonic()
        assert silent.recv(1) == b""  # closed after the head's time, no byte sent
        assert time.monotonic() - started < 10
    held = []
    try:
        for _ in range(16):
            sock, status, _ = _open(port)
            assert status == 101
            held.append(sock)
        status, text = _status(port)
        assert status == 503 and "full" in text
        held.pop().close()
        deadline = time.monotonic() + 10  # the door sees the close and frees the place
        while (status := _status(port)[0]) == 503 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert status == 101
    finally:
        for sock in held:
            sock.close()
    deadline = time.monotonic() + 10  # the door sees the closes and frees their places
    while (status := _status(port)[0]) == 503 and time.monotonic() < deadline:
        time.sleep(0.05)
    with socket.create_connection(("127.0.0.1", port), timeout=15) as huge:
        huge.sendall(b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\nX: " + b"a" * (64 << 10))
        assert b" 431 " in huge.recv(4096)
    assert parse_head(_head(port)).one("host") == f"127.0.0.1:{port}"


def test_clients_that_never_read_keep_the_server_small(mesh: Mesh) -> None:
    proc, url = mesh.bridge("--max-clients", "32")
    server = psutil.Process(proc.pid)
    frames: list[float] = []
    sub = mesh.node.subscribe(
        mesh.node.keys.cam_frames(), Image, callback=lambda m: frames.append(m.stamp)
    )
    stalled = subprocess.Popen(
        ["node", str(CLIENT / "client.mjs"), url, "--stall", "20", "--want", "/camera/image"],
        stdout=subprocess.PIPE,
        text=True,
    )
    peaks: list[int] = []
    sampling = threading.Event()

    def sample() -> None:
        while not sampling.wait(0.05):
            peaks.append(server.memory_info().rss)

    sampler = threading.Thread(target=sample)
    try:
        assert stalled.stdout is not None
        assert '"stalled":20' in stalled.stdout.readline()
        base = server.memory_info().rss
        sampler.start()
        seen = len(frames)
        deadline = time.monotonic() + 120
        while len(frames) < seen + 60 and time.monotonic() < deadline:
            mesh.learn(1)  # the camera sends 10 frames/s while the view moves (1/s at rest)
        assert len(frames) >= seen + 60, "the camera sent too few frames"
    finally:
        sampling.set()
        if sampler.is_alive():
            sampler.join()
        sub.close()
        stalled.send_signal(signal.SIGTERM)
        stalled.communicate(timeout=30)
    # each client holds its queue of 4 raw frames (2.8 MB each) and the frame being sent to it
    # (twice: the message and the WebSocket's write buffer): 20 × 6 × 2.8 MB ≈ 340 MB, until
    # the front door drops it; unbounded, the 60 frames would be 3.4 GB
    assert max(peaks) - base < 450 << 20, (base >> 20, max(peaks) >> 20)
    assert proc.poll() is None


def test_a_stop_under_subscribe_churn_exits_at_once(mesh: Mesh, tmp_path: Path) -> None:
    proc, url = mesh.bridge()
    churn = subprocess.Popen(
        ["node", str(CLIENT / "client.mjs"), url, "--churn", "3000"],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert churn.stdout is not None
        assert '"churned":3000' in churn.stdout.readline()
        started = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        proc.wait(30)
        took = time.monotonic() - started
    finally:
        churn.send_signal(signal.SIGTERM)
        churn.communicate(timeout=30)
    err = (mesh.tmp / f"bridge-{mesh.bridges.index(proc)}.err").read_text()
    assert proc.returncode == 0, (proc.returncode, err[-2000:])
    assert took < 2.0, took
    assert "Traceback" not in err, err[-2000:]


def test_the_upgrade_rules() -> None:
    rules = UpgradeRules("0.0.0.0", 8765, token=None)  # inside a container
    for host in ("localhost:8765", "127.0.0.1:8765", "172.17.0.2:8765", "[::1]:8765"):
        assert rules.refusal(parse_head(_head(8765, host=host))) is None, host
    refused = rules.refusal(parse_head(_head(8765, host="evil.example:8765")))
    assert refused is not None and refused.status == 421
    double = _head(8765).replace(b"\r\n\r\n", b"\r\nHost: evil.example\r\n\r\n")
    refused = rules.refusal(parse_head(double))
    assert refused is not None and refused.status == 400
    with pytest.raises(ValueError, match="request line"):
        parse_head(b"\x00\xff nonsense\r\n\r\n")
    with pytest.raises(ConfigError):
        from archery.apps.foxglove.upgrade import check_origin_flag

        check_origin_flag("https://example.org/page")


def _masked_text(text: str) -> bytes:
    """One WebSocket text frame as a client sends it (masked; payload under 126 bytes)."""
    payload = text.encode()
    mask = os.urandom(4)
    masked = bytes(b ^ mask[i % 4] for i, b in enumerate(payload))
    return bytes([0x81, 0x80 | len(payload)]) + mask + masked


def test_the_sdks_own_log_lines_cannot_be_forged(mesh: Mesh) -> None:
    """A newline in what a client sends (an unknown `op`) reaches the SDK's error line, which
    the bridge's logging writes on one line: no forged line starts in its log."""
    _, url = mesh.bridge()
    log = mesh.tmp / f"bridge-{len(mesh.bridges) - 1}.err"
    sock, status, _ = _open(_port(url))
    with sock:
        assert status == 101
        sock.sendall(_masked_text('{"op": "bogus\\nERROR forged line"}'))
        line = until(
            lambda: next((x for x in log.read_text().splitlines() if "bogus" in x), None),
            "the SDK's error line in the bridge's log",
        )
    assert "bogus ERROR forged line" in line
    assert not any(x.startswith("ERROR forged") for x in log.read_text().splitlines())
