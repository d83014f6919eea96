"""`archery dashboard` as a web app on this machine must be: it answers only its own `Host`
(DNS rebinding), a GET changes nothing (the page's POSTs carry its token), it follows only
robots alive on the router and lets go of those no page polls, and half-open connections time
out and cannot take every thread."""

from __future__ import annotations

import dataclasses
import http.client
import json
import socket
import threading
import time
from collections.abc import Callable

import pytest

from archery.apps.dashboard.guard import MAX_CONNECTIONS, host_allowed
from archery.apps.dashboard.server import MAX_ROBOTS, TOKEN_HEADER, Dashboard, bind
from archery.mesh.netflags import NetConfig
from archery.mesh.node import Node
from archery.protocol.verbs.learner import LEARNER_VERBS, LearnerStatusReply
from tests.rpc import some_verbs

Answer = tuple[int, dict[str, str], bytes]


def request(
    dash: Dashboard,
    path: str,
    *,
    method: str = "GET",
    host: str | None = None,
    headers: dict[str, str] | None = None,
) -> Answer:
    """One request to the dashboard with `Host: host` (default its own address)."""
    address, port = bound(dash)
    connection = http.client.HTTPConnection(address, port, timeout=30)
    try:
        connection.putrequest(method, path, skip_host=True, skip_accept_encoding=True)
        connection.putheader("Host", host or f"{address}:{port}")
        for name, value in (headers or {}).items():
            connection.putheader(name, value)
        connection.endheaders()
        response = connection.getresponse()
        return response.status, dict(response.headers), response.read()
    finally:
        connection.close()


def bound(dash: Dashboard) -> tuple[str, int]:
    """The dashboard's address and port."""
    address, port = dash.server.server_address[:2]
    return str(address), int(port)


def wait_for(condition: Callable[[], bool], what: str, timeout: float = 30) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, what
        time.sleep(0.02)


def token_of(dash: Dashboard) -> str:
    status, headers, _ = request(dash, "/api/robots")
    assert status == 200
    return headers[TOKEN_HEADER]


PATHS = (
    "/",
    "/static/dashboard.js",
    "/api/state",
    "/api/frame.png",
    "/api/scene.jpg",
    "/api/robots",
)


def test_a_foreign_host_is_answered_421_and_nothing_else(net: NetConfig) -> None:
    with Dashboard(net, bind("127.0.0.1", 0)) as dash:
        port = bound(dash)[1]
        for host in ("evil.example", f"evil.example:{port}", "127.0.0.1:1", f"localhost.:{port}"):
            for path in PATHS:
                status, headers, body = request(dash, path, host=host)
                assert status == 421, (host, path, status)
                assert body.count(b"\n") == 1 and len(body) < 200, body
                assert TOKEN_HEADER not in headers and b"robot" not in body
            status, _, _ = request(
                dash, "/api/watch", method="POST", host=host, headers={TOKEN_HEADER: "x"}
            )
            assert status == 421
        for host in (
            f"127.0.0.1:{port}",
            f"localhost:{port}",
            f"[::1]:{port}",
            f"LocalHost:{port}",
        ):
            status, _, body = request(dash, "/", host=host)
            assert status == 200 and b"dashboard.js" in body, host
        status, _, body = request(dash, "/api/state")
        assert status == 200 and json.loads(body)["robot"] == net.robot


def test_a_dashboard_bound_to_another_address_answers_to_it(net: NetConfig) -> None:
    with Dashboard(net, bind("127.0.0.2", 0)) as dash:
        port = bound(dash)[1]
        assert request(dash, "/", host=f"127.0.0.2:{port}")[0] == 200
        assert request(dash, "/", host=f"localhost:{port}")[0] == 200
        assert request(dash, "/", host=f"127.0.0.3:{port}")[0] == 421


@pytest.mark.parametrize(
    ("header", "bound", "port", "allowed"),
    [
        ("127.0.0.1:8765", "127.0.0.1", 8765, True),
        ("localhost:8765", "127.0.0.1", 8765, True),
        ("[::1]:8765", "127.0.0.1", 8765, True),
        ("localhost", "127.0.0.1", 80, True),
        ("localhost", "127.0.0.1", 8765, False),
        ("192.0.2.7:8765", "192.0.2.7", 8765, True),
        ("192.0.2.7:8765", "0.0.0.0", 8765, True),  # every interface: any address
        ("[2001:db8::1]:8765", "::", 8765, True),
        ("evil.example:8765", "0.0.0.0", 8765, False),
        ("192.0.2.8:8765", "192.0.2.7", 8765, False),
        ("::1:8765", "127.0.0.1", 8765, False),
        ("[127.0.0.1]:8765", "127.0.0.1", 8765, False),
        ("127.0.0.1:8765x", "127.0.0.1", 8765, False),
        ("127.0.0.1:", "127.0.0.1", 8765, False),
        ("", "127.0.0.1", 8765, False),
        (None, "127.0.0.1", 8765, False),
    ],
)
def test_the_host_allow_list(header: str | None, bound: str, port: int, allowed: bool) -> None:
    assert host_allowed(header, bound, port) is allowed


def test_a_get_changes_nothing_and_a_post_needs_the_token(net: NetConfig) -> None:
    with Dashboard(net, bind("127.0.0.1", 0)) as dash:
        own = dash.watch()
        assert request(dash, "/api/state?scene=1")[0] == 200
        assert not own.scene_wanted()  # a GET no longer makes the camera render
        for k in range(MAX_ROBOTS + 3):
            status, _, body = request(dash, f"/api/state?robot=ghost{k}")
            assert status == 404 and "not watched" in json.loads(body)["error"]
        assert dash.watched() == [net.robot]
        robots = json.loads(request(dash, "/api/robots")[2])["robots"]
        assert not [r for r in robots if r.startswith("ghost")]
        # a POST without the token (a form of another site), or from another site's page
        token = token_of(dash)
        for headers in (
            {},
            {TOKEN_HEADER: token[:-1]},
            {TOKEN_HEADER: token, "Origin": "http://evil.example"},
        ):
            status, _, body = request(dash, "/api/scene", method="POST", headers=headers)
            assert status == 403 and body.count(b"\n") == 1, (headers, body)
        assert not own.scene_wanted()
        # GET of a POST's path: refused, nothing done
        assert request(dash, "/api/scene")[0] == 405
        assert not own.scene_wanted()
        # the page's own POST
        origin = "http://{}:{}".format(*bound(dash))
        status, _, _ = request(
            dash, "/api/scene", method="POST", headers={TOKEN_HEADER: token, "Origin": origin}
        )
        assert status == 200 and own.scene_wanted()
        # a ghost robot: 404 with one line, no watch
        status, _, body = request(
            dash, "/api/watch?robot=ghost1", method="POST", headers={TOKEN_HEADER: token}
        )
        assert status == 404 and body == b"robot 'ghost1' has no service alive on the router\n"
        status, _, body = request(
            dash, "/api/watch?robot=no%20such", method="POST", headers={TOKEN_HEADER: token}
        )
        assert status == 400 and body.count(b"\n") == 1 and b"invalid robot name" in body
        assert dash.watched() == [net.robot]
        # a body too long for a POST the page sends empty
        status, _, _ = request(
            dash,
            "/api/watch",
            method="POST",
            headers={TOKEN_HEADER: token, "Content-Length": "100000"},
        )
        assert status == 413


def test_a_watch_is_for_a_live_robot_and_closed_once_nobody_polls_it(net: NetConfig) -> None:
    other = dataclasses.replace(net, robot=net.robot + "b")
    status_reply = LearnerStatusReply(state="idle")
    with (
        Node("learner", other) as learner,
        Dashboard(net, bind("127.0.0.1", 0), watch_idle=1.5) as dash,
    ):
        learner.serve(
            learner.keys.learner_rpc(),
            some_verbs(LEARNER_VERBS, {"status": lambda _: status_reply}),
        )
        learner.ready()
        token = token_of(dash)
        follow = f"/api/watch?robot={other.robot}"
        wait_for(
            lambda: request(dash, follow, method="POST", headers={TOKEN_HEADER: token})[0] == 200,
            "the other robot is never followed",
        )
        assert dash.watched() == sorted([net.robot, other.robot])
        # polled, it stays followed past `watch_idle`
        until = time.monotonic() + 2.5
        while time.monotonic() < until:
            status, _, body = request(dash, f"/api/state?robot={other.robot}")
            assert status == 200 and json.loads(body)["robot"] == other.robot
            time.sleep(0.05)
        assert other.robot in dash.watched()
        # nobody polls it: closed, its slot free again; the dashboard's own robot stays
        wait_for(lambda: dash.watched() == [net.robot], "the idle watch is never closed")
        assert request(dash, f"/api/state?robot={other.robot}")[0] == 404
        assert request(dash, "/api/state")[0] == 200


def _threads_settle(baseline: int) -> int:
    """The threads over `baseline` once their count stops rising (at most a few s)."""
    last, deadline = -1, time.monotonic() + 5
    while time.monotonic() < deadline:
        now = threading.active_count() - baseline
        if now == last:
            return now
        last = now
        time.sleep(0.2)
    return last


def test_half_open_connections_time_out_and_cannot_take_every_thread(net: NetConfig) -> None:
    with Dashboard(net, bind("127.0.0.1", 0, request_timeout=8.0)) as dash:
        assert request(dash, "/api/state")[0] == 200
        baseline = threading.active_count()
        idle = [socket.create_connection(bound(dash), timeout=30) for _ in range(200)]
        try:
            # the page still answers at once: an idle connection gives way to it
            started = time.monotonic()
            status, _, _ = request(dash, "/api/state")
            assert status == 200 and time.monotonic() - started < 5.0  # before any timeout
            assert _threads_settle(baseline) <= MAX_CONNECTIONS + 2
            assert dash.server.connections()[0] <= MAX_CONNECTIONS
            # every half-open connection is closed: for a new one, or after its timeout
            started = time.monotonic()
            for connection in idle:
                assert connection.recv(1) == b""
            assert time.monotonic() - started < 8.0 + 10
        finally:
            for connection in idle:
                connection.close()
        wait_for(lambda: dash.server.connections() == (0, 0), "connections stay open")


def test_when_every_connection_is_busy_a_new_one_gets_503(net: NetConfig) -> None:
    with Dashboard(net, bind("127.0.0.1", 0, request_timeout=5.0, max_connections=2)) as dash:
        # two connections whose requests have come but not ended (a POST's body on its way)
        busy = []
        for _ in range(2):
            connection = socket.create_connection(bound(dash), timeout=30)
            connection.sendall(
                b"POST /api/scene HTTP/1.0\r\nHost: %s:%d\r\nContent-Length: 10\r\n\r\n"
                % (bound(dash)[0].encode(), bound(dash)[1])
            )
            busy.append(connection)
        try:
            wait_for(lambda: dash.server.connections() == (2, 0), "the requests never arrive")
            with socket.create_connection(bound(dash), timeout=30) as third:
                answer = b"".join(iter(lambda: third.recv(4096), b""))
            assert answer.startswith(b"HTTP/1.0 503 ")
            assert answer.endswith(b"\r\n\r\nthe dashboard is busy: try again soon\n")
        finally:
            for connection in busy:
                connection.close()
        wait_for(lambda: request(dash, "/api/state")[0] == 200, "the dashboard stays busy")
