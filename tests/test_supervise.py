"""`archery up` supervises: a crashed child is restarted (the others untouched), a clean exit
under on-failure is left down, a spent budget stops everything (exit 1, naming the child), and
a killed router is restarted on its endpoint while every service reconnects by itself."""

from __future__ import annotations

import contextlib
import dataclasses
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import psutil
import pytest
import zenoh

from archery.apps.up.launch_config import SERVICES, default_mesh
from archery.apps.up.launcher import Launcher
from archery.apps.up.restart_policy import RestartPolicy
from archery.apps.up.supervisor import GiveUp, Supervisor
from archery.mesh.netflags import NetConfig
from archery.mesh.node import Node
from archery.mesh.router import free_tcp_endpoint, wait_for_endpoint
from archery.protocol.errors import ConfigError
from tests.rpc import rpc_call

ROBOT = "sup1"


class Tokens:
    """Every liveliness change of one robot's services, in order, seen by one node."""

    def __init__(self, node: Node) -> None:
        self.events: list[tuple[str, str]] = []
        self.cond = threading.Condition()
        self.sub = node.session.liveliness().declare_subscriber(
            node.keys.alive_all(), self._on, history=True
        )

    def _on(self, sample: zenoh.Sample) -> None:
        kind = "put" if sample.kind == zenoh.SampleKind.PUT else "delete"
        with self.cond:
            self.events.append((str(sample.key_expr).rsplit("/", 1)[-1], kind))
            self.cond.notify_all()

    def wait_for(self, *wanted: tuple[str, str], after: int = 0, timeout: float = 60) -> int:
        """Wait until the events from index `after` contain `wanted` in order; the index
        after the last one."""
        with self.cond:
            deadline = time.monotonic() + timeout
            while True:
                index, found = after, 0
                for i, event in enumerate(self.events[after:], start=after):
                    if found < len(wanted) and event == wanted[found]:
                        found, index = found + 1, i + 1
                if found == len(wanted):
                    return index
                remaining = deadline - time.monotonic()
                assert remaining > 0, f"not seen {wanted} in {self.events[after:]}"
                self.cond.wait(remaining)


@dataclasses.dataclass
class Mesh:
    launcher: Launcher
    supervisor: Supervisor
    lines: list[str]
    node: Node
    tokens: Tokens

    def pids(self) -> dict[str, int]:
        return {n: c.proc.pid for n, c in self.launcher.children.items() if c.proc}

    def wait_restarted(self, name: str, old_pid: int, timeout: float = 60) -> None:
        """Wait until the supervisor has started `name` again (a new process)."""
        deadline = time.monotonic() + timeout
        while self.pids()[name] == old_pid:
            assert time.monotonic() < deadline, f"{name} not restarted: {self.lines}"
            assert self.thread_alive(), self.lines
            time.sleep(0.05)

    def assert_only_restarted(self, name: str, before: dict[str, int]) -> None:
        """`name` runs as a new process; every other child is the same process, running."""
        now = self.pids()
        assert now[name] != before[name]
        assert {n: p for n, p in now.items() if n != name} == {
            n: p for n, p in before.items() if n != name
        }
        assert self.launcher.first_exit() is None

    def thread_alive(self) -> bool:
        return self._thread.is_alive()

    _thread: threading.Thread = dataclasses.field(init=False)


@pytest.fixture(scope="module")
def mesh(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Mesh]:
    """All five services and a router whose restart waits 2 s (an outage of about 2 s)."""
    tmp = tmp_path_factory.mktemp("supervise")
    base = default_mesh(free_tcp_endpoint(), ROBOT, runs=str(tmp / "runs"))
    router = dataclasses.replace(base.router, restart=RestartPolicy(backoff=2.0))
    launcher = Launcher(logs=tmp / "logs", mesh=dataclasses.replace(base, router=router))
    launcher.up(120)
    lines: list[str] = []
    supervisor = Supervisor(launcher, report=lines.append)
    stop = threading.Event()
    outcome: list[GiveUp | None] = []
    thread = threading.Thread(target=lambda: outcome.append(supervisor.run(stop)), daemon=True)
    thread.start()
    try:
        with Node(None, launcher.net) as node:
            state = Mesh(launcher, supervisor, lines, node, Tokens(node))
            state._thread = thread
            yield state
    finally:
        stop.set()
        thread.join(30)
        launcher.stop_all()
    assert outcome == [None], outcome  # no policy gave up


def test_a_killed_service_is_restarted_and_the_others_are_untouched(mesh: Mesh) -> None:
    mesh.node.wait_alive(SERVICES, timeout=30)
    before = mesh.pids()
    after = len(mesh.tokens.events)
    mesh.launcher.kill("camera")  # SIGKILL: a crash
    mesh.tokens.wait_for(("camera", "delete"), ("camera", "put"), after=after)
    mesh.wait_restarted("camera", before["camera"])
    assert "camera was killed by signal 9; restart 1 of 5 within 60 s, in 0.5 s" in mesh.lines
    mesh.assert_only_restarted("camera", before)
    mesh.node.wait_alive(SERVICES, timeout=30)


@pytest.mark.slow
def test_the_router_is_restarted_and_every_service_reconnects(mesh: Mesh) -> None:
    """Router killed, restarted on the same endpoint after 2 s: the same five service
    processes are alive again on the new router, and they answer requests."""
    before = mesh.pids()
    mesh.launcher.kill("router")
    killed = time.monotonic()
    mesh.wait_restarted("router", before["router"])
    wait_for_endpoint(mesh.launcher.endpoint, 30)
    listening = time.monotonic()
    assert listening - killed >= 2.0  # the router's back-off: an outage of 2 s at least
    # A fresh node knows only what the new router knows: every token was declared again.
    with Node(None, NetConfig(connect=(mesh.launcher.endpoint,), robot=ROBOT)) as node:
        node.wait_alive(SERVICES, timeout=30)
        alive_after = time.monotonic() - listening
        status = rpc_call(node, node.keys.learner_rpc(), "status", timeout=10)
    assert isinstance(status, dict)
    print(f"all five alive {alive_after:.2f} s after the router listened again")
    assert alive_after < 15
    assert "router was killed by signal 9; restart 1 of 5 within 60 s, in 2 s" in mesh.lines
    mesh.assert_only_restarted("router", before)
    mesh.node.wait_alive(SERVICES, timeout=30)  # the old node's session reconnected too


def test_a_clean_exit_under_on_failure_is_left_down(mesh: Mesh) -> None:
    before = mesh.pids()
    after = len(mesh.tokens.events)
    mesh.launcher.kill("detector", signal.SIGTERM)  # a clean stop: exit status 0
    assert mesh.launcher.children["detector"].returncode == 0
    mesh.tokens.wait_for(("detector", "delete"), after=after)
    deadline = time.monotonic() + 30
    while "detector" not in mesh.supervisor.left:
        assert time.monotonic() < deadline and mesh.thread_alive(), mesh.lines
        time.sleep(0.05)
    assert "detector exited with status 0; restart policy 'on-failure' keeps it down" in mesh.lines
    assert mesh.pids() == before  # nothing restarted, nothing stopped
    assert "detector" not in mesh.supervisor.pending and mesh.thread_alive()
    others = [n for n in SERVICES if n != "detector"]
    mesh.node.wait_alive(others, timeout=30)
    assert "detector" not in mesh.node.alive()


def _children(pid: int) -> dict[str, int]:
    """The direct children of a process, by the verb they run."""
    out = {}
    for child in psutil.Process(pid).children():
        with contextlib.suppress(psutil.NoSuchProcess):
            out[child.cmdline()[3]] = child.pid  # python -m archery.apps.cli VERB ...
    return out


def test_up_stops_everything_when_the_budget_is_spent(tmp_path: Path) -> None:
    """A real `archery up --config`: one restart allowed; the second crash stops all, exit 1,
    with one line naming the child and why."""
    endpoint = free_tcp_endpoint()
    config = tmp_path / "mesh.toml"
    config.write_text(
        f'[router]\nendpoint = "{endpoint}"\n[robots.supcli]\nservices = ["controller"]\n'
    )
    argv = [sys.executable, "-m", "archery.apps.cli", "up", "--config", str(config)]
    argv += ["--logs", str(tmp_path / "logs"), "--restart-budget", "1"]
    proc = subprocess.Popen(
        argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=os.environ
    )
    try:
        net = NetConfig(connect=(endpoint,), robot="supcli")
        deadline = time.monotonic() + 60
        while True:  # the router must listen before a node can connect
            assert proc.poll() is None, proc.communicate()
            try:
                node = Node(None, net)
                break
            except ConfigError:
                assert time.monotonic() < deadline
                time.sleep(0.1)
        with node:
            node.wait_alive(["controller"], timeout=60)
            first = _children(proc.pid)
            os.kill(first["controller"], signal.SIGKILL)
            node.wait_gone("controller", timeout=30)
            # the restarted child (a liveliness query may still show the old token a moment)
            restart_by = time.monotonic() + 60
            while _children(proc.pid).get("controller", first["controller"]) == first["controller"]:
                assert time.monotonic() < restart_by, "the controller was not restarted"
                time.sleep(0.05)
            node.wait_alive(["controller"], timeout=60)
            second = _children(proc.pid)
            assert second["router"] == first["router"]
            os.kill(second["controller"], signal.SIGKILL)
            out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 1, err
    lines = err.strip().splitlines()
    assert (
        "archery up: controller was killed by signal 9; restart 1 of 1 within 60 s, in 0.5 s"
        in lines
    )
    assert lines[-1] == (
        "archery up: stopped everything: controller was killed by signal 9; 1 restarts "
        "within 60 s spent the budget of 1"
    )
    assert "all stopped cleanly" not in out
    assert not Path(f"/proc/{second['router']}").exists()  # stopped and reaped


@dataclasses.dataclass
class _Proc:
    name: str
    returncode: int | None = None
    started: float = 0.0


class _FakeLauncher:
    """The part of a Launcher the Supervisor uses; restarts are recorded, not run."""

    def __init__(self, policy: RestartPolicy) -> None:
        self.children = {n: _Proc(n) for n in ("router", "camera")}
        self.policy_ = policy
        self.restarted: list[tuple[str, float]] = []
        self.now = 100.0

    def policy(self, name: str) -> RestartPolicy:
        return self.policy_

    def restart(self, name: str) -> None:
        self.restarted.append((name, self.now))
        self.children[name] = _Proc(name, None, self.now)


def test_the_supervisor_waits_out_the_back_off_and_gives_up_on_a_bad_configuration() -> None:
    fake = _FakeLauncher(RestartPolicy(backoff=1.0))
    lines: list[str] = []
    supervisor = Supervisor(fake, report=lines.append, clock=lambda: fake.now)  # type: ignore[arg-type]  # a fake launcher
    fake.children["camera"].returncode = 1
    assert supervisor.step() is None
    assert lines == ["camera exited with status 1; restart 1 of 5 within 60 s, in 1 s"]
    assert fake.restarted == []  # not before its back-off
    fake.now += 0.9
    assert supervisor.step() is None and fake.restarted == []
    fake.now += 0.1
    assert supervisor.step() is None and fake.restarted == [("camera", 101.0)]
    fake.now += 0.5
    fake.children["camera"].returncode = -9  # again, soon: twice the back-off
    assert supervisor.step() is None
    assert lines[-1] == "camera was killed by signal 9; restart 2 of 5 within 60 s, in 2 s"
    fake.children["router"].returncode = 2  # a bad configuration ends supervision at once
    outcome = supervisor.step()
    assert outcome is not None and outcome.child.name == "router"
    assert outcome.line() == (
        "router exited with status 2 (a bad configuration: a restart cannot help)"
    )
    assert supervisor.restart_count() == 2


def test_an_observer_whose_budget_is_spent_is_left_down_and_the_mesh_runs_on() -> None:
    fake = _FakeLauncher(RestartPolicy(budget=1, backoff=0.0))
    fake.children["yarp"] = _Proc("yarp")
    fake.observers = {"yarp": object()}  # type: ignore[attr-defined]  # a supervised observer
    lines: list[str] = []
    supervisor = Supervisor(fake, report=lines.append, clock=lambda: fake.now)  # type: ignore[arg-type]  # a fake launcher
    fake.children["yarp"].returncode = -11  # a crash inside YARP's library: restarted
    assert supervisor.step() is None and fake.restarted == [("yarp", 100.0)]
    fake.children["yarp"].returncode = -11  # again: the budget is spent, yet nothing ends
    assert supervisor.step() is None
    assert lines[-1].endswith("spent the budget of 1; left down, the mesh runs on")
    assert "yarp" in supervisor.left and fake.restarted == [("yarp", 100.0)]
    fake.children["camera"].returncode = 2  # a service's end still ends everything
    assert supervisor.step() is not None
