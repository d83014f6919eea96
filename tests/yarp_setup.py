"""YARP for a test module, as a user configures it: YARP's own `yarpserver` on loopback, a
YARP configuration folder of the test's own that names it, `YARP_IP=127.0.0.1`, and YARP's
network initialised in the test process; all undone by `close`."""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from archery.apps.yarp.network import free_server_port

__all__ = ["YarpSetup"]


class YarpSetup:
    """`yarpserver` on 127.0.0.1:`self.port`, this process's YARP pointed at it (`self.env`:
    the environment a YARP tool of the test gets)."""

    def __init__(self, yarp: Any, folder: Path) -> None:
        self.yarp = yarp
        self.port = free_server_port("127.0.0.1")
        folder.mkdir(parents=True, exist_ok=True)
        (folder / "yarp.conf").write_text(f"127.0.0.1 {self.port} yarp\n")
        wanted = {"YARP_CONFIG_HOME": str(folder), "YARP_IP": "127.0.0.1"}
        self._before = {name: os.environ.get(name) for name in wanted}
        self.env = {**os.environ, **wanted}
        self.server = subprocess.Popen(
            [str(Path(sys.executable).parent / "yarpserver"), "--read", "--socket", str(self.port)],
            env=self.env,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            start_new_session=True,  # YARP's launcher script and the server it runs: one group
        )
        deadline = time.monotonic() + 30
        while not self._answers():
            if time.monotonic() > deadline or self.server.poll() is not None:
                os.killpg(self.server.pid, signal.SIGKILL)
                raise AssertionError(f"yarpserver did not start on {self.port}")
            time.sleep(0.05)
        os.environ.update(wanted)
        yarp.Network.init()
        # a process whose YARP met another name server before keeps its contact: this one's
        yarp.Network.setNameServerContact(yarp.Contact("/root", "tcp", "127.0.0.1", self.port))

    def _answers(self) -> bool:
        try:
            with socket.create_connection(("127.0.0.1", self.port), timeout=0.5):
                return True
        except OSError:
            return False

    def tool(self, name: str) -> str:
        """The path of one of YARP's tools beside this Python."""
        return str(Path(sys.executable).parent / name)

    def close(self) -> None:
        self.yarp.Network.fini()
        os.killpg(self.server.pid, signal.SIGTERM)
        self.server.communicate(timeout=60)
        for name, value in self._before.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value


def crash_output_port(raw: socket.socket) -> None:
    """YARP 3.5's own NULL dereference, on a connection `raw` to an output port: `CONNECT` then
    `r` (a request to read from a port that writes); returns when the bridge closes it, as it
    dies."""
    raw.sendall(b"CONNECT /probe\n")
    raw.sendall(b"r\n")
    raw.settimeout(10)
    with contextlib.suppress(OSError):
        while raw.recv(4096):
            pass
