"""`archery yarp`: its flags, their checks (a bad `--yarp-server`, `--yarp-ip` or `--prefix`, an
address off loopback in plain mode, a `--secure` deployment without YARP's key: bad input, exit
2) and the bridge started on the robot (`viewer_main`: the run until Ctrl-C or SIGTERM), its
YARP side by one deadline, `--wait` from the start, whatever the name server does (a start
stuck inside YARP's own calls ends the process: one line, exit 1); at the end, one line of what
it served and refused."""

from __future__ import annotations

import argparse
import ipaddress
import os
import sys
import threading
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

from archery.apps.viewer import View, add_wait_arg, viewer_main
from archery.mesh.cliargs import ArgumentParser, seconds
from archery.mesh.netflags import NetConfig, add_network_args, check_server_host
from archery.protocol.errors import ArcheryError, ConfigError
from archery.protocol.exit_status import FAILURE
from archery.protocol.robotspec import CALL_TIMEOUT

if TYPE_CHECKING:
    from archery.apps.yarp.auth import YarpKey
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
        "machine only; another needs --secure, or --insecure-network)",
    )
    parser.add_argument(
        "--operator",
        action="store_true",
        help="take position moves, reference speeds and streamed position commands (under the "
        "parts' leases) and the archery verbs; without it each is answered [fail] and nothing "
        "moves. In plain mode every local user's YARP client may then move the robot; with "
        "--secure DIR only YARP processes holding DIR/yarp/auth.conf connect at all",
    )
    parser.add_argument(
        "--timeout",
        type=seconds,
        default=CALL_TIMEOUT,
        help=f"wall s for each call to the mesh (default {CALL_TIMEOUT:g})",
    )
    add_wait_arg(parser)
    return parser


@dataclass(frozen=True)
class _Prepared:
    """What `_check` made of the flags for `_start`."""

    server: NameServer | None
    prefix: str
    key: YarpKey | None
    deadline: float  # time.monotonic() by which the start ends (--wait from the flags' check)


def _check(args: argparse.Namespace) -> tuple[NetConfig, _Prepared]:
    from archery.apps.yarp.auth import read_key
    from archery.apps.yarp.network import parse_server
    from archery.mesh.acl import OPERATOR, VIEWER

    deadline = time.monotonic() + args.wait
    net = NetConfig.from_args(args).with_identity(OPERATOR if args.operator else VIEWER)
    try:
        ipaddress.ip_address(args.yarp_ip)
    except ValueError:
        raise ConfigError(f"--yarp-ip {args.yarp_ip!r}: give an address, e.g. 127.0.0.1") from None
    if args.secure is None:
        try:
            check_server_host(args.yarp_ip, args.insecure_network)
        except ConfigError:
            raise ConfigError(
                f"--yarp-ip {args.yarp_ip}: plain mode's YARP authenticates no one, and this "
                "address is reachable from other machines, which could then read (and with "
                "--operator move) the robot. Keep 127.0.0.1, give --secure DIR (YARP's own "
                "authentication with the deployment's key), or --insecure-network on a network "
                "you trust"
            ) from None
    prefix = args.prefix or f"/{net.robot}"
    parts = prefix.split("/")
    if (
        not prefix.startswith("/")
        or prefix.endswith("/")
        or not all(part.replace("_", "").replace("-", "").isalnum() for part in parts[1:])
    ):
        raise ConfigError(f"--prefix {prefix!r}: give a YARP name such as /icubSim")
    server = parse_server(args.yarp_server) if args.yarp_server else None
    key = read_key(args.secure) if args.secure is not None else None
    return net, _Prepared(server, prefix, key, deadline)


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
        assert server is not None
        key = self.network.key
        auth = f"; every connection authenticated with {key.path}" if key else ""
        return (
            f"{READY.removeprefix('archery yarp: ')} as {self.bridge.prefix} ({mode}), "
            f"{len(self.bridge.ports())} ports on the YARP name server {server} ({server.origin}; "
            f"`yarp conf {server.host} {server.port}` to use it{auth})"
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


_GRACE = 1.0  # s past the deadline for the start's own checks to end it in their words


def _start(view: View, prepared: _Prepared) -> _OnYarp:
    """The YARP side started in a thread of its own, given up at the deadline: YARP's calls
    (initialising, registering) wait on the name server without a bound of their own."""
    from archery.apps.yarp.network import YarpNetwork

    network = YarpNetwork(view.args.yarp_ip, prepared.server, prepared.key)
    outcome: list[_OnYarp | BaseException] = []

    def run() -> None:
        try:
            outcome.append(_open(view, network, prepared))
        except BaseException as exc:  # handed to the caller
            outcome.append(exc)

    thread = threading.Thread(target=run, name="yarp-start", daemon=True)
    thread.start()
    thread.join(max(prepared.deadline - time.monotonic(), 0.0) + _GRACE)
    if not outcome:
        _give_up(network, view.args.wait)
    if isinstance(outcome[0], BaseException):
        raise outcome[0]
    return outcome[0]


def _open(view: View, network: YarpNetwork, prepared: _Prepared) -> _OnYarp:
    from archery.apps.yarp.bridge import YarpBridge

    args = view.args
    try:
        network.start(prepared.deadline)
        bridge = YarpBridge(
            network.yarp, view.node, prepared.prefix, operator=args.operator, timeout=args.timeout
        )
    except BaseException:
        network.close()
        raise
    try:
        network.stage = "checking the bridge's registrations"
        _registered(network, bridge)
        if prepared.key is not None:
            network.stage = "checking that the bridge's ports authenticate"
            _demands(bridge, prepared.key, prepared.deadline)
    except BaseException:
        bridge.close()
        network.close()
        raise
    return _OnYarp(network, bridge, view)


def _registered(network: YarpNetwork, bridge: YarpBridge) -> None:
    """Check that the name server holds each of the bridge's ports at `--yarp-ip`: YARP opens a
    port whose registration failed anonymously, on an address of its own choosing.

    Raises:
        ArcheryError: one is not so registered.
    """
    for name in bridge.ports():
        contact = network.yarp.Network.queryName(name)
        if not contact.isValid() or contact.getHost() != network.ip:
            raise ArcheryError(
                f"the YARP name server at {network.server} did not register {name} at "
                f"{network.ip}: it answers, but not as a name server"
            )


def _demands(bridge: YarpBridge, key: YarpKey, deadline: float) -> None:
    """Check that the bridge's ports demand `key` of whoever connects, as YARP's handshake
    from here shows: YARP reads the first auth.conf it finds, once per process.

    Raises:
        ArcheryError: they do not.
    """
    from archery.apps.yarp.auth import NotAuthenticated, check_port

    where = bridge.archery.port.where()
    try:
        check_port(where.getHost(), where.getPort(), key, max(deadline - time.monotonic(), 0.5))
    except NotAuthenticated as exc:
        raise ArcheryError(
            f"the bridge's YARP ports do not demand the key of {key.path} ({exc}): an auth.conf "
            "in the working folder? YARP reads that one first"
        ) from None


def _give_up(network: YarpNetwork, wait: float) -> None:
    """End the process: the start is stuck inside YARP's own call, which no one can interrupt
    and which holds YARP's locks, so nothing of YARP's may run again in this process."""
    print(
        f"archery yarp: the start did not end within --wait {wait:g} s: stuck {network.stage} "
        f"with the YARP name server at {network.server}, which answered at first, then not "
        "as a name server",
        file=sys.stderr,
        flush=True,
    )
    network.abandon()
    sys.stdout.flush()
    os._exit(FAILURE)
