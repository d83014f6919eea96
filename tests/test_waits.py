"""Every wait says what it waits for, at once, with its limit: `learn` (the router, the
services), `alive --wait`, `ports --wait`, `experiment --world mesh`; Ctrl-C during any of them
exits 130 with one line, and a wait that runs out is one error line and exit status 1."""

from __future__ import annotations

import queue
import signal
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from archery.mesh.netflags import NetConfig
from archery.mesh.router import free_tcp_endpoint

LINE_WITHIN = 60.0  # s: the waiting line comes at once; this bounds a loaded machine's start-up


class Waiting:
    """`archery ARGS…` as a child process whose stderr is read line by line as it comes."""

    def __init__(self, *args: str, cwd: Path | None = None) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "archery.apps.cli", *args],
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            cwd=cwd,
        )
        self.lines: queue.Queue[str | None] = queue.Queue()
        self.seen: list[str] = []
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        assert self.proc.stderr is not None
        for line in self.proc.stderr:
            self.lines.put(line.rstrip("\n"))
        self.lines.put(None)

    def line_with(self, text: str) -> str:
        """The first stderr line holding `text`; fails if the process ends without one."""
        while True:
            line = self.lines.get(timeout=LINE_WITHIN)
            assert line is not None, f"ended without {text!r}: {self.seen}"
            self.seen.append(line)
            if text in line:
                return line

    def interrupt(self) -> tuple[int, list[str]]:
        """Ctrl-C; the exit status and the stderr lines after those already read."""
        assert self.proc.poll() is None, "ended before Ctrl-C"
        self.proc.send_signal(signal.SIGINT)
        return self.finish()

    def finish(self) -> tuple[int, list[str]]:
        status = self.proc.wait(timeout=60)
        rest = []
        while (line := self.lines.get(timeout=10)) is not None:
            rest.append(line)
        return status, rest


def _dead() -> str:
    return free_tcp_endpoint()  # a free port: nothing listens there


def test_learn_says_it_waits_for_the_router_at_once_and_ctrl_c_ends_it() -> None:
    dead = _dead()
    learn = Waiting("learn", "--connect", dead, "--wait", "120")
    line = learn.line_with("waiting")
    assert line == f"archery learn: waiting up to 120 s for the router at {dead} (Ctrl-C to stop)"
    status, rest = learn.interrupt()
    assert status == 130, rest
    assert rest == ["archery learn: interrupted (Ctrl-C)"], rest


def test_learn_against_nothing_waits_then_fails_with_status_1() -> None:
    dead = _dead()
    learn = Waiting("learn", "--connect", dead, "--wait", "1")
    assert "waiting up to 1 s for the router" in learn.line_with("waiting")
    status, rest = learn.finish()
    assert status == 1, rest
    assert len(rest) == 1 and dead in rest[0] and "Traceback" not in rest[0], rest


def test_learn_names_the_services_it_waits_for(net: NetConfig) -> None:
    flags = ["--connect", net.connect[0], "--robot", net.robot]
    learn = Waiting("learn", *flags, "--wait", "120")
    line = learn.line_with("waiting")
    assert line == (
        "archery learn: waiting up to 120 s for the services: robot, camera, detector, "
        "controller, learner (Ctrl-C to stop)"
    ), line
    status, rest = learn.interrupt()
    assert status == 130 and rest == ["archery learn: interrupted (Ctrl-C)"], rest


@pytest.mark.parametrize("verb", ["alive", "ports"])
def test_alive_and_ports_say_what_they_wait_for(verb: str, net: NetConfig) -> None:
    flags = ["--connect", net.connect[0], "--robot", net.robot]
    names = ["camera"] if verb == "alive" else []
    tool = Waiting(verb, *names, *flags, "--wait", "120")
    line = tool.line_with("waiting")
    if verb == "alive":
        assert (
            line == "archery alive: waiting up to 120 s for the services: camera (Ctrl-C to stop)"
        )
    else:
        assert line == (
            f"archery ports: waiting up to 120 s for a service of robot {net.robot!r} to come "
            "alive (Ctrl-C to stop)"
        )
    status, rest = tool.interrupt()
    assert status == 130 and rest == [f"archery {verb}: interrupted (Ctrl-C)"], rest


def test_alive_waits_for_the_router_and_runs_out_with_status_1() -> None:
    dead = _dead()
    alive = Waiting("alive", "--connect", dead, "--wait", "1")
    assert alive.line_with("waiting") == (
        f"archery alive: waiting up to 1 s for the router at {dead} (Ctrl-C to stop)"
    )
    status, rest = alive.finish()
    assert status == 1 and len(rest) == 1 and dead in rest[0], rest


def test_a_mesh_experiment_says_it_waits_for_robots(net: NetConfig, tmp_path: Path) -> None:
    flags = ["--connect", net.connect[0], "--robot", net.robot]
    out = tmp_path / "exp"
    experiment = Waiting(
        "experiment", "--world", "mesh", "--algo", "random", "--sessions", "1", "--rollouts", "2",
        "--out", str(out), "--no-progress", "--wait", "120", *flags,
    )  # fmt: skip
    line = experiment.line_with("waiting")
    assert line.startswith(
        "archery experiment: waiting up to 120 s for a robot on the mesh (Ctrl-C"
    )
    assert line.endswith("(Ctrl-C to stop)"), line
    status, rest = experiment.interrupt()
    assert status == 130 and rest == ["archery experiment: interrupted (Ctrl-C)"], rest


def test_a_mesh_experiment_waits_for_the_router_then_fails_with_status_1(tmp_path: Path) -> None:
    dead = _dead()
    experiment = Waiting(
        "experiment", "--world", "mesh", "--connect", dead, "--wait", "1", "--no-progress",
        "--out", str(tmp_path / "exp"),
    )  # fmt: skip
    assert experiment.line_with("waiting") == (
        f"archery experiment: waiting up to 1 s for the router at {dead} (Ctrl-C to stop)"
    )
    status, rest = experiment.finish()
    assert status == 1 and len(rest) == 1 and dead in rest[0], rest
