"""The observers whose cost `bench_record` measures: `archery record` and `archery dashboard`
with a client that polls the dashboard as its page does; and, for reference, a spinner: a
process that only burns the CPU nobody else wants (a busy loop in Linux's SCHED_IDLE class),
what any work beside the mesh costs it on this machine at the lowest priority there is."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import threading
import urllib.request
from pathlib import Path

import psutil

from archery.apps.dashboard.server import TOKEN_HEADER
from archery.mesh.router import free_tcp_endpoint
from tests.spawn import spawn

__all__ = ["CONDITIONS", "Observers", "PageClient", "cpu_seconds", "stop"]

#: (name, with the recorder, with the dashboard, with the spinner), the unwatched baseline first.
CONDITIONS = (
    ("none", False, False, False),
    ("recorder", True, False, False),
    ("dashboard", False, True, False),
    ("both", True, True, False),
    ("idle spinner", False, False, True),
)
#: the spinner's program: itself in SCHED_IDLE (it runs only on a core nothing else wants, and
#: yields it at once to any other thread), then a busy loop
SPIN = "import os\nos.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))\nwhile True: pass"
POLL = 0.5  # s: the page's poll period (`POLL_MS` in the dashboard's script)


def stop(proc: subprocess.Popen[str]) -> str:
    """SIGINT a child, wait for it and return its stdout.

    Raises:
        RuntimeError: it exited with another status than 0; with its stderr.
    """
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=120)
    if proc.returncode != 0:
        raise RuntimeError(f"exit {proc.returncode}: {err}")
    return out


def cpu_seconds(pids: dict[str, int]) -> dict[str, float]:
    """CPU time (user + system, s) each named process has used so far."""
    out = {}
    for name, pid in pids.items():
        times = psutil.Process(pid).cpu_times()
        out[name] = times.user + times.system
    return out


class PageClient:
    """Polls `/api/state` every `POLL` s and fetches `/api/frame.png` whenever the frame's
    version changes, like the dashboard's page in a browser; with `scene`, as a page with its
    scene panel open (a POST of `/api/scene` with the page's token before each poll,
    `/api/scene.jpg` whenever the view's version changes); counts its requests."""

    def __init__(self, url: str, scene: bool = False) -> None:
        self.url = url
        self.scene = scene
        self.states = 0
        self.frames = 0
        self.scenes = 0
        self.errors = 0
        self._token = ""  # the dashboard's, from its answers' `TOKEN_HEADER`
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="page-client", daemon=True)
        self._thread.start()

    def _get(self, path: str) -> bytes:
        with urllib.request.urlopen(self.url + path, timeout=10) as response:
            self._token = response.headers.get(TOKEN_HEADER, self._token)
            body: bytes = response.read()
            return body

    def _want_scene(self) -> None:
        """Ask for the scene view as the page does while its panel is open."""
        if not self._token:
            self._get("api/robots")
        request = urllib.request.Request(
            self.url + "api/scene", method="POST", headers={TOKEN_HEADER: self._token}
        )
        with urllib.request.urlopen(request, timeout=10) as response:
            response.read()

    def _run(self) -> None:
        version = scene = 0
        while not self._stop.wait(POLL):
            try:
                if self.scene:
                    self._want_scene()
                state = json.loads(self._get("api/state"))
                self.states += 1
                if state["frame"]["version"] != version:
                    version = state["frame"]["version"]
                    self._get(f"api/frame.png?v={version}")
                    self.frames += 1
                if self.scene and state["scene"]["version"] != scene:
                    scene = state["scene"]["version"]
                    self._get(f"api/scene.jpg?v={scene}")
                    self.scenes += 1
            except OSError:
                self.errors += 1

    def close(self) -> None:
        self._stop.set()
        self._thread.join(15)


class Observers:
    """Starts the observers of one condition on a mesh, and stops them (a context manager).

    Args:
        endpoint: the router's endpoint.
        robot: the robot recorded and watched.
        out: the recorder's file.
        recorder: run `archery record` (every key of the robot).
        dashboard: run `archery dashboard` and a client polling it.
        spinner: run the spinner (`SPIN`; not one of `pids`: its CPU is all there is).
        env: the observers' environment (default this process's), e.g. an earlier tree's.
        cwd: their working folder (default this process's): `python -m` imports from it first,
            so one outside any tree for an earlier tree's code.
    """

    def __init__(
        self,
        endpoint: str,
        robot: str,
        out: Path,
        *,
        recorder: bool,
        dashboard: bool,
        spinner: bool = False,
        env: dict[str, str] | None = None,
        cwd: Path | None = None,
    ) -> None:
        self.said: list[str] = []
        self._recorder: subprocess.Popen[str] | None = None
        self._dashboard: subprocess.Popen[str] | None = None
        self._spinner: subprocess.Popen[bytes] | None = None
        self._client: PageClient | None = None
        flags = ["--connect", endpoint, "--robot", robot]
        try:
            if spinner:
                self._spinner = subprocess.Popen([sys.executable, "-c", SPIN])
            if recorder:
                self._recorder = spawn(
                    "record",
                    "--out",
                    str(out),
                    "--force",  # each repeat records anew into the benchmark's own file
                    *flags,
                    ready="archery record: recording",
                    env=env,
                    cwd=cwd,
                )
            if dashboard:
                port = free_tcp_endpoint().rsplit(":", 1)[1]
                self._dashboard = spawn(
                    "dashboard",
                    "--port",
                    port,
                    *flags,
                    ready="archery dashboard: serving",
                    env=env,
                    cwd=cwd,
                )
                self._client = PageClient(f"http://127.0.0.1:{port}/")
        except BaseException:
            self.close()
            raise

    def pids(self) -> dict[str, int]:
        """The observers' processes: "recorder", "dashboard" (those that run)."""
        procs = {"recorder": self._recorder, "dashboard": self._dashboard}
        return {name: proc.pid for name, proc in procs.items() if proc is not None}

    def close(self) -> None:
        """Stop what runs; the recorder's and the client's summaries go to `said`."""
        if self._spinner is not None:
            spinner, self._spinner = self._spinner, None
            spinner.kill()
            spinner.wait()
        if self._client is not None:
            client, self._client = self._client, None
            client.close()
            self.said.append(
                f"page client: {client.states} states, {client.frames} frames, "
                f"{client.errors} errors"
            )
        for name in ("_dashboard", "_recorder"):
            proc = getattr(self, name)
            if proc is not None:
                setattr(self, name, None)
                lines = stop(proc).strip().splitlines()
                if lines:
                    self.said.append(lines[-1])

    def __enter__(self) -> Observers:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
