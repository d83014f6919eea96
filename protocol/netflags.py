"""The network flags of every process (--connect, --listen, --mode, --robot); the Zenoh config.

Every process listens and connects only where it is told. By default a process is a Zenoh
client of the router it is given: it opens no listening socket and links to nothing else. In
every mode multicast scouting and gossip are
off, and a peer's listen endpoints are set explicitly (none by default; a Zenoh peer would
otherwise listen on every interface and connect to whatever addresses other peers gossip). So
every process reaches the mesh through the router it is given, all traffic meets there
(containers do not carry multicast, and parallel test runs must never meet), and nothing opens
a socket on any address but the ones on the command line. Shared-memory transport is off too:
it was reported to drop large messages under CPU stalls.
"""

from __future__ import annotations

import argparse
import json
import re
from dataclasses import dataclass

import zenoh

from protocol.cliargs import clean_zenoh_error
from protocol.errors import ConfigError
from protocol.keys import DEFAULT_ROBOT, validate_robot
from protocol.logs import add_log_args

__all__ = ["DEFAULT_ROUTER", "MODES", "NetConfig", "add_network_args", "open_session"]

DEFAULT_ROUTER = "tcp/127.0.0.1:7447"
MODES = ("peer", "client", "router")
_ENDPOINT = re.compile(r"^(tcp|udp|tls|quic|ws|unixsock-stream)/\S+$")


@dataclass(frozen=True)
class NetConfig:
    """Where a process meets the mesh.

    Attributes:
        connect: endpoints to connect to (e.g. "tcp/127.0.0.1:7447"); a router, usually.
        listen: endpoints to listen on (a router, or a peer others should reach).
        mode: "client" (default: every link goes to the router), "peer" (also links directly to
            the peers it is given with --connect and accepts links on --listen) or "router".
        robot: key prefix of the robot this process belongs to (default "icubSim").
    """

    connect: tuple[str, ...] = (DEFAULT_ROUTER,)
    listen: tuple[str, ...] = ()
    mode: str = "client"
    robot: str = DEFAULT_ROBOT

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ConfigError(f"--mode {self.mode!r} is not one of {', '.join(MODES)}")
        for flag, endpoints in (("--connect", self.connect), ("--listen", self.listen)):
            for endpoint in endpoints:
                if not isinstance(endpoint, str) or not _ENDPOINT.match(endpoint):
                    raise ConfigError(
                        f"{flag} {endpoint!r} is not a Zenoh endpoint; use PROTO/ADDRESS, "
                        f"e.g. {DEFAULT_ROUTER}"
                    )
        if self.mode == "client" and not self.connect:
            raise ConfigError("--mode client needs at least one --connect endpoint (a router)")
        try:
            validate_robot(self.robot)
        except ValueError as exc:
            raise ConfigError(f"--robot: {exc}") from None

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> NetConfig:
        """Build from the flags added by `add_network_args`."""
        connect = tuple(args.connect) if args.connect else ()
        if not connect and args.mode != "router":
            connect = (DEFAULT_ROUTER,)
        return cls(
            connect=connect,
            listen=tuple(args.listen or ()),
            mode=args.mode,
            robot=args.robot,
        )

    def zenoh_config(self) -> zenoh.Config:
        """The Zenoh configuration for these settings."""
        config = zenoh.Config()
        config.insert_json5("mode", json.dumps(self.mode))
        config.insert_json5("connect/endpoints", json.dumps(list(self.connect)))
        # Explicit, even when empty: a Zenoh peer otherwise listens on every interface.
        config.insert_json5("listen/endpoints", json.dumps(list(self.listen)))
        config.insert_json5("scouting/multicast/enabled", "false")
        # No gossip: a process never learns other processes' addresses, so it connects only to
        # the endpoints it was given and all traffic meets at the router.
        config.insert_json5("scouting/gossip/enabled", "false")
        config.insert_json5("transport/shared_memory/enabled", "false")
        return config


def add_network_args(parser: argparse.ArgumentParser, *, default_mode: str = "client") -> None:
    """Add --connect (repeatable), --listen (repeatable), --mode, --robot and the logging flags
    (--log-level, -v: applied by the `archery` entry point, see `protocol.logs`)."""
    add_log_args(parser)
    group = parser.add_argument_group("network")
    group.add_argument(
        "--connect",
        action="append",
        metavar="ENDPOINT",
        help=f"Zenoh endpoint to connect to, repeatable (default {DEFAULT_ROUTER})",
    )
    group.add_argument(
        "--listen", action="append", metavar="ENDPOINT", help="endpoint to listen on, repeatable"
    )
    group.add_argument("--mode", choices=MODES, default=default_mode, help="Zenoh session mode")
    group.add_argument(
        "--robot", default=DEFAULT_ROBOT, help=f"robot key prefix (default {DEFAULT_ROBOT})"
    )


def open_session(net: NetConfig) -> zenoh.Session:
    """Open a Zenoh session for `net`.

    Raises:
        ConfigError: the session cannot open (in client mode: no router reachable).
    """
    try:
        return zenoh.open(net.zenoh_config())
    except zenoh.ZError as exc:
        if net.mode == "router" or not net.connect:
            raise ConfigError(
                f"cannot open a Zenoh {net.mode} session listening on "
                f"{', '.join(net.listen) or '(no endpoint)'}: {clean_zenoh_error(exc)}. Is "
                f"another router running there? Use --listen with a free port"
            ) from None
        where = ", ".join(net.connect)
        listen = f" listening on {', '.join(net.listen)}" if net.listen else ""
        raise ConfigError(
            f"cannot open a Zenoh {net.mode} session{listen} connecting to {where}: "
            f"{clean_zenoh_error(exc)}. Is a router running there? Start one with "
            f"`archery router --listen {net.connect[0] if net.connect else 'ENDPOINT'}`"
        ) from None
