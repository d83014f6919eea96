"""`archery dashboard`: a live view of a learning session in the browser.

A small page served by the package itself (`_Handler`: its endpoints, and why no web
framework) through the guarded HTTP server of `apps.dashboard.guard`; the mesh side is one
`apps.dashboard.watch.MeshWatch` per robot followed (`Dashboard`); `--operator`: `confirm.py`.
What the page shows: docs/commands.md, under `archery dashboard`.
"""

from __future__ import annotations

import argparse
import errno
import hmac
import ipaddress
import json
import logging
import secrets
import socket
import threading
import time
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler
from importlib import resources
from typing import Any
from urllib.parse import parse_qs, urlsplit

from archery.apps.dashboard.confirm import CONFIRM_PATH, add_operator_arg, confirm, node_settings
from archery.apps.dashboard.guard import MAX_CONNECTIONS, REQUEST_TIMEOUT, GuardedServer
from archery.apps.dashboard.watch import MeshWatch
from archery.apps.viewer import View, add_wait_arg, viewer_main
from archery.mesh.cliargs import ArgumentParser, int_in
from archery.mesh.netflags import NetConfig, add_network_args, check_server_host
from archery.mesh.node import Node
from archery.mesh.priority import OBSERVER_NICE, add_nice_arg, lower_priority
from archery.protocol.errors import ArcheryError, ConfigError
from archery.protocol.keys import validate_robot

__all__ = [
    "DEFAULT_PORT",
    "MAX_ROBOTS",
    "TOKEN_HEADER",
    "WATCH_IDLE",
    "Dashboard",
    "NotWatched",
    "main",
]

log = logging.getLogger("archery.dashboard")

DEFAULT_PORT = 8780  # `archery foxglove` keeps Foxglove's usual 8765
MAX_ROBOTS = 32  # robots one dashboard follows at most (a watch each)
WATCH_IDLE = 30.0  # s: a watch of another robot that no page polled this long is closed
TOKEN_HEADER = "X-Dashboard-Token"  # the page's token: on every answer, required on each POST
_MAX_BODY = 1024  # B: a POST's body at most (the page sends none)
_POSTS = ("/api/watch", "/api/scene")
_WRONG_HOST = (
    b"this dashboard answers only to its own address (Host localhost, 127.0.0.1 or the "
    b"--host address, with its port)\n"
)
_TYPES = {".html": "text/html", ".js": "text/javascript", ".css": "text/css"}
_PAGES = {"/": "index.html", "/index.html": "index.html"}


def _static(name: str) -> bytes | None:
    """A file of the package's `static/` folder, or None when there is no such file."""
    if "/" in name or name.startswith("."):
        return None
    path = resources.files("archery.apps.dashboard").joinpath("static", name)
    return path.read_bytes() if path.is_file() else None


class _Server(GuardedServer):
    dashboard: Dashboard


class _Handler(BaseHTTPRequestHandler):
    """The dashboard's requests.

    A standard-library threading HTTP server (`guard.GuardedServer`) serves three files
    (`static/`: HTML, CSS and a short script that draws the face and the curve as SVG), a JSON
    endpoint (`/api/state?robot=R`) the page polls twice a second, the frame as PNG
    (`/api/frame.png?robot=R`), the scene view as JPEG (`/api/scene.jpg?robot=R`) and the
    robots alive (`/api/robots`). Why: no extra dependency (no web framework, no Rerun),
    nothing fetched from a CDN so it works offline and behind a firewall, and any plain browser
    (or `curl`, or a headless Chromium in the tests) can read it.

    As a web app on this machine must, it answers only requests whose `Host` is its own
    address (421 otherwise: a page of another site cannot read the camera through DNS
    rebinding), closes a connection whose request does not come within
    `guard.REQUEST_TIMEOUT` s and serves at most `guard.MAX_CONNECTIONS` at once. A GET
    changes nothing: what changes what is watched is a POST carrying the page's token
    (`do_POST`).
    """

    server: _Server
    server_version = "archery-dashboard"

    def setup(self) -> None:
        super().setup()
        self.connection.settimeout(self.server.request_timeout)  # each read, then closed

    def log_message(self, format: str, *args: Any) -> None:
        log.debug("%s " + format, self.address_string(), *args)

    def parse_request(self) -> bool:
        """The request line and headers read; nothing is answered to a `Host` not allowed."""
        if not super().parse_request() or not self.server.started(self.connection):
            return False
        if not self.server.allows(self.headers.get("Host")):
            self._send(HTTPStatus.MISDIRECTED_REQUEST, _WRONG_HOST, "text/plain")
            return False
        return True

    def _send(self, status: int, body: bytes, ctype: str) -> None:
        self.send_response(status)
        self.send_header("Content-Type", ctype)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        self.send_header("X-Content-Type-Options", "nosniff")
        dashboard = getattr(self.server, "dashboard", None)
        if status != HTTPStatus.MISDIRECTED_REQUEST and dashboard is not None:
            self.send_header(TOKEN_HEADER, dashboard.token)
        self.end_headers()
        if self.command != "HEAD":
            self.wfile.write(body)

    def _text(self, status: int, line: str) -> None:
        self._send(status, (line + "\n").encode(), "text/plain; charset=utf-8")

    def do_HEAD(self) -> None:
        self.do_GET()

    def do_GET(self) -> None:
        url = urlsplit(self.path)
        path, query = url.path, parse_qs(url.query)
        if path in self.server.dashboard.posts:
            what = "the session" if path == CONFIRM_PATH else "what is watched"
            self._text(HTTPStatus.METHOD_NOT_ALLOWED, f"{path} changes {what}: POST it")
            return
        if path.startswith("/api/"):
            self._api(path, query)
            return
        name = _PAGES.get(path)
        if name is None and path.startswith("/static/"):
            name = path.removeprefix("/static/")
        content = _static(name) if name else None
        if name is None or content is None:
            self._send(HTTPStatus.NOT_FOUND, b"not found\n", "text/plain")
            return
        ctype = _TYPES.get("." + name.rsplit(".", 1)[-1], "application/octet-stream")
        self._send(HTTPStatus.OK, content, ctype + "; charset=utf-8")

    def do_POST(self) -> None:
        """`/api/watch?robot=R` (follow a robot alive on the router; 404 for one that is not),
        `/api/scene?robot=R` (a page shows the scene view: the page posts it with each poll
        while its scene panel is open) and, with `--operator` only, `/api/confirm?robot=R&
        request=N` (the operator did request N: `apps.dashboard.confirm`; else 404), each with
        the page's token in `TOKEN_HEADER`: a random one per server, sent with every answer; a
        page of another site cannot read it, nor send a header of its own without this
        server's consent."""
        url = urlsplit(self.path)
        dashboard = self.server.dashboard
        if not self._drain_body():
            return
        if url.path not in dashboard.posts:
            self._text(HTTPStatus.NOT_FOUND, "not found")
            return
        token = self.headers.get(TOKEN_HEADER, "")
        origin = self.headers.get("Origin")
        if not hmac.compare_digest(token.encode(), dashboard.token.encode()):
            self._text(HTTPStatus.FORBIDDEN, f"no valid {TOKEN_HEADER}: POST from the page only")
            return
        if origin is not None and not self.server.allows(urlsplit(origin).netloc):
            self._text(HTTPStatus.FORBIDDEN, "a page of another site may not POST here")
            return
        query = parse_qs(url.query)
        robot = query.get("robot", [None])[0]
        try:
            if url.path == CONFIRM_PATH:
                self._send(*confirm(dashboard.watch(robot), query))
                return
            if url.path == "/api/watch":
                watch = dashboard.follow(robot)
            else:
                watch = dashboard.watch(robot)
                watch.want_scene()
        except NotWatched as exc:
            self._text(HTTPStatus.NOT_FOUND, str(exc))
            return
        except ArcheryError as exc:
            self._text(HTTPStatus.BAD_REQUEST, str(exc))
            return
        body = json.dumps({"robot": watch.keys.robot}).encode()
        self._send(HTTPStatus.OK, body, "application/json")

    def _drain_body(self) -> bool:
        """Read a POST's body (nothing is expected of it); False when it is too long (413)."""
        try:
            length = int(self.headers.get("Content-Length") or 0)
        except ValueError:
            length = -1
        if not 0 <= length <= _MAX_BODY:
            self.close_connection = True
            self._text(HTTPStatus.REQUEST_ENTITY_TOO_LARGE, f"a body of {_MAX_BODY} B at most")
            return False
        self.rfile.read(length)
        return True

    def _api(self, path: str, query: dict[str, list[str]]) -> None:
        dashboard = self.server.dashboard
        if path == "/api/robots":
            body = json.dumps(dashboard.robots()).encode()
            self._send(HTTPStatus.OK, body, "application/json")
            return
        try:
            watch = dashboard.watch(query.get("robot", [None])[0])
        except ArcheryError as exc:
            status = HTTPStatus.NOT_FOUND if isinstance(exc, NotWatched) else HTTPStatus.BAD_REQUEST
            body = json.dumps({"error": str(exc)}).encode()
            self._send(status, body, "application/json")
            return
        if path == "/api/state":
            state = watch.snapshot() | {"operator": dashboard.operator}
            body = json.dumps(state, allow_nan=False).encode()
            self._send(HTTPStatus.OK, body, "application/json")
        elif path in ("/api/frame.png", "/api/scene.jpg"):
            png = path == "/api/frame.png"
            data, _ = watch.frame() if png else watch.scene()
            if data is None:
                missing = b"no frame measured yet\n" if png else b"no scene view yet\n"
                self._send(HTTPStatus.NOT_FOUND, missing, "text/plain")
            else:
                self._send(HTTPStatus.OK, data, "image/png" if png else "image/jpeg")
        else:
            self._send(HTTPStatus.NOT_FOUND, b"not found\n", "text/plain")


def _check_host(host: str) -> str:
    try:
        return str(ipaddress.ip_address(host))
    except ValueError:
        if host == "localhost":
            return "127.0.0.1"
        raise ConfigError(
            f"--host {host!r} is not an IP address; give one of this machine's addresses, "
            f"e.g. 127.0.0.1 (this machine only)"
        ) from None


def bind(
    host: str,
    port: int,
    *,
    request_timeout: float = REQUEST_TIMEOUT,
    max_connections: int = MAX_CONNECTIONS,
) -> _Server:
    """The HTTP server listening on `host:port` (port 0: a free one), not serving yet; a
    connection's request may take `request_timeout` s, `max_connections` are served at once.

    Raises:
        ConfigError: the port is taken, or the address is not this machine's.
    """
    server_class = type(
        "_BoundServer",
        (_Server,),
        {"address_family": socket.AF_INET6 if ":" in host else socket.AF_INET},
    )
    try:
        return server_class(
            (host, port),
            _Handler,
            request_timeout=request_timeout,
            max_connections=max_connections,
        )
    except OSError as exc:
        if exc.errno == errno.EADDRINUSE:
            raise ConfigError(
                f"--port {port}: address {host}:{port} is in use by another program; "
                f"choose another --port (0 picks a free one)"
            ) from None
        raise ConfigError(f"--host {host} --port {port}: cannot listen: {exc.strerror}") from None


class NotWatched(ArcheryError):
    """A robot the dashboard does not follow (a page POSTs `/api/watch` first), or one that is
    not alive on the router (nothing to follow)."""

    code = "not_watched"


class Dashboard:
    """The server and the mesh watches together (the node's robot's, and each other robot's
    a page chose, while it is alive on the router and a page polls it); a context manager
    (tests use it directly). `token` is what the page sends with each POST; `operator`
    (`--operator`): `/api/confirm` is served, and the page shows its Confirm button.

    The mesh side is an anonymous node with one `MeshWatch` per robot followed, at most
    `MAX_ROBOTS`; another robot's is closed once no page polled it for `WATCH_IDLE` s. A watch
    subscribes to the rollouts, watches the liveliness tokens and calls only the learner's
    `status`, each service's `describe` (its ports' message counts), the detector's `frame`
    and, while a page shows it, the camera's `scene`, so watching never disturbs a session;
    with `operator`, the learner's `confirm` when the page's Confirm button is pressed.
    """

    def __init__(
        self,
        net: NetConfig,
        server: _Server,
        *,
        watch_idle: float = WATCH_IDLE,
        node: Node | None = None,
        operator: bool = False,
    ) -> None:
        self.server = server
        self.operator = operator
        self.posts = (*_POSTS, CONFIRM_PATH) if operator else _POSTS
        self._own_node = node is None  # a node given stays its giver's to close
        try:
            self.node = Node(None, net) if node is None else node
        except BaseException:
            self.server.server_close()
            raise
        self.token = secrets.token_urlsafe(24)
        self.watch_idle = watch_idle
        self._lock = threading.Lock()
        self._watches = {net.robot: MeshWatch(self.node)}
        self._polled: dict[str, float] = {}  # robot -> monotonic s of its last poll (not ours)
        self._stop = threading.Event()
        self.server.dashboard = self
        self._thread = threading.Thread(
            target=self.server.serve_forever, name="dashboard-http", daemon=True
        )
        self._thread.start()
        self._reaper = threading.Thread(target=self._reap, name="dashboard-reap", daemon=True)
        self._reaper.start()

    @property
    def url(self) -> str:
        address, port = self.server.server_address[:2]
        host = str(address)  # as an f-string shows it
        shown = f"[{host}]" if ":" in host else host
        return f"http://{shown}:{port}/"

    def _robot(self, robot: str | None) -> str:
        return self.node.keys.robot if robot is None else validate_robot(robot)

    def watch(self, robot: str | None = None) -> MeshWatch:
        """The watch of `robot` (None: the dashboard's own robot), as a page polls it: a watch
        polled within `watch_idle` s stays open.

        Raises:
            KeyNameError: not a robot name.
            NotWatched: the dashboard does not follow `robot` (`follow` starts a watch).
        """
        robot = self._robot(robot)
        with self._lock:
            watch = self._watches.get(robot)
            if watch is None:
                raise NotWatched(
                    f"robot {robot!r} is not watched: choose it in the page (POST /api/watch)"
                )
            if robot in self._polled:
                self._polled[robot] = time.monotonic()
            return watch

    def follow(self, robot: str | None) -> MeshWatch:
        """The watch of `robot`, started when it is alive on the router (a service of it has its
        liveliness token); closed again once no page polled it for `watch_idle` s.

        Raises:
            KeyNameError: not a robot name.
            NotWatched: no service of `robot` is alive on the router.
            ConfigError: `MAX_ROBOTS` robots are watched already.
        """
        robot = self._robot(robot)
        with self._lock:
            watch = self._watches.get(robot)
            if watch is not None:
                if robot in self._polled:
                    self._polled[robot] = time.monotonic()
                return watch
        if robot not in self.node.alive_robots(timeout=1.0):
            raise NotWatched(f"robot {robot!r} has no service alive on the router")
        with self._lock:
            watch = self._watches.get(robot)
            if watch is None:
                if len(self._watches) >= MAX_ROBOTS:
                    raise ConfigError(
                        f"this dashboard follows {MAX_ROBOTS} robots already; start another "
                        f"`archery dashboard --robot {robot}` for more"
                    )
                watch = self._watches[robot] = MeshWatch(self.node, robot=robot)
            self._polled[robot] = time.monotonic()
            return watch

    def watched(self) -> list[str]:
        """The robots watched now, sorted."""
        with self._lock:
            return sorted(self._watches)

    def _reap(self) -> None:
        """Close each watch (but the dashboard's own robot's) no page polled for `watch_idle` s."""
        while not self._stop.wait(min(1.0, self.watch_idle / 4)):
            now = time.monotonic()
            with self._lock:
                idle = [r for r, t in self._polled.items() if now - t > self.watch_idle]
                closing = [self._watches.pop(r) for r in idle]
                for robot in idle:
                    del self._polled[robot]
            for robot, watch in zip(idle, closing, strict=True):
                log.info(
                    "robot %s: no page polled it for %g s, not watched", robot, self.watch_idle
                )
                watch.close()

    def robots(self) -> dict[str, Any]:
        """{"default": the dashboard's robot, "robots": every robot with a live service on the
        router and every robot watched, sorted}."""
        alive = set(self.node.alive_robots(timeout=1.0))
        return {"default": self.node.keys.robot, "robots": sorted(alive | set(self.watched()))}

    def close(self) -> None:
        self._stop.set()
        self.server.shutdown()
        self.server.server_close()
        self._reaper.join(timeout=10)
        with self._lock:
            watches = list(self._watches.values())
        for watch in watches:
            watch.close()
        if self._own_node:
            self.node.close()

    def __enter__(self) -> Dashboard:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def main(argv: list[str] | None = None) -> int:
    """`archery dashboard [--port N] [--host ADDR] [--operator]`: serve until Ctrl-C."""
    parser = ArgumentParser(
        prog="archery dashboard",
        description="serve a live view of the robot's session in the browser: each "
        "rollout's camera frame with overlay, the whole robot from the side camera, target face, "
        "distance per rollout, liveliness and port rates; a selector for the robots of a fleet; "
        "what the session waits for the operator to do; read-only unless --operator",
    )
    add_network_args(parser, default_mode="client")
    add_nice_arg(parser, OBSERVER_NICE)
    http = parser.add_argument_group("web page")
    http.add_argument(
        "--port",
        type=int_in(0, 65535, "a port number"),
        default=DEFAULT_PORT,
        help=f"default {DEFAULT_PORT}",
    )
    http.add_argument("--host", default="127.0.0.1", help="default 127.0.0.1: this machine only")
    add_operator_arg(http)
    add_wait_arg(parser, robot=False)
    return viewer_main(
        argv, prog="dashboard", parser=parser, check=_check, start=_start, robot=False
    )


def _check(args: argparse.Namespace) -> tuple[NetConfig, _Server]:
    """The node's settings and the HTTP server, bound."""
    host = _check_host(args.host)
    check_server_host(host, args.insecure_network)
    return node_settings(args), bind(host, args.port)


class _Serving:
    """The dashboard, as `viewer_main` runs it."""

    def __init__(self, dashboard: Dashboard) -> None:
        self.dashboard = dashboard

    def ready(self) -> str:
        mode = "operator: its Confirm button" if self.dashboard.operator else "read-only"
        return f"serving {self.dashboard.url} (robot {self.dashboard.node.keys.robot}, {mode})"

    def close(self) -> None:
        self.dashboard.close()


def _start(view: View, server: _Server) -> _Serving:
    lower_priority(view.args.nice)
    return _Serving(Dashboard(view.node.net, server, node=view.node, operator=view.args.operator))
