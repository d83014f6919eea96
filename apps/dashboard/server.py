"""`archery dashboard`: a live view of a learning session in the browser.

The page shows the camera frame of each rollout with the detector's overlay and a caption
(rollout, θ, r), the scene view (the whole robot from the side camera, while the page shows
it), the target face with each rollout's impact coloured by rollout, the distance-per-rollout
curve, each service's liveliness and each stream port's rate; on a fleet, a selector switches
between the robots alive on the router.

Design: a small page served by the package itself. A standard-library `ThreadingHTTPServer`
serves three files (`static/`: HTML, CSS and a short script that draws the face and the curve
as SVG), a JSON endpoint (`/api/state?robot=R[&scene=1]`) the page polls twice a second (with
`scene=1` while its scene panel is open), the frame as PNG (`/api/frame.png?robot=R`), the
scene view as JPEG (`/api/scene.jpg?robot=R`) and the robots alive (`/api/robots`). Why: no
extra dependency (no web framework, no Rerun), nothing fetched from a CDN so it works offline
and behind a firewall, and any plain browser (or `curl`, or a headless Chromium in the tests)
can read it. The mesh side (`watch.MeshWatch`, one per robot looked at, at most
`MAX_ROBOTS`) is an anonymous node: it subscribes to the rollouts, and calls only the learner's
`status`, the detector's `frame` and, while a page shows it, the camera's `scene`, so watching
never disturbs a session.
"""

from __future__ import annotations

import errno
import ipaddress
import json
import logging
import socket
import sys
import threading
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from typing import Any
from urllib.parse import parse_qs, urlsplit

from apps.dashboard.watch import MeshWatch
from mesh.acl import VIEWER
from mesh.cliargs import ArgumentParser, int_in
from mesh.netflags import NetConfig, add_network_args
from mesh.node import Node
from mesh.priority import OBSERVER_NICE, add_nice_arg, lower_priority
from mesh.signals import shutdown_on_signals
from protocol.errors import ArcheryError, ConfigError
from protocol.exit_status import for_error
from protocol.keys import validate_robot

__all__ = ["DEFAULT_PORT", "MAX_ROBOTS", "Dashboard", "main"]

log = logging.getLogger("archery.dashboard")

DEFAULT_PORT = 8765
MAX_ROBOTS = 32  # robots one dashboard follows at most (a watch each)
_TYPES = {".html": "text/html", ".js": "text/javascript", ".css": "text/css"}
_PAGES = {"/": "index.html", "/index.html": "index.html"}


def _static(name: str) -> bytes | None:
    """A file of the package's `static/` folder, or None when there is no such file."""
    if "/" in name or name.startswith("."):
        return None
    path = resources.files("apps.dashboard").joinpath("static", name)
    return path.read_bytes() if path.is_file() else None


class _Server(ThreadingHTTPServer):
    daemon_threads = True
    dashboard: Dashboard


class _Handler(BaseHTTPRequestHandler):
    server: _Server
    server_version = "archery-dashboard"

    def log_message(self, format: str, *args: Any) -> None:
        log.debug("%s " + format, self.address_string(), *args)

    def _send(self, status: int, body: bytes, ctype: str) -> None:
        self.send_response(status)
        self.send_header("Content-Type", ctype)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        self.end_headers()
        if self.command != "HEAD":
            self.wfile.write(body)

    def do_HEAD(self) -> None:
        self.do_GET()

    def do_GET(self) -> None:
        url = urlsplit(self.path)
        path, query = url.path, parse_qs(url.query)
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

    def _api(self, path: str, query: dict[str, list[str]]) -> None:
        dashboard = self.server.dashboard
        if path == "/api/robots":
            body = json.dumps(dashboard.robots()).encode()
            self._send(HTTPStatus.OK, body, "application/json")
            return
        try:
            watch = dashboard.watch(query.get("robot", [None])[0])
        except ArcheryError as exc:
            body = json.dumps({"error": str(exc)}).encode()
            self._send(HTTPStatus.BAD_REQUEST, body, "application/json")
            return
        if path == "/api/state":
            if query.get("scene") == ["1"]:
                watch.want_scene()
            body = json.dumps(watch.snapshot(), allow_nan=False).encode()
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
            f"e.g. 127.0.0.1 (this machine only) or 0.0.0.0 (every interface)"
        ) from None


def bind(host: str, port: int) -> _Server:
    """The HTTP server listening on `host:port` (port 0: a free one), not serving yet.

    Raises:
        ConfigError: the port is taken, or the address is not this machine's.
    """
    server_class = type(
        "_BoundServer",
        (_Server,),
        {"address_family": socket.AF_INET6 if ":" in host else socket.AF_INET},
    )
    try:
        return server_class((host, port), _Handler)
    except OSError as exc:
        if exc.errno == errno.EADDRINUSE:
            raise ConfigError(
                f"--port {port}: address {host}:{port} is in use by another program; "
                f"choose another --port (0 picks a free one)"
            ) from None
        raise ConfigError(f"--host {host} --port {port}: cannot listen: {exc.strerror}") from None


class Dashboard:
    """The server and the mesh watches together (the node's robot's, and each other robot's
    once a page asks for it); a context manager (tests use it directly)."""

    def __init__(self, net: NetConfig, server: _Server) -> None:
        self.server = server
        try:
            self.node = Node(None, net)
        except BaseException:
            self.server.server_close()
            raise
        self._lock = threading.Lock()
        self._watches = {net.robot: MeshWatch(self.node)}
        self.server.dashboard = self
        self._thread = threading.Thread(
            target=self.server.serve_forever, name="dashboard-http", daemon=True
        )
        self._thread.start()

    @property
    def url(self) -> str:
        address, port = self.server.server_address[:2]
        host = str(address)  # as an f-string shows it
        shown = f"[{host}]" if ":" in host else host
        return f"http://{shown}:{port}/"

    def watch(self, robot: str | None = None) -> MeshWatch:
        """The watch of `robot` (None: the dashboard's own robot), started on first use.

        Raises:
            KeyNameError: not a robot name.
            ConfigError: `MAX_ROBOTS` robots are watched already.
        """
        robot = self.node.keys.robot if robot is None else validate_robot(robot)
        with self._lock:
            watch = self._watches.get(robot)
            if watch is None:
                if len(self._watches) >= MAX_ROBOTS:
                    raise ConfigError(
                        f"this dashboard follows {MAX_ROBOTS} robots already; start another "
                        f"`archery dashboard --robot {robot}` for more"
                    )
                watch = self._watches[robot] = MeshWatch(self.node, robot=robot)
            return watch

    def robots(self) -> dict[str, Any]:
        """{"default": the dashboard's robot, "robots": every robot with a live service on the
        router and every robot watched, sorted}."""
        alive = set(self.node.alive_robots(timeout=1.0))
        with self._lock:
            watched = set(self._watches)
        return {"default": self.node.keys.robot, "robots": sorted(alive | watched)}

    def close(self) -> None:
        self.server.shutdown()
        self.server.server_close()
        with self._lock:
            watches = list(self._watches.values())
        for watch in watches:
            watch.close()
        self.node.close()

    def __enter__(self) -> Dashboard:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def main(argv: list[str] | None = None) -> int:
    """`archery dashboard [--port N] [--host ADDR]`: serve the live view until Ctrl-C."""
    parser = ArgumentParser(
        prog="archery dashboard",
        description="serve a live view of the robot's session in the browser: each "
        "rollout's camera frame with overlay, the whole robot from the side camera, target face, "
        "distance per rollout, liveliness and port rates; a selector for the robots of a fleet",
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
    args = parser.parse_args(argv)
    try:
        net = NetConfig.from_args(args).with_identity(VIEWER)
        host = _check_host(args.host)
        server = bind(host, args.port)
    except ArcheryError as exc:
        print(f"archery dashboard: {exc}", file=sys.stderr)
        return 2
    lower_priority(args.nice)
    stop = shutdown_on_signals()
    try:
        with Dashboard(net, server) as dash:
            print(f"archery dashboard: serving {dash.url} (robot {net.robot})", flush=True)
            stop.wait()
    except ArcheryError as exc:
        print(f"archery dashboard: {exc}", file=sys.stderr)
        return for_error(exc.code)
    return 0
