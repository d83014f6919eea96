"""`archery up` and its Launcher: start, liveliness, a child's death, clean stops, a busy port."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from archery.apps.topics.recording import open_recording
from archery.apps.up.launch_config import SERVICES
from archery.apps.up.launcher import Launcher, LaunchError
from archery.mesh.netflags import NetConfig
from archery.mesh.node import Node
from archery.mesh.router import free_tcp_endpoint, open_router, wait_for_endpoint
from archery.protocol.errors import ConfigError
from archery.protocol.messages import Image


def test_launcher_starts_watches_and_stops(tmp_path: Path) -> None:
    endpoint = free_tcp_endpoint()
    with Launcher(endpoint, "up1", tmp_path / "logs") as launcher:
        took = launcher.up(60, services=("robot", "controller"))
        assert took < 60
        net = NetConfig(connect=(endpoint,), robot="up1")
        with Node(None, net) as node:
            node.wait_alive(["robot", "controller"], timeout=10)
        assert launcher.first_exit() is None
        launcher.kill("controller")
        dead = launcher.first_exit()
        assert dead is not None and dead.name == "controller"
        assert "controller was killed by signal 9" in launcher.describe_exit(dead)
        launcher.start("controller")  # a restart
        launcher.wait_alive(["controller"], 60)
        codes = launcher.stop_all()
    assert codes == {"robot": 0, "controller": 0, "router": 0}
    assert "robot" in (tmp_path / "logs" / "robot.log").read_text()


def test_a_child_that_fails_at_start_is_named(tmp_path: Path) -> None:
    endpoint = free_tcp_endpoint()
    launcher = Launcher(endpoint, "up2", tmp_path, service_args={"robot": ["--rtf", "-3"]})
    with pytest.raises(LaunchError, match="robot exited with status 2") as error:
        launcher.up(60, services=("robot",))
    assert "--rtf" in str(error.value)  # the end of its log says why
    assert all(c.returncode is not None for c in launcher.children.values())


def test_bad_settings(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="no service 'robots'; services: robot"):
        Launcher(free_tcp_endpoint(), "x", tmp_path, service_args={"robots": []})
    endpoint = free_tcp_endpoint()
    with open_router(endpoint):
        launcher = Launcher(endpoint, "x", tmp_path)
        with pytest.raises(ConfigError, match="Is another router or `archery up` running"):
            launcher.start_router()
        assert launcher.children == {}
        # a secure router's port: the hint keeps its tls/ form
        secure = Launcher(endpoint.replace("tcp/", "tls/"), "x", tmp_path)
        with pytest.raises(ConfigError, match=r"Use --listen tls/127\.0\.0\.1:PORT"):
            secure.start_router()


def _up(endpoint: str, tmp_path: Path, *extra: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [
            sys.executable,
            "-m",
            "archery.apps.cli",
            "up",
            "--listen",
            endpoint,
            "--robot",
            "upcli",
            "--logs",
            str(tmp_path / "logs"),
            "--runs",
            str(tmp_path / "runs"),
            *extra,
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def test_up_port_in_use(tmp_path: Path) -> None:
    endpoint = free_tcp_endpoint()
    with open_router(endpoint):
        proc = _up(endpoint, tmp_path)
        _, err = proc.communicate(timeout=60)
    assert proc.returncode == 2
    assert f"cannot listen on {endpoint}" in err


@pytest.mark.slow
def test_up_starts_all_and_stops_cleanly_on_ctrl_c(tmp_path: Path) -> None:
    endpoint = free_tcp_endpoint()
    proc = _up(endpoint, tmp_path, "--record", str(tmp_path / "run.mcap"))
    try:
        net = NetConfig(connect=(endpoint,), robot="upcli")
        deadline = time.monotonic() + 120
        while True:  # the router must be up before a node can connect
            assert proc.poll() is None, proc.communicate()
            try:
                with Node(None, net) as node:
                    node.wait_alive(SERVICES, timeout=max(1.0, deadline - time.monotonic()))
                break
            except ConfigError:
                time.sleep(0.2)
        assert proc.stdout is not None
        started = proc.stdout.readline() + proc.stdout.readline() + proc.stdout.readline()
        assert "all alive" in started and "recording to" in started, started
        with Node(None, net) as node:  # the camera's frames reach the recorder
            frames = node.subscribe(node.keys.cam_frames(), Image)
            frames.wait_newer(30)
            # and a later one (an unchanged view goes out at the camera's rest rate, 1/s): the
            # recorder, subscribed since it started, has had the first well before Ctrl-C
            frames.wait_newer(30)
        proc.send_signal(signal.SIGINT)
        try:
            out, err = proc.communicate(timeout=90)
        except subprocess.TimeoutExpired:
            proc.kill()
            out, err = proc.communicate()
            logs = {p.name: p.read_text()[-600:] for p in (tmp_path / "logs").glob("*.log")}
            raise AssertionError(f"up did not stop: {out}\n{err}\n{logs}") from None
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err
    assert "all stopped cleanly" in out
    for name in SERVICES:
        assert (tmp_path / "logs" / f"{name}.log").exists()
    recording = open_recording(tmp_path / "run.mcap")
    assert recording.complete and recording.metadata["robot"] == "upcli"
    keys = {key for key, _, _ in recording.messages()}
    assert {"upcli/cam/target:o", "upcli/world/state:o", "upcli/torso/state:o"} <= keys


def _children_of(endpoint: str) -> list[int]:
    """The pids of processes whose command line names `endpoint` (`up`'s children)."""
    pids = []
    for entry in Path("/proc").iterdir():
        try:
            cmdline = (entry / "cmdline").read_bytes()
        except OSError:
            continue
        if entry.name.isdigit() and endpoint.encode() in cmdline and b"archery.apps.cli" in cmdline:
            pids.append(int(entry.name))
    return pids


def test_ctrl_c_while_starting_stops_everything_at_once(tmp_path: Path) -> None:
    """SIGINT as soon as the router listens, while 3 robot stacks are starting: `up` stops all
    it started and exits 130 (the goal: within 5 s; asserted with room for a loaded machine)."""
    endpoint = free_tcp_endpoint()
    proc = _up(endpoint, tmp_path, "--robots", "3")
    try:
        wait_for_endpoint(endpoint, 60)
        started = time.monotonic()
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=30)
        took = time.monotonic() - started
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, err
    assert "interrupted while starting" in err
    assert took < 15, took
    deadline = time.monotonic() + 10
    while _children_of(endpoint) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert _children_of(endpoint) == []
