"""`archery up`: a router and all five services as child processes of one command.

It starts `archery router --listen ENDPOINT` and `archery robot|camera|detector|controller|
learner --connect ENDPOINT --robot NAME` (each with `python -m services.cli`, so this module
imports no service), waits until every service is alive by liveliness, and then watches them.
Ctrl-C or SIGTERM stops them all, the learner first and the router last, each with SIGTERM (a
clean stop, exit status 0) and SIGKILL after a grace period; the first child that exits on its
own stops the rest too, and `up` says which one it was, its exit status and the end of its log.
Each child's output goes to `LOGS/<name>.log`; the children die with their parent.
"""

from __future__ import annotations

import argparse
import ctypes
import os
import shlex
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from protocol.cliargs import ArgumentParser, check_writable_dir, count, nonnegative, seconds
from protocol.errors import ArcheryError, ConfigError, RpcTimeout
from protocol.netflags import DEFAULT_ROUTER, DEFAULT_SECURE_ROUTER, NetConfig, add_network_args
from protocol.node import Node, shutdown_on_signals
from protocol.router import wait_for_endpoint

__all__ = ["SERVICES", "Child", "LaunchError", "Launcher", "main"]

SERVICES = ("robot", "controller", "camera", "detector", "learner")
STOP_ORDER = ("learner", "detector", "camera", "controller", "robot")
_PR_SET_PDEATHSIG = 1


class LaunchError(ArcheryError):
    """A child could not start, died, or did not come alive in time."""

    code = "launch_failed"


def _die_with_parent() -> None:
    """In the child before exec: get SIGTERM when the parent dies (Linux), so no orphans."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(_PR_SET_PDEATHSIG, signal.SIGTERM)
    except (OSError, AttributeError):
        pass


def _check_free(endpoint: str) -> None:
    """Raise ConfigError when something already listens on a tcp endpoint."""
    proto, address = endpoint.split("/", 1)
    if proto not in ("tcp", "tls"):
        return
    host, port = address.rsplit(":", 1)
    with socket.socket(socket.AF_INET6 if ":" in host.strip("[]") else socket.AF_INET) as sock:
        # As a listener would: a port left in TIME_WAIT by a router just stopped is free.
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind((host.strip("[]"), int(port)))
        except OSError as exc:
            raise ConfigError(
                f"cannot listen on {endpoint}: {exc.strerror or exc}. Is another router or "
                f"`archery up` running? Use --listen tcp/127.0.0.1:PORT with a free port, or "
                f"connect to the running one"
            ) from None


@dataclass
class Child:
    """One child process and its log file."""

    name: str
    argv: list[str]
    log: Path
    proc: subprocess.Popen[bytes] | None = None
    started: float = field(default=0.0)

    def tail(self, lines: int = 12) -> str:
        """The last lines of its log."""
        try:
            text = self.log.read_text(errors="replace")
        except OSError:
            return ""
        return "\n".join(text.rstrip().splitlines()[-lines:])

    @property
    def returncode(self) -> int | None:
        """Its exit status once it has ended (negative: killed by that signal)."""
        return None if self.proc is None else self.proc.poll()


class Launcher:
    """Starts, watches and stops the router and the services. Use as a context manager.

    Args:
        endpoint: where the router listens and the services connect (`tcp/HOST:PORT`).
        robot: the robot prefix.
        logs: directory of the children's logs.
        service_args: extra command-line arguments per service name.
        router: start a router (False: connect the services to one that runs already).
        secure: a deployment directory (`archery keys init`): every child runs with --secure.
    """

    def __init__(
        self,
        endpoint: str = DEFAULT_ROUTER,
        robot: str = "icubSim",
        logs: Path = Path("runs/logs"),
        service_args: dict[str, Sequence[str]] | None = None,
        router: bool = True,
        secure: str | None = None,
    ) -> None:
        self.net = NetConfig(connect=(endpoint,), robot=robot, secure=secure)
        self.secure = ["--secure", secure] if secure else []
        self.endpoint = endpoint
        self.logs = Path(logs)
        self.service_args = {k: list(v) for k, v in (service_args or {}).items()}
        unknown = sorted(set(self.service_args) - set(SERVICES))
        if unknown:
            raise ConfigError(f"no service {unknown[0]!r}; services: {', '.join(SERVICES)}")
        self.with_router = router
        self.children: dict[str, Child] = {}
        self.env = os.environ | {"MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}

    # -- starting -------------------------------------------------------------------------------
    def _spawn(self, name: str, argv: list[str]) -> Child:
        self.logs.mkdir(parents=True, exist_ok=True)
        child = Child(
            name, [sys.executable, "-m", "services.cli", *argv], self.logs / f"{name}.log"
        )
        with open(child.log, "ab") as log:
            log.write(f"--- {time.strftime('%H:%M:%S')} {shlex.join(child.argv)}\n".encode())
            log.flush()
            child.proc = subprocess.Popen(
                child.argv,
                stdin=subprocess.DEVNULL,
                stdout=log,
                stderr=subprocess.STDOUT,
                env=self.env,
                start_new_session=True,  # a terminal's Ctrl-C reaches only us; we stop them
                preexec_fn=_die_with_parent,
            )
        child.started = time.monotonic()
        self.children[name] = child
        return child

    def start_router(self, timeout: float = 15.0) -> None:
        """Start the router and wait until it listens."""
        _check_free(self.endpoint)
        child = self._spawn("router", ["router", "--listen", self.endpoint, *self.secure])
        try:
            wait_for_endpoint(self.endpoint, timeout)
        except ConfigError:
            self.stop_all()
            raise LaunchError(
                f"the router did not listen on {self.endpoint} within {timeout:g} s "
                f"(exit status {child.returncode}); its log {child.log}:\n{child.tail()}"
            ) from None

    def start(self, name: str) -> Child:
        """Start (or restart) one service."""
        if name not in SERVICES:
            raise ConfigError(f"no service {name!r}; services: {', '.join(SERVICES)}")
        old = self.children.get(name)
        if old is not None and old.returncode is None:
            raise LaunchError(
                f"{name} is running already (pid {old.proc.pid if old.proc else '?'})"
            )
        argv = [name, "--connect", self.endpoint, "--robot", self.net.robot, *self.secure]
        return self._spawn(name, argv + self.service_args.get(name, []))

    def up(self, timeout: float = 90.0, services: Iterable[str] = SERVICES) -> float:
        """Start the router (if asked) and the services; wait until all are alive.

        Returns:
            Seconds until all were alive.

        Raises:
            LaunchError: one died or was not alive in time; everything started is stopped.
        """
        start = time.monotonic()
        names = list(services)
        try:
            if self.with_router:
                self.start_router()
            for name in names:
                self.start(name)
            self.wait_alive(names, timeout)
        except BaseException:
            self.stop_all()
            raise
        return time.monotonic() - start

    def wait_alive(self, names: Iterable[str], timeout: float = 90.0) -> None:
        """Wait by liveliness until the named services are alive.

        Raises:
            LaunchError: one exited meanwhile, or some are missing after `timeout` s.
        """
        names = list(names)
        deadline = time.monotonic() + timeout
        with Node(None, self.net) as node:
            while True:
                dead = self.first_exit()
                if dead is not None:
                    raise LaunchError(self.describe_exit(dead))
                try:
                    node.wait_alive(names, timeout=min(1.0, max(0.05, deadline - time.monotonic())))
                    return
                except RpcTimeout:
                    if time.monotonic() >= deadline:
                        missing = sorted(set(names) - node.alive())
                        logs = "\n".join(
                            f"--- {n} ({self.children[n].log}):\n{self.children[n].tail(6)}"
                            for n in missing
                            if n in self.children
                        )
                        raise LaunchError(
                            f"not alive after {timeout:g} s: {', '.join(missing)}\n{logs}"
                        ) from None

    # -- watching -------------------------------------------------------------------------------
    def first_exit(self) -> Child | None:
        """The first child found to have exited, if any."""
        return next((c for c in self.children.values() if c.returncode is not None), None)

    def describe_exit(self, child: Child) -> str:
        """Which child ended, how, and the end of its log."""
        code = child.returncode
        how = (
            f"was killed by signal {-code}"
            if code is not None and code < 0
            else f"exited with status {code}"
        )
        return f"{child.name} {how}; the end of its log {child.log}:\n{child.tail()}"

    def watch(self, stop: threading.Event, poll: float = 0.2) -> Child | None:
        """Block until `stop` is set (None) or a child exits (that child)."""
        while not stop.wait(poll):
            dead = self.first_exit()
            if dead is not None:
                return dead
        return None

    # -- stopping -------------------------------------------------------------------------------
    def kill(self, name: str) -> None:
        """SIGKILL one child (tests: a crash) and reap it."""
        child = self.children[name]
        if child.proc is not None and child.proc.poll() is None:
            child.proc.kill()
            child.proc.wait(10)

    def stop(self, names: Iterable[str], grace: float = 10.0) -> dict[str, int | None]:
        """SIGTERM the named children together, SIGKILL those still running after `grace` s.

        Returns:
            Each one's exit status.
        """
        chosen = [self.children[n] for n in names if n in self.children]
        for child in chosen:
            if child.proc is not None and child.proc.poll() is None:
                child.proc.terminate()
        deadline = time.monotonic() + grace
        for child in chosen:
            if child.proc is None:
                continue
            try:
                child.proc.wait(max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                child.proc.kill()
                child.proc.wait(10)
        return {c.name: c.returncode for c in chosen}

    def stop_all(self, grace: float = 10.0) -> dict[str, int | None]:
        """Stop the services (all at once, the learner's session first), then the router."""
        codes = self.stop(["learner"], grace) if "learner" in self.children else {}
        codes |= self.stop([n for n in STOP_ORDER if n != "learner"], grace)
        codes |= self.stop(["router"], grace)
        return codes

    def __enter__(self) -> Launcher:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop_all()


def build_parser() -> argparse.ArgumentParser:
    """The flags of `archery up`."""
    parser = ArgumentParser(prog="archery up", description=__doc__.split("\n")[0])
    add_network_args(parser)
    parser.add_argument("--logs", default="runs/logs", help="directory of the children's logs")
    parser.add_argument("--runs", default="runs", help="the learner's session directory")
    parser.add_argument("--seed", type=count, default=0, help="the robot's shot-noise seed")
    parser.add_argument(
        "--rtf",
        type=nonnegative,
        default=0.0,
        help="the robot's real-time factor (0: as fast as possible)",
    )
    parser.add_argument(
        "--no-router",
        action="store_true",
        help="start no router: the services connect to the --connect endpoint",
    )
    parser.add_argument(
        "--timeout", type=seconds, default=90.0, help="wait this long for all services (s)"
    )
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run `archery up` until Ctrl-C/SIGTERM (exit 0) or a child's failure (exit 1)."""
    args = build_parser().parse_args(argv)
    try:
        default = DEFAULT_SECURE_ROUTER if args.secure else DEFAULT_ROUTER
        if args.no_router:
            endpoint = (args.connect or [default])[0]
        else:
            endpoint = (args.listen or [default])[0]
        check_writable_dir(Path(args.logs), "--logs", create=True)
        check_writable_dir(Path(args.runs), "--runs", create=True)
        launcher = Launcher(
            endpoint,
            NetConfig(connect=(endpoint,), robot=args.robot, secure=args.secure).robot,
            Path(args.logs),
            {
                "robot": ["--seed", str(args.seed), "--rtf", str(args.rtf)],
                "learner": ["--runs", args.runs],
            },
            router=not args.no_router,
            secure=args.secure,
        )
        stop = shutdown_on_signals()
        print(
            f"archery up: starting a router on {endpoint} and {', '.join(SERVICES)} …", flush=True
        )
        took = launcher.up(args.timeout)
    except (ConfigError, LaunchError) as exc:
        print(f"archery up: {exc}", file=sys.stderr)
        return 2 if isinstance(exc, ConfigError) else 1
    print(
        f"archery up: all alive in {took:.1f} s (robot {launcher.net.robot!r}, logs in "
        f"{launcher.logs}/). Run `archery learn {shlex.join(launcher.secure)}"
        f"{' ' if args.secure else ''}--connect {endpoint}` in another shell; "
        f"Ctrl-C stops everything.",
        flush=True,
    )
    dead = launcher.watch(stop)
    if dead is not None:
        print(f"archery up: {launcher.describe_exit(dead)}", file=sys.stderr)
    print("archery up: stopping …", flush=True)
    codes = launcher.stop_all()
    unclean = {n: c for n, c in codes.items() if c != 0 and (dead is None or n != dead.name)}
    if unclean:
        listed = ", ".join(f"{n} ({c})" for n, c in unclean.items())
        print(f"archery up: did not stop cleanly: {listed}", file=sys.stderr)
    else:
        print("archery up: all stopped cleanly", flush=True)
    return 1 if dead is not None or unclean else 0
