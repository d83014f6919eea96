"""Shared fixtures: a real Zenoh router on a free loopback port, per-test robot prefixes.

The suite runs in what a user's shell has: the rendering variables a harness or a developer's
shell may carry are removed before anything is imported, so the product picks its backend
itself (`sim.gl_backend`) in every test and every child process, as it does for a user.
"""

from __future__ import annotations

import os

for _variable in ("MUJOCO_GL", "PYOPENGL_PLATFORM"):
    os.environ.pop(_variable, None)

import itertools
import signal
import subprocess
import sys
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

import pytest

from archery.mesh.netflags import NetConfig
from archery.mesh.router import free_tcp_endpoint, spawn_router

_counter = itertools.count()


@pytest.fixture(autouse=True)
def _children_exit_statuses() -> Iterator[None]:
    """In a process where YARP's devices have run (remote_controlboard in a test's own process),
    SIGCHLD is ignored and every child's exit status reads 0: each test starts and ends with
    the default, so the statuses it and the next module's fixtures read are the children's."""
    signal.signal(signal.SIGCHLD, signal.SIG_DFL)
    yield
    signal.signal(signal.SIGCHLD, signal.SIG_DFL)


@pytest.fixture(scope="session")
def router_endpoint() -> Iterator[str]:
    """A real `archery router` process on a free loopback port, for the whole test session."""
    endpoint = free_tcp_endpoint()
    proc = spawn_router(endpoint)
    yield endpoint
    proc.terminate()
    proc.wait(timeout=10)


@pytest.fixture
def net(router_endpoint: str) -> NetConfig:
    """Network settings for one test: the shared router and a robot prefix of its own."""
    return NetConfig(connect=(router_endpoint,), robot=f"t{os.getpid()}x{next(_counter)}")


def archery(*args: str, timeout: float = 60.0) -> subprocess.CompletedProcess[str]:
    """Run the `archery` CLI in a child process and capture its output."""
    return subprocess.run(
        [sys.executable, "-m", "archery.apps.cli", *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        stdin=subprocess.DEVNULL,
    )


@contextmanager
def serving(run: Callable[[Any, threading.Event], None], config: Any) -> Iterator[None]:
    """A service `run(config, stop)` on a thread until the block ends; its failure fails a test."""
    stop = threading.Event()
    failed: list[BaseException] = []

    def target() -> None:
        try:
            run(config, stop)
        except BaseException as exc:
            failed.append(exc)

    thread = threading.Thread(target=target, daemon=True)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join(timeout=15)
        assert not thread.is_alive(), "the service did not stop"
        assert not failed, failed
