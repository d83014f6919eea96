"""`archery up`: a router and all five services as supervised child processes of one command.

It starts `archery router --listen ENDPOINT` and `archery robot|camera|detector|controller|
learner --connect ENDPOINT --robot NAME` (each with `python -m archery.apps.cli`, so this module
imports no service), waits until every service is alive by liveliness (each wait said as it
begins, by the caller's `on_wait`: `apps.waits`), and then supervises them
(`apps.up.supervisor`, `apps.up.restart_policy`; `Launcher` tells how they stop, and where their
output goes). The mesh is the built-in default or a launch description (`--config mesh.toml`,
`apps.up.launch_config`); `--robots N` starts a fleet: N robot stacks under `ROBOT1` … `ROBOTN`
and one learner serving them all (`launch_config.default_mesh`). A supervised observer (the
YARP bridge) is restarted by its policy, stopped first, its group killed 1 s after SIGTERM.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

from archery.apps.up.child import Child, spawn
from archery.apps.up.launch_config import (
    SERVICES,
    MeshConfig,
    RobotSpec,
    RouterSpec,
    ServiceSpec,
)
from archery.apps.up.logfile import LOG_FILE_BYTES, LOG_FILES, RotatingLog
from archery.apps.up.restart_policy import RestartPolicy, describe_status
from archery.mesh.credentials import identity_folder
from archery.mesh.liveliness import OnWait
from archery.mesh.netflags import DEFAULT_ROUTER, NetConfig
from archery.mesh.node import Node
from archery.mesh.router import wait_for_endpoint
from archery.protocol.errors import ArcheryError, ConfigError, RpcTimeout

__all__ = [
    "INTERRUPT_GRACE",
    "OBSERVER_GRACE",
    "ROUTER_START",
    "STOP_ORDER",
    "LaunchError",
    "Launcher",
    "Observer",
    "StartInterrupted",
]

STOP_ORDER = ("learner", "detector", "camera", "controller", "robot")


class LaunchError(ArcheryError):
    """A child could not start, died, or did not come alive in time."""

    code = "launch_failed"


class StartInterrupted(LaunchError):
    """Ctrl-C or SIGTERM while starting: everything started was stopped."""

    code = "interrupted"


INTERRUPT_GRACE = 2.0  # s a child stopped during start-up gets before SIGKILL
#: s a supervised observer gets after SIGTERM before SIGKILL of its process group (a handler
#: that cannot run while a library's C++ code holds the process is no handler)
OBSERVER_GRACE = 1.0


@dataclass(frozen=True)
class Observer:
    """A supervised observer: its command line, the bytes its log holds once it is ready, its
    restart policy. Exhausting its budget leaves it down; the mesh runs on without it."""

    argv: tuple[str, ...]
    ready: bytes
    restart: RestartPolicy


ROUTER_START = 15.0  # s the router may take to listen


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
                f"`archery up` running? Use --listen {proto}/{host}:PORT with a free port, or "
                f"connect to the running one"
            ) from None


class Launcher:
    """Starts, watches and stops the router and the services. Use as a context manager.

    A child that exits is restarted, left down or ends everything as its restart policy
    decides, the router on its same endpoint (the services reconnect to it by themselves).
    Ctrl-C or SIGTERM stops them all (`stop_all`), the learner first and the router last, each
    with SIGTERM (a clean stop, exit status 0) and SIGKILL after a grace period. Each child's
    output goes through a pipe to `LOGS/<name>.log`, rotated through `<name>.log.1` and
    `<name>.log.2` at 8 MiB a file, so at most 24 MiB a child (`apps.up.logfile`); the children
    die with their parent (`apps.up.child`).

    Args:
        endpoint: where the router listens and the services connect (`tcp/HOST:PORT`).
        robot: the robot prefix.
        logs: directory of the children's logs.
        service_args: extra command-line arguments per service name.
        router: start a router (False: connect the services to one that runs already).
        secure: a deployment directory (`archery keys init`): every child runs with --secure,
            given a folder of its own with the CA certificate and its identity only
            (`mesh.credentials.identity_folder`), removed when everything stopped.
        mesh: a whole launch description (`apps.up.launch_config`); it replaces `endpoint`,
            `robot`, `service_args` and `router`, and gives each child its restart policy.
        insecure_network: the router may listen beyond loopback in plain mode
            (`--insecure-network`).
        log_bytes: bytes of one log file at most (`apps.up.logfile.LOG_FILE_BYTES`).
        log_files: log files per child, rotated (`apps.up.logfile.LOG_FILES`): a child's logs
            take at most `log_files × log_bytes` bytes.
    """

    def __init__(
        self,
        endpoint: str = DEFAULT_ROUTER,
        robot: str = "icubSim",
        logs: Path = Path("runs/logs"),
        service_args: dict[str, Sequence[str]] | None = None,
        router: bool = True,
        secure: str | None = None,
        *,
        mesh: MeshConfig | None = None,
        insecure_network: bool = False,
        log_bytes: int = LOG_FILE_BYTES,
        log_files: int = LOG_FILES,
    ) -> None:
        if mesh is None:
            args = {k: tuple(v) for k, v in (service_args or {}).items()}
            unknown = sorted(set(args) - set(SERVICES))
            if unknown:
                raise ConfigError(f"no service {unknown[0]!r}; services: {', '.join(SERVICES)}")
            mesh = MeshConfig(
                RouterSpec(endpoint, router),
                (RobotSpec(robot),),
                {name: ServiceSpec(args.get(name, ())) for name in SERVICES},
            )
        self.mesh = mesh
        self.endpoint = mesh.router.endpoint
        self.net = NetConfig(connect=(self.endpoint,), robot=mesh.robots[0].prefix, secure=secure)
        self.secure = ["--secure", secure] if secure else []  # for tools of the operator
        # each child's own folder: the CA certificate and its identity only (never `ca.key`)
        self._secrets = Path(tempfile.mkdtemp(prefix="archery-identities-")) if secure else None
        self._deployment = Path(secure) if secure else None
        self._insecure = ["--insecure-network"] if insecure_network else []
        self.logs = Path(logs)
        self.specs = {spec.id: spec for spec in mesh.children()}
        self.with_router = mesh.router.start
        self.children: dict[str, Child] = {}
        self.log_bytes = log_bytes
        self.log_files = log_files
        self._outputs: dict[str, RotatingLog] = {}  # by child name, kept across restarts
        self._stop: threading.Event | None = None  # set: stop starting (`up`)
        self.observers: dict[str, Observer] = {}  # supervised observers, by child name
        #: called with an observer's name and its ready line once a restart of it is ready
        self.on_ready: Callable[[str, str], None] | None = None
        self.env = dict(os.environ)  # each child picks its rendering backend (sim.gl_backend)

    def policy(self, name: str) -> RestartPolicy:
        """The restart policy of a child (`router`, a service's id or an observer's name)."""
        if name in self.observers:
            return self.observers[name].restart
        return self.mesh.router.restart if name == "router" else self.specs[name].restart

    # -- starting -------------------------------------------------------------------------------
    def output(self, name: str) -> RotatingLog:
        """The rotating log `LOGS/NAME.log` of the child `name` (one per name: a restarted
        child goes on writing to it)."""
        if name not in self._outputs:
            self.logs.mkdir(parents=True, exist_ok=True)
            path = self.logs / f"{name}.log"
            self._outputs[name] = RotatingLog(path, self.log_bytes, self.log_files)
        return self._outputs[name]

    def _spawn(self, name: str, argv: list[str]) -> Child:
        argv = [sys.executable, "-m", "archery.apps.cli", *argv]
        child = spawn(name, argv, self.output(name), self.env)
        self.children[name] = child
        return child

    def start_router(
        self,
        timeout: float = ROUTER_START,
        *,
        restart: bool = False,
        on_wait: OnWait | None = None,
    ) -> None:
        """Start the router and wait until it listens.

        Args:
            timeout: how long to wait (s).
            restart: a restart by the supervisor: no check that the port is free (the router
                says so itself, exit status 2), and a failure stops only the new router.
            on_wait: called once, as the wait begins, with what it waits for and `timeout`.
        """
        if not restart:
            _check_free(self.endpoint)
        argv = ["router", "--listen", self.endpoint, *self._identity("router")]
        child = self._spawn("router", argv + self._insecure)
        if on_wait is not None:
            on_wait(f"the router to listen on {self.endpoint}", timeout)
        deadline = time.monotonic() + timeout
        while child.returncode is None:
            self._check_stop()
            try:
                wait_for_endpoint(self.endpoint, min(0.5, max(0.0, deadline - time.monotonic())))
                return
            except ConfigError:
                if time.monotonic() >= deadline:
                    break
        if restart:
            self.kill("router")
        else:
            self.stop_all()
        raise LaunchError(
            f"the router did not listen on {self.endpoint} within {timeout:g} s "
            f"(exit status {child.returncode}); its log {child.log}:\n{child.tail()}"
        )

    def start(self, name: str) -> Child:
        """Start (or restart) one service (by its id: the service's name for one robot)."""
        spec = self.specs.get(name)
        if spec is None:
            raise ConfigError(f"no service {name!r}; services: {', '.join(self.specs)}")
        old = self.children.get(name)
        if old is not None and old.returncode is None:
            raise LaunchError(
                f"{name} is running already (pid {old.proc.pid if old.proc else '?'})"
            )
        argv = [spec.service, "--connect", self.endpoint, "--robot", spec.robot]
        argv += self._identity(spec.service)
        return self._spawn(name, argv + list(spec.args))

    def _identity(self, identity: str) -> list[str]:
        """`--secure FOLDER` of a child of `identity` (none in plain mode)."""
        if self._secrets is None or self._deployment is None:
            return []
        return ["--secure", str(identity_folder(self._deployment, identity, self._secrets))]

    def restart(self, name: str) -> None:
        """Start a child that exited again: the router on its endpoint, a service, or an
        observer (`on_ready` told once its log says it is ready)."""
        if name == "router":
            self.start_router(restart=True)
        elif name in self.observers:
            self._restart_observer(name)
        else:
            self.start(name)

    def observe(self, name: str, observer: Observer) -> Child:
        """Start a supervised observer (its log `LOGS/NAME.log`, this run's words only)."""
        output = self.output(name)
        output.close()
        for path in output.paths:
            path.unlink(missing_ok=True)
        self.observers[name] = observer
        child = spawn(name, list(observer.argv), output, self.env)
        self.children[name] = child
        return child

    def _restart_observer(self, name: str) -> None:
        observer = self.observers[name]
        old = self.children.get(name)
        if old is not None and old.proc is not None:
            kill_group(old.proc.pid)  # whatever it started in its group goes with it
        path = self.output(name).path
        start = _size(path)
        child = spawn(name, list(observer.argv), self.output(name), self.env)
        self.children[name] = child

        def wait_ready() -> None:
            while child.returncode is None:
                said = _read_from(path, start)
                line = next((x for x in said.splitlines() if observer.ready in x), None)
                if line is not None:
                    if self.on_ready is not None:
                        self.on_ready(name, line.decode(errors="replace").strip())
                    return
                time.sleep(0.05)

        threading.Thread(target=wait_ready, name=f"{name} ready", daemon=True).start()

    def up(
        self,
        timeout: float = 90.0,
        services: Iterable[str] | None = None,
        stop: threading.Event | None = None,
        on_wait: OnWait | None = None,
    ) -> float:
        """Start the router (if asked) and the services; wait until all are alive.

        Args:
            timeout: how long to wait for them (s).
            services: the ids of the services to start (default: all of the mesh).
            stop: set by Ctrl-C/SIGTERM: start no more, stop what started (within
                `INTERRUPT_GRACE` s each) and raise `StartInterrupted`.
            on_wait: called as each wait begins, with what it waits for and its limit (s):
                the router to listen (`ROUTER_START` s), then the services started
                (`timeout` s); see `apps.waits`.

        Returns:
            Seconds until all were alive.

        Raises:
            LaunchError: one died or was not alive in time; everything started is stopped.
            StartInterrupted: `stop` was set.
        """
        start = time.monotonic()
        names = list(self.specs if services is None else services)
        self._stop = stop
        try:
            if self.with_router:
                self.start_router(on_wait=on_wait)
            for name in names:
                self._check_stop()
                self.start(name)
            if on_wait is not None and names:
                on_wait(f"the services: {', '.join(names)}", timeout)
            self.wait_alive(names, timeout)
        except StartInterrupted:
            self.stop(list(self.children), INTERRUPT_GRACE)  # all at once: no order to keep
            self.forget_identities()
            raise
        except BaseException:
            self.stop_all()
            raise
        finally:
            self._stop = None
        return time.monotonic() - start

    def _check_stop(self) -> None:
        if self._stop is not None and self._stop.is_set():
            raise StartInterrupted("interrupted while starting: stopped everything started")

    def wait_alive(self, names: Iterable[str], timeout: float = 90.0) -> None:
        """Wait by liveliness until the named services (ids) are alive.

        Raises:
            LaunchError: one exited meanwhile, or some are missing after `timeout` s.
        """
        by_robot: dict[str, dict[str, str]] = {}
        for name in names:
            spec = self.specs[name]
            by_robot.setdefault(spec.robot, {})[spec.service] = name
        deadline = time.monotonic() + timeout
        for robot, ids in by_robot.items():
            with Node(None, dataclasses.replace(self.net, robot=robot)) as node:
                self._wait_robot(node, ids, deadline, timeout)

    def _wait_robot(self, node: Node, ids: dict[str, str], deadline: float, timeout: float) -> None:
        while True:
            self._check_stop()
            dead = self.first_exit()
            if dead is not None:
                raise LaunchError(self.describe_exit(dead))
            try:
                node.wait_alive(ids, timeout=min(1.0, max(0.05, deadline - time.monotonic())))
                return
            except RpcTimeout:
                if time.monotonic() >= deadline:
                    missing = sorted(ids[s] for s in set(ids) - node.alive())
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
        how = "is running" if code is None else describe_status(code)
        return f"{child.name} {how}; the end of its log {child.log}:\n{child.tail()}"

    def watch(self, stop: threading.Event, poll: float = 0.2) -> Child | None:
        """Block until `stop` is set (None) or a child exits (that child); no restarts (see
        `apps.up.supervisor.Supervisor` for those)."""
        while not stop.wait(poll):
            dead = self.first_exit()
            if dead is not None:
                return dead
        return None

    # -- stopping -------------------------------------------------------------------------------
    def kill(self, name: str, sig: int = signal.SIGKILL) -> None:
        """Send a signal to one child (tests: SIGKILL, a crash) and reap it."""
        child = self.children[name]
        if child.proc is not None and child.proc.poll() is None:
            child.proc.send_signal(sig)
            child.proc.wait(30)
        child.drain()

    def stop(
        self, names: Iterable[str], grace: float = 10.0, *, group: bool = False
    ) -> dict[str, int | None]:
        """SIGTERM the named children together, SIGKILL those still running after `grace` s
        (`group`: SIGKILL to each one's process group, what it started with it).

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
                if group:
                    kill_group(child.proc.pid)
                else:
                    child.proc.kill()
                child.proc.wait(10)
        for child in chosen:
            child.drain()  # their last lines, into their logs
        return {c.name: c.returncode for c in chosen}

    def forget_identities(self) -> None:
        """Remove the children's identity folders (once every child has stopped)."""
        if self._secrets is not None:
            shutil.rmtree(self._secrets, ignore_errors=True)

    def stop_all(self, grace: float = 10.0) -> dict[str, int | None]:
        """Stop the supervised observers (`OBSERVER_GRACE` s each, then their process groups
        killed), the services (all at once, the learners' sessions first), then the router."""
        observers = [n for n in self.children if n in self.observers]
        codes = self.stop(observers, OBSERVER_GRACE, group=True) if observers else {}
        services = [n for n in self.children if n != "router" and n not in self.observers]
        learners = [n for n in services if self.specs[n].service == "learner"]
        rest = sorted(
            (n for n in services if n not in learners),
            key=lambda n: STOP_ORDER.index(self.specs[n].service),
        )
        codes |= self.stop(learners, grace) if learners else {}
        codes |= self.stop(rest, grace)
        codes |= self.stop(["router"], grace)
        self.forget_identities()
        return codes

    def __enter__(self) -> Launcher:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop_all()
        for output in self._outputs.values():
            output.close()


def kill_group(pid: int) -> None:
    """SIGKILL the process group of `pid` (a child `spawn` started leads its own)."""
    with contextlib.suppress(ProcessLookupError, PermissionError):
        os.killpg(pid, signal.SIGKILL)


def _size(path: Path) -> int:
    try:
        return path.stat().st_size
    except FileNotFoundError:
        return 0


def _read_from(path: Path, start: int) -> bytes:
    """A log's bytes from `start` (all of it once it was rotated below `start`)."""
    try:
        with path.open("rb") as file:
            if file.seek(0, os.SEEK_END) >= start:
                file.seek(start)
            else:
                file.seek(0)
            return file.read()
    except FileNotFoundError:
        return b""
