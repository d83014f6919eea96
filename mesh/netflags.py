"""The network flags of every process (--connect, --listen, --mode, --robot); the Zenoh config.

Every process listens and connects only where it is told: by default a Zenoh client of the
router it is given, with multicast scouting, gossip and shared memory off (the docstring of
`NetConfig.zenoh_config` says why), and with `--secure DIR` mutual TLS on every link
(`NetConfig._tls_config`). docs/commands.md, 'Network flags and logs', tells the flags, and
docs/secure.md the secure deployment.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime as dt
import ipaddress
import json
import re
import socket
from dataclasses import dataclass
from pathlib import Path

import zenoh

from archery.mesh.cliargs import clean_zenoh_error
from archery.mesh.logs import add_log_args
from archery.protocol.errors import ConfigError, Unreachable
from archery.protocol.keys import DEFAULT_ROBOT, validate_robot

__all__ = [
    "DEFAULT_ROUTER",
    "DEFAULT_SECURE_ROUTER",
    "MODES",
    "NetConfig",
    "add_network_args",
    "check_server_host",
    "listens",
    "open_session",
]

DEFAULT_ROUTER = "tcp/127.0.0.1:7447"
DEFAULT_SECURE_ROUTER = "tls/127.0.0.1:7447"
_IDENTITY = re.compile(r"^[A-Za-z][A-Za-z0-9_\-]{0,63}$")
MODES = ("peer", "client", "router")
_ENDPOINT = re.compile(r"^(tcp|udp|tls|quic|ws|unixsock-stream)/\S+$")
_PORT = re.compile(r"^(?:tcp|udp|tls|quic|ws)/.*:(\d+)$")  # the port of an IP endpoint


@dataclass(frozen=True)
class NetConfig:
    """Where a process meets the mesh.

    Attributes:
        connect: endpoints to connect to (e.g. "tcp/127.0.0.1:7447"); a router, usually.
        listen: endpoints to listen on (a router, or a peer others should reach).
        mode: "client" (default: every link goes to the router), "peer" (also links directly to
            the peers it is given with --connect and accepts links on --listen) or "router".
        robot: key prefix of the robot this process belongs to (default "icubSim").
        secure: a deployment directory (`archery keys init`): mutual TLS with its CA and, for
            a router, its access control; None: plain links.
        identity: whose certificate to present (`DIR/NAME.pem`); None: the process's default
            (`with_identity`).
        replace: a service whose name is taken asks the live instance to stop and starts
            (otherwise it refuses to start).
        insecure_network: in plain mode, allow `listen` beyond loopback (anyone who reaches
            that address may then publish, serve and call anything).
    """

    connect: tuple[str, ...] = (DEFAULT_ROUTER,)
    listen: tuple[str, ...] = ()
    mode: str = "client"
    robot: str = DEFAULT_ROBOT
    secure: str | None = None
    identity: str | None = None
    replace: bool = False
    insecure_network: bool = False

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
                port = _PORT.search(endpoint)
                if port is not None and not 0 <= int(port.group(1)) <= 65535:
                    raise ConfigError(
                        f"{flag} {endpoint!r}: port {port.group(1)} is not a port number "
                        "(0 to 65535)"
                    )
        if self.mode == "client" and not self.connect:
            raise ConfigError("--mode client needs at least one --connect endpoint (a router)")
        try:
            validate_robot(self.robot)
        except ValueError as exc:
            raise ConfigError(f"--robot: {exc}") from None
        if self.identity is not None and not _IDENTITY.match(self.identity):
            raise ConfigError(f"--identity {self.identity!r} is not a valid identity name")
        if self.secure is None and not self.insecure_network:
            for endpoint in self.listen:
                if not _loopback(endpoint):
                    raise ConfigError(
                        f"--listen {endpoint}: plain mode trusts every peer, and this address "
                        "is reachable from other machines, which could then move the robot. Use "
                        "--secure DIR (mutual TLS and access control: `archery keys init DIR`), "
                        "listen on 127.0.0.1, or give --insecure-network on a network you trust "
                        "(e.g. a container network)"
                    )
        if self.secure is not None:
            for flag, endpoints in (("--connect", self.connect), ("--listen", self.listen)):
                for endpoint in endpoints:
                    if not endpoint.startswith("tls/"):
                        raise ConfigError(
                            f"{flag} {endpoint!r}: --secure allows only mutual-TLS endpoints; "
                            f"use tls/HOST:PORT (e.g. {DEFAULT_SECURE_ROUTER}), never plain "
                            f"{endpoint.split('/', 1)[0]}/"
                        )

    def with_identity(self, default: str) -> NetConfig:
        """These settings with `identity` set to `default` unless --identity chose one."""
        if self.identity is not None:
            return self
        return dataclasses.replace(self, identity=default)

    def _credential(self, name: str) -> str:
        assert self.secure is not None
        path = Path(self.secure) / name
        if not path.is_file():
            raise ConfigError(
                f"--secure {self.secure}: no {name} (identity {self.identity!r}); create the "
                f"deployment with `archery keys init {self.secure}`"
            )
        return str(path.resolve())

    def _tls_config(self, config: zenoh.Config) -> None:
        """Mutual TLS on every link, for `--secure DIR` (a deployment made by `archery keys init
        DIR`): endpoints must be `tls/...`, the process presents the certificate of its
        identity (the service's name, `operator`, `viewer` or `replay` for the tools, `router`
        for the router; `--identity NAME` overrides it), verifies the other end against the
        deployment's CA, and a router enforces the access control of `DIR/acl.json5`."""
        if self.identity is None:
            raise ConfigError("--secure needs an identity (--identity NAME)")
        ca = self._credential("ca.pem")
        key = self._credential(f"{self.identity}.key")
        cert = self._credential(f"{self.identity}.pem")
        tls = {
            "root_ca_certificate": ca,
            "enable_mtls": True,
            "listen_private_key": key,
            "listen_certificate": cert,
            "connect_private_key": key,
            "connect_certificate": cert,
            "verify_name_on_connect": True,
            "close_link_on_expiration": True,
        }
        for name, value in tls.items():
            config.insert_json5(f"transport/link/tls/{name}", json.dumps(value))
        if self.mode == "router":
            acl = Path(self._credential("acl.json5")).read_text()
            try:
                config.insert_json5("access_control", acl)
            except zenoh.ZError as exc:
                raise ConfigError(f"{self.secure}/acl.json5 is not a valid policy: {exc}") from None

    def expired_hint(self) -> str:
        """Why a secure session may have failed: a missing, expired or not-yet-valid
        certificate of this identity ("" when none of these is the case)."""
        if self.secure is None or self.identity is None:
            return ""
        from cryptography import x509

        try:
            path = Path(self.secure) / f"{self.identity}.pem"
            cert = x509.load_pem_x509_certificate(path.read_bytes())
        except (OSError, ValueError) as exc:
            return f" (cannot read the certificate of {self.identity!r}: {exc})"
        now = dt.datetime.now(dt.UTC)
        if cert.not_valid_after_utc < now:
            return f" (the certificate {path} expired on {cert.not_valid_after_utc} UTC)"
        if cert.not_valid_before_utc > now:
            return f" (the certificate {path} is valid only from {cert.not_valid_before_utc} UTC)"
        return ""

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> NetConfig:
        """Build from the flags added by `add_network_args`."""
        secure = getattr(args, "secure", None)
        connect = tuple(args.connect) if args.connect else ()
        if not connect and args.mode != "router":
            connect = (DEFAULT_SECURE_ROUTER if secure else DEFAULT_ROUTER,)
        return cls(
            connect=connect,
            listen=tuple(args.listen or ()),
            mode=args.mode,
            robot=args.robot,
            secure=secure,
            identity=getattr(args, "identity", None),
            replace=bool(getattr(args, "replace", False)),
            insecure_network=bool(getattr(args, "insecure_network", False)),
        )

    def zenoh_config(self) -> zenoh.Config:
        """The Zenoh configuration for these settings.

        By default a process is a Zenoh client of the router it is given: it opens no listening
        socket and links to nothing else. In every mode multicast scouting and gossip are off,
        and a peer's listen endpoints are set explicitly (none by default; a Zenoh peer would
        otherwise listen on every interface and connect to whatever addresses other peers
        gossip). So every process reaches the mesh through the router it is given, all traffic
        meets there (containers do not carry multicast, and parallel test runs must never
        meet), and nothing opens a socket on any address but the ones on the command line.
        Shared-memory transport is off too: it was reported to drop large messages under CPU
        stalls.
        """
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
        if self.secure is not None:
            self._tls_config(config)
        return config


def add_network_args(parser: argparse.ArgumentParser, *, default_mode: str = "client") -> None:
    """Add --connect (repeatable), --listen (repeatable), --mode, --robot, --secure,
    --identity and the logging flag (--log-level: applied by the `archery` entry point, see
    `mesh.logs`)."""
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
    group.add_argument(
        "--secure",
        metavar="DIR",
        help="mutual TLS (and, for a router, access control) with the credentials of DIR "
        "(`archery keys init DIR`); endpoints must be tls/..., default "
        f"{DEFAULT_SECURE_ROUTER}",
    )
    group.add_argument(
        "--insecure-network",
        action="store_true",
        help="allow --listen (plain mode) or a server's --host beyond loopback (anyone reaching "
        "it may see or move the robot; prefer --secure)",
    )
    group.add_argument(
        "--identity",
        metavar="NAME",
        help="with --secure: the identity to present (default: the service's name, "
        "`operator` for tools, `router` for the router)",
    )


def check_server_host(host: str, insecure_network: bool) -> None:
    """Raise ConfigError (one line) when a local server (the dashboard, the Foxglove bridge) is
    asked to listen on `host` beyond loopback without `--insecure-network`: the mesh's rule for
    `--listen`, since these servers authenticate no one and a page or client that reaches them
    sees the robot (and, with --operator, commands it)."""
    if insecure_network or _loopback(f"tcp/{host}:0"):
        return
    raise ConfigError(
        f"--host {host}: this server authenticates no one, and this address is reachable from "
        "other machines. Listen on 127.0.0.1 (the default; reach it from elsewhere through an "
        "SSH tunnel), or give --insecure-network on a network you trust (e.g. a container "
        "network)"
    )


def _loopback(endpoint: str) -> bool:
    """Whether a listen endpoint is reachable from this machine only (loopback, a Unix socket)."""
    proto, _, address = endpoint.partition("/")
    if proto == "unixsock-stream":
        return True
    host = address.rpartition(":")[0].strip("[]") or address
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False  # a host name: it may resolve to any interface


def open_session(net: NetConfig) -> zenoh.Session:
    """Open a Zenoh session for `net`.

    Raises:
        ConfigError: the session cannot open (in client mode: no router reachable).
    """
    config = net.zenoh_config()
    try:
        return zenoh.open(config)
    except zenoh.ZError as exc:
        if net.mode == "router" or not net.connect:
            raise ConfigError(
                f"cannot open a Zenoh {net.mode} session listening on "
                f"{', '.join(net.listen) or '(no endpoint)'}: {clean_zenoh_error(exc)}. Is "
                f"another router running there? Use --listen with a free port"
            ) from None
        where = ", ".join(net.connect)
        listen = f" listening on {', '.join(net.listen)}" if net.listen else ""
        if net.secure is not None:
            raise Unreachable(
                f"cannot open a secure Zenoh {net.mode} session as {net.identity!r} connecting "
                f"to {where}: {clean_zenoh_error(exc)}{net.expired_hint()}. Is a router with "
                f"the same deployment ({net.secure}) running there (`archery router --secure "
                f"{net.secure} --listen ENDPOINT`)?"
            ) from None
        tls = [e for e in net.connect if e.startswith("tcp/") and listens(e)]
        if tls:
            raise Unreachable(
                f"cannot open a Zenoh {net.mode} session{listen} connecting to {where}: "
                f"{clean_zenoh_error(exc)}. Something listens on {tls[0]} but does not answer "
                f"plain Zenoh: a secure router? Connect with --secure DIR --connect "
                f"tls/{tls[0].split('/', 1)[1]}"
            ) from None
        raise Unreachable(
            f"cannot open a Zenoh {net.mode} session{listen} connecting to {where}: "
            f"{clean_zenoh_error(exc)}. Is a router running there? Start one with "
            f"`archery router --listen {net.connect[0] if net.connect else 'ENDPOINT'}`"
        ) from None


def listens(endpoint: str, timeout: float = 0.5) -> bool:
    """Whether a TCP connection to a `PROTO/HOST:PORT` endpoint (tcp, tls) is accepted now
    (`timeout`: s to wait for it)."""
    host, _, port = endpoint.split("/", 1)[1].rpartition(":")
    try:
        with socket.create_connection((host.strip("[]"), int(port)), timeout=timeout):
            return True
    except (OSError, ValueError):
        return False
