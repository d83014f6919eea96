"""Listen only where told: the kernel's socket table of a whole mesh running a session.

With the default flags, only the router listens (on the one endpoint it was given), and every
other process, services and the `learn` client alike, has exactly its links to that endpoint:
no listener on any interface, no connection to an address it was not given.
"""

from __future__ import annotations

import contextlib
import subprocess
import sys
from pathlib import Path

import psutil
import pytest

from archery.apps.up.launch_config import SERVICES
from archery.apps.up.launcher import Launcher
from archery.mesh.router import free_tcp_endpoint


def _sockets(pid: int) -> list[psutil._common.pconn]:
    """The inet sockets of a process and its descendants."""
    proc = psutil.Process(pid)
    found = []
    for p in [proc, *proc.children(recursive=True)]:
        with contextlib.suppress(psutil.NoSuchProcess):
            found.extend(p.net_connections(kind="inet"))
    return found


def _check_client(name: str, pid: int, router: tuple[str, int]) -> int:
    """Assert that every socket of `pid` is a TCP link to the router; return how many."""
    sockets = _sockets(pid)
    for s in sockets:
        assert s.status != psutil.CONN_LISTEN, f"{name} listens on {s.laddr}"
        assert s.raddr, f"{name} has an unconnected socket {s}"
        assert (s.raddr.ip, s.raddr.port) == router, f"{name} is linked to {s.raddr}"
        assert s.laddr.ip == router[0], f"{name} uses the local address {s.laddr.ip}"
    return len(sockets)


@pytest.mark.slow
def test_every_socket_of_a_running_mesh_is_on_the_given_loopback_endpoint(
    tmp_path: Path,
) -> None:
    endpoint = free_tcp_endpoint()
    host, port = endpoint.split("/", 1)[1].rsplit(":", 1)
    router = (host, int(port))
    robot = "loopback"
    with Launcher(endpoint, robot, tmp_path / "logs") as launcher:
        launcher.up(120)
        learn = subprocess.Popen(
            [
                *(sys.executable, "-m", "archery.apps.cli", "learn", "--connect", endpoint),
                *("--robot", robot, "--rollouts", "2", "--no-until-hit", "--quiet"),
            ],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        linked = 0
        try:
            while learn.poll() is None:  # sample the client's sockets for as long as it runs
                try:
                    linked = max(linked, _check_client("learn", learn.pid, router))
                except psutil.NoSuchProcess:
                    break
            out, err = learn.communicate(timeout=120)
        finally:
            if learn.poll() is None:
                learn.kill()
        assert learn.returncode == 0, err
        assert '"status": "finished"' in out
        assert linked >= 1, "the learn client was never seen linked to the router"

        for name in SERVICES:
            assert _check_client(name, launcher.children[name].proc.pid, router) >= 1, name
        router_sockets = _sockets(launcher.children["router"].proc.pid)
        listening = {(s.laddr.ip, s.laddr.port) for s in router_sockets if not s.raddr}
        assert listening == {router}
        for s in router_sockets:
            assert s.type == psutil.socket.SOCK_STREAM, f"the router has a non-TCP socket {s}"
            if s.raddr:
                assert s.laddr == router and s.raddr.ip == host, f"router link {s}"
        assert launcher.first_exit() is None
