"""`archery yarp`: its flags, their checks (a bad `--yarp-server`, `--yarp-ip` or `--prefix` is
bad input, exit 2) and the bridge started on the robot (`viewer_main`: the run until Ctrl-C or
SIGTERM); at the end, one line of what it served and refused."""

from __future__ import annotations

import argparse
import ipaddress
from typing import TYPE_CHECKING

from archery.apps.viewer import View, add_wait_arg, viewer_main
from archery.mesh.cliargs import ArgumentParser, seconds
from archery.mesh.netflags import NetConfig, add_network_args
from archery.protocol.errors import ConfigError
from archery.protocol.robotspec import CALL_TIMEOUT

if TYPE_CHECKING:
    from archery.apps.yarp.bridge import YarpBridge
    from archery.apps.yarp.network import NameServer, YarpNetwork

__all__ = ["READY", "build_parser", "main"]

READY = "archery yarp: on YARP"  # the line `archery up --yarp` waits for


def build_parser() -> ArgumentParser:
    """The flags of `archery yarp`."""
    parser = ArgumentParser(
        prog="archery yarp",
        description="the robot as a YARP robot (YARP 3.5's wire, YARP's own library): each "
        "part's control board for remote_controlboard (PREFIX/PART/rpc:i, command:i, state:o, "
        "stateExt:o; degrees), the target camera (PREFIX/cam/target:o), the detector's "
        "measurements (PREFIX/detector/hit:o), the world's events (PREFIX/world/events:o) and "
        "the archery verbs (PREFIX/archery/rpc:i, for `yarp rpc`); read-only unless --operator",
    )
    add_network_args(parser, default_mode="client")
    parser.add_argument("--prefix", help="the robot's YARP name (default /ROBOT, e.g. /icubSim)")
    parser.add_argument(
        "--yarp-server",
        metavar="HOST:PORT",
        help="the YARP name server to register with (default: the one `yarp conf` names if it "
        "answers, else a yarpserver the bridge runs itself on --yarp-ip)",
    )
    parser.add_argument(
        "--yarp-ip",
        default="127.0.0.1",
        help="the address YARP's ports listen on and register (default 127.0.0.1: this "
        "machine only)",
    )
    parser.add_argument(
        "--operator",
        action="store_true",
        help="take position moves, reference speeds and streamed position commands (under the "
        "parts' leases) and the archery verbs; without it each is answered [fail] and nothing "
        "moves (YARP has no authentication: the bridge is the boundary)",
    )
    parser.add_argument(
        "--timeout",
        type=seconds,
        default=CALL_TIMEOUT,
        help=f"wall s for each call to the mesh (default {CALL_TIMEOUT:g})",
    )
    add_wait_arg(parser)
    return parser


def _check(args: argparse.Namespace) -> tuple[NetConfig, tuple[NameServer | None, str]]:
    from archery.apps.yarp.network import parse_server
    from archery.mesh.acl import OPERATOR, VIEWER

    net = NetConfig.from_args(args).with_identity(OPERATOR if args.operator else VIEWER)
    try:
        ipaddress.ip_address(args.yarp_ip)
    except ValueError:
        raise ConfigError(f"--yarp-ip {args.yarp_ip!r}: give an address, e.g. 127.0.0.1") from None
    prefix = args.prefix or f"/{net.robot}"
    parts = prefix.split("/")
    if (
        not prefix.startswith("/")
        or prefix.endswith("/")
        or not all(part.replace("_", "").replace("-", "").isalnum() for part in parts[1:])
    ):
        raise ConfigError(f"--prefix {prefix!r}: give a YARP name such as /icubSim")
    server = parse_server(args.yarp_server) if args.yarp_server else None
    return net, (server, prefix)


def main(argv: list[str] | None = None) -> int:
    """`archery yarp`: keep the robot on YARP's network until Ctrl-C or SIGTERM."""
    return viewer_main(argv, prog="yarp", parser=build_parser(), check=_check, start=_start)


class _OnYarp:
    """The bridge and its YARP network, as `viewer_main` runs them."""

    def __init__(self, network: YarpNetwork, bridge: YarpBridge, view: View) -> None:
        self.network, self.bridge, self.view = network, bridge, view

    def ready(self) -> str:
        mode = "operator" if self.view.args.operator else "read-only"
        server = self.network.server
        return (
            f"{READY.removeprefix('archery yarp: ')} as {self.bridge.prefix} ({mode}), "
            f"{len(self.bridge.ports())} ports on the YARP name server {server} ({server.origin}; "
            f"`yarp conf {server.host} {server.port}` to use it)"
        )

    def close(self) -> str:
        counts = {
            "states": sum(b.counts["states"] for b in self.bridge.boards.values()),
            "requests": sum(b.counts["requests"] for b in self.bridge.boards.values()),
            "refused": sum(b.counts["refused"] for b in self.bridge.boards.values()),
            **self.bridge.counts,
        }
        self.bridge.close()
        self.network.close()
        return "stopped (" + ", ".join(f"{k} {v}" for k, v in counts.items()) + ")"


def _start(view: View, prepared: tuple[NameServer | None, str]) -> _OnYarp:
    from archery.apps.yarp.bridge import YarpBridge
    from archery.apps.yarp.network import YarpNetwork

    server, prefix = prepared
    args = view.args
    network = YarpNetwork(args.yarp_ip, server, args.wait)
    try:
        bridge = YarpBridge(
            network.yarp, view.node, prefix, operator=args.operator, timeout=args.timeout
        )
    except BaseException:
        network.close()
        raise
    return _OnYarp(network, bridge, view)
