"""`archery router`: a Zenoh router from the Python package (no separate binary needed).

With `--secure DIR` it accepts only mutual-TLS links from holders of a certificate of DIR's CA
and enforces DIR/acl.json5 (see `mesh.acl`) on every link.
"""

from __future__ import annotations

import logging
import socket
import subprocess
import sys
import time

import zenoh

from archery.mesh.cliargs import ArgumentParser
from archery.mesh.netflags import (
    DEFAULT_ROUTER,
    DEFAULT_SECURE_ROUTER,
    NetConfig,
    add_network_args,
    open_session,
)
from archery.mesh.signals import shutdown_on_signals, wait_for_stop
from archery.protocol.errors import ConfigError

__all__ = ["free_tcp_endpoint", "main", "open_router", "spawn_router", "wait_for_endpoint"]

log = logging.getLogger("archery.router")


def free_tcp_endpoint(host: str = "127.0.0.1") -> str:
    """A `tcp/HOST:PORT` endpoint on a port that is free right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind((host, 0))
        return f"tcp/{host}:{sock.getsockname()[1]}"


def open_router(
    listen: str | list[str], connect: tuple[str, ...] = (), secure: str | None = None
) -> zenoh.Session:
    """Open an in-process router session listening on `listen` (one endpoint or several);
    `secure`: a deployment directory (mutual TLS and its access control)."""
    endpoints = (listen,) if isinstance(listen, str) else tuple(listen)
    net = NetConfig(mode="router", listen=endpoints, connect=connect, secure=secure)
    return open_session(net.with_identity("router"))


def wait_for_endpoint(endpoint: str, timeout: float = 10.0) -> None:
    """Block until a TCP endpoint accepts connections.

    Raises:
        ConfigError: it does not within `timeout` seconds.
    """
    host, port = endpoint.split("/", 1)[1].rsplit(":", 1)
    deadline = time.monotonic() + timeout
    while True:
        try:
            with socket.create_connection((host.strip("[]"), int(port)), timeout=0.5):
                return
        except OSError:
            if time.monotonic() > deadline:
                raise ConfigError(f"nothing listens on {endpoint} after {timeout:g} s") from None
            time.sleep(0.02)


def spawn_router(
    endpoint: str, timeout: float = 10.0, secure: str | None = None, log_level: str = "warn"
) -> subprocess.Popen[bytes]:
    """Start `archery router --listen ENDPOINT [--secure DIR]` as a child process and wait
    until it listens; it logs at `log_level` (default warn: tests and benchmarks stay quiet)."""
    extra = ["--secure", secure] if secure is not None else []
    extra += ["--log-level", log_level]
    proc = subprocess.Popen(
        [sys.executable, "-m", "archery.apps.cli", "router", "--listen", endpoint, *extra],
        stdin=subprocess.DEVNULL,
    )
    try:
        wait_for_endpoint(endpoint, timeout)
    except ConfigError:
        proc.kill()
        raise
    return proc


def main(argv: list[str] | None = None) -> int:
    """Run a router until SIGINT/SIGTERM; exit status 0 on a clean stop."""
    parser = ArgumentParser(prog="archery router", description=__doc__)
    add_network_args(parser, default_mode="router")
    args = parser.parse_args(argv)
    if not args.listen:
        args.listen = [DEFAULT_SECURE_ROUTER if args.secure else DEFAULT_ROUTER]
    try:
        net = NetConfig.from_args(args).with_identity("router")
        if net.mode != "router":
            raise ConfigError(f"archery router runs in router mode, not --mode {net.mode}")
        stop = shutdown_on_signals()
        with open_session(net):
            secure = f" (mutual TLS, access control of {net.secure})" if net.secure else ""
            log.info("router listening on %s%s", ", ".join(net.listen), secure)
            wait_for_stop(stop)
    except ConfigError as exc:
        print(f"archery router: {exc}", file=sys.stderr)
        return 2
    log.info("router stopped")
    return 0
