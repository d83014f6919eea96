"""`archery up --body yarp --remote NAME`: the robot child serves a YARP robot's control boards
(YARP 3.5's `fakeMotionControl`, the fixtures of tests/test_yarp_body.py), the other four
services start as usual, and the body flags that do not fit are one line, exit 2."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from archery.mesh.router import free_tcp_endpoint
from tests.conftest import archery
from tests.test_yarp_body import Robots, name_server, robots

__all__ = ["name_server", "robots"]  # the fixtures, used by name


def test_up_body_yarp_brings_all_five_services_alive(robots: Robots, tmp_path: Path) -> None:
    signal.signal(signal.SIGCHLD, signal.SIG_DFL)  # YARP's handler reaps children (conftest)
    endpoint = free_tcp_endpoint()
    argv = [sys.executable, "-m", "archery.apps.cli", "up", "--listen", endpoint]
    argv += ["--robot", f"upyarp{os.getpid()}", "--logs", str(tmp_path / "logs")]
    argv += ["--runs", str(tmp_path / "runs"), "--body", "yarp", "--remote", "/fake"]
    argv += ["--release-open", "7.5"]  # a shot flag, passed on to the robot
    out = tmp_path / "up.out"
    with out.open("wb") as sink:
        proc = subprocess.Popen(
            [*argv, "--timeout", "120"],
            env=robots.setup.env,
            stdin=subprocess.DEVNULL,
            stdout=sink,
            stderr=subprocess.STDOUT,
        )
    try:
        deadline = time.monotonic() + 180
        while b"all alive in" not in out.read_bytes():
            assert proc.poll() is None, out.read_text(errors="replace")[-3000:]
            assert time.monotonic() < deadline, out.read_text(errors="replace")[-3000:]
            time.sleep(0.2)
        robot_log = (tmp_path / "logs" / "robot.log").read_text(errors="replace")
        assert "/fake" in robot_log, robot_log[-2000:]
        assert "release by r_index_proximal to 7.5°" in robot_log, robot_log[-2000:]
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            status = proc.wait(90)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
            raise
    said = out.read_text(errors="replace")
    assert status == 0, said[-3000:]
    assert "all stopped cleanly" in said


@pytest.mark.parametrize(
    ("flags", "why"),
    [
        (["--body", "yarp"], "--body yarp needs --remote NAME"),
        (["--remote", "/icubSim"], "--remote goes with --body yarp"),
        (["--archery-rpc", "/icubSim/archery/rpc:i"], "--archery-rpc goes with --body yarp"),
        (["--body", "yarp", "--remote", "icubSim"], "--remote 'icubSim'"),
        (["--body", "yarp", "--remote", "/icubSim", "--rtf", "1"], "--rtf is the simulated"),
        (["--body", "yarp", "--remote", "/icubSim", "--robots", "2"], "--robots 2: a YARP"),
        (["--release-open", "5"], "--release-open goes with --body yarp"),
        (["--body", "yarp", "--remote", "/icubSim", "--landing", "sideways"], "invalid choice"),
    ],
)
def test_body_flags_that_do_not_fit_are_one_line_exit_2(
    flags: list[str], why: str, tmp_path: Path
) -> None:
    done = archery("up", "--logs", str(tmp_path / "logs"), "--runs", str(tmp_path), *flags)
    assert done.returncode == 2, done.stderr
    assert done.stderr.count("\n") == 1 and why in done.stderr, done.stderr
