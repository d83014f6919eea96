"""`archery foxglove`: its flags, the checks of where it listens, and the bridge started on the
robot (`viewer_main`: the run until Ctrl-C or SIGTERM)."""

from __future__ import annotations

import argparse
import errno
import secrets
import socket
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from archery.apps.foxglove.front_door import MAX_CONNECTIONS
from archery.apps.foxglove.upgrade import check_origin_flag
from archery.apps.viewer import View, add_wait_arg, viewer_main
from archery.mesh.cliargs import ArgumentParser, add_force_arg, check_output_file
from archery.mesh.netflags import NetConfig, add_network_args, check_server_host
from archery.protocol.errors import ConfigError
from archery.protocol.exit_status import BAD_INPUT, OK

if TYPE_CHECKING:
    from archery.apps.foxglove.bridge import Bridge

__all__ = ["check_listen", "main"]

DEFAULT_PORT = 8765  # Foxglove's usual WebSocket port


def check_listen(host: str, port: int) -> None:
    """Raise ConfigError (one line) unless a server can listen on `host`:`port`: the host must
    name this machine and the port be free (0: any free port)."""
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except socket.gaierror as exc:
        raise ConfigError(f"--host {host!r}: not a host name or address ({exc.strerror})") from None
    family, kind, proto, _, address = infos[0]
    with socket.socket(family, kind, proto) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind(address)
        except OSError as exc:
            if exc.errno == errno.EADDRINUSE:
                raise ConfigError(
                    f"--port {port}: already in use on {host} (choose another, or 0 for any)"
                ) from None
            if exc.errno == errno.EADDRNOTAVAIL:
                raise ConfigError(
                    f"--host {host!r}: not an address of this machine (a server listens only "
                    "on its own addresses, e.g. 127.0.0.1)"
                ) from None
            raise ConfigError(f"--host {host!r} --port {port}: cannot listen: {exc}") from None


def _url_host(host: str) -> str:
    """`host` as a URL names it (an IPv6 address in brackets)."""
    return f"[{host}]" if ":" in host else host


def build_parser() -> ArgumentParser:
    """The flags of `archery foxglove`."""
    parser = ArgumentParser(
        prog="archery foxglove",
        description="a live Foxglove WebSocket server that follows a running mesh: the iCub in "
        "3D, the camera with the detector's marks, the learning curve and the world's events "
        "(open ws://HOST:PORT in the Foxglove app)",
    )
    add_network_args(parser, default_mode="client")
    parser.add_argument("--host", default="127.0.0.1", help="where to listen (default 127.0.0.1)")
    parser.add_argument(
        "--port", type=int, default=DEFAULT_PORT, help=f"(default {DEFAULT_PORT}; 0: any free)"
    )
    parser.add_argument(
        "--jpeg", action="store_true", help="send the camera's frames as JPEG (less bandwidth)"
    )
    parser.add_argument(
        "--operator",
        action="store_true",
        help="let clients call the learner's status/start/stop and the robot's reset, and set "
        "the wind (in secure mode: as the operator identity); default read-only",
    )
    parser.add_argument(
        "--allow-origin",
        action="append",
        default=[],
        metavar="URL",
        help="also accept WebSocket connections from pages of this origin (e.g. "
        "https://viewer.example.org; repeatable); the Foxglove app's own and this machine's "
        "pages are always accepted, any other page is refused",
    )
    parser.add_argument(
        "--max-clients",
        type=int,
        default=MAX_CONNECTIONS,
        help=f"connections served at once; the next one is refused (default {MAX_CONNECTIONS})",
    )
    parser.add_argument(
        "--layout",
        metavar="FILE.json",
        help="write the bridge's Foxglove layout to this file (import it once) and exit",
    )
    add_force_arg(parser, "an existing --layout file")
    add_wait_arg(parser)
    return parser


def _write_layout(path: str, force: bool) -> int:
    from archery.apps.foxglove.layout import layout

    try:
        check_output_file(path, "--layout", (".json",), force=force)
    except ConfigError as exc:
        print(f"archery foxglove: {exc}", file=sys.stderr)
        return BAD_INPUT
    Path(path).write_text(layout().to_json() + "\n", encoding="utf-8")
    print(f"archery foxglove: wrote the layout to {path} (import it in the Foxglove app)")
    return OK


def main(argv: list[str] | None = None) -> int:
    """`archery foxglove`: serve the mesh to Foxglove clients until Ctrl-C or SIGTERM."""
    return viewer_main(
        argv,
        prog="foxglove",
        parser=build_parser(),
        check=_check,
        start=_start,
        early=lambda args: None if args.layout is None else _write_layout(args.layout, args.force),
    )


def _check(args: argparse.Namespace) -> tuple[NetConfig, str | None]:
    """The node's settings and the operator's token (None: read-only)."""
    from archery.mesh.acl import OPERATOR, VIEWER

    if not 0 <= args.port <= 65535:
        raise ConfigError(f"--port {args.port}: give a port number from 0 to 65535")
    if args.max_clients < 1:
        raise ConfigError(f"--max-clients {args.max_clients}: give at least 1")
    for origin in args.allow_origin:
        check_origin_flag(origin)
    check_server_host(args.host, args.insecure_network)
    check_listen(args.host, args.port)
    net = NetConfig.from_args(args).with_identity(OPERATOR if args.operator else VIEWER)
    if args.operator and net.secure and net.identity != OPERATOR:
        raise ConfigError(
            f"--operator in secure mode runs as identity {OPERATOR!r}, not {net.identity!r}"
        )
    return net, secrets.token_urlsafe(24) if args.operator else None


class _Serving:
    """The bridge, as `viewer_main` runs it."""

    def __init__(self, bridge: Bridge, view: View, token: str | None) -> None:
        self.bridge = bridge
        self.view = view
        self.token = token

    def ready(self) -> str:
        args = self.view.args
        mode = "operator" if args.operator else "read-only"
        where = f"ws://{_url_host(args.host)}:{self.bridge.port}/"
        if self.token is not None:
            where += f"?token={self.token}"
        return f"serving {self.view.node.keys.robot} on {where} ({mode})"

    def close(self) -> None:
        self.bridge.close()


def _start(view: View, token: str | None) -> _Serving:
    from archery.apps.foxglove.bridge import Bridge
    from archery.sim.urdf import mesh_root, urdf_text

    assert view.frames is not None
    args = view.args
    bridge = Bridge(
        view.node,
        view.frames,
        urdf_text(),
        mesh_root(),
        host=args.host,
        port=args.port,
        jpeg=args.jpeg,
        operator=args.operator,
        token=token,
        origins=tuple(args.allow_origin),
        max_clients=args.max_clients,
    )
    return _Serving(bridge, view, token)
