"""One child process of `archery up` and its log (`apps.up.logfile`: rotating, bounded)."""

from __future__ import annotations

import ctypes
import os
import shlex
import signal
import subprocess
import threading
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from archery.apps.up.logfile import LOG_FILES, RotatingLog, pump, read_tail

__all__ = ["DRAIN_WAIT", "Child", "die_with_parent", "popen_tied", "spawn"]

_PR_SET_PDEATHSIG = 1
DRAIN_WAIT = 5.0  # s to wait for the last of an ended child's output to reach its log


@dataclass
class Child:
    """One child process and its log.

    Attributes:
        name: its name in `archery up` (`router` or a service's id).
        argv: its command line.
        log: its live log file (`LOGS/NAME.log`; older output in `NAME.log.1`, …).
        proc: the process, once started.
        started: when it started (monotonic s).
        output: the rotating log its output goes to.
        pump: the thread copying its output (a pipe) into `output`.
    """

    name: str
    argv: list[str]
    log: Path
    proc: subprocess.Popen[bytes] | None = None
    started: float = field(default=0.0)
    output: RotatingLog | None = None
    pump: threading.Thread | None = None

    def drain(self, timeout: float = DRAIN_WAIT) -> None:
        """Once it has ended, wait (at most `timeout` s) until the rest of its output is in its
        log (a child's last words, e.g. why it exited, may still be in the pipe)."""
        if self.pump is not None and self.returncode is not None:
            self.pump.join(timeout)

    def tail(self, lines: int = 12) -> str:
        """The last lines of its log (all of its output, once it has ended)."""
        self.drain()
        files = self.output.files if self.output is not None else LOG_FILES
        return read_tail(self.log, lines, files)

    @property
    def returncode(self) -> int | None:
        """Its exit status once it has ended (negative: killed by that signal)."""
        return None if self.proc is None else self.proc.poll()


def spawn(name: str, argv: list[str], output: RotatingLog, env: Mapping[str, str]) -> Child:
    """Start `argv` as a child that dies with this process, in a session of its own, its stdout
    and stderr piped into `output` (after a line naming the command).

    Raises:
        OSError: it could not be started.
    """
    output.write(f"--- {time.strftime('%H:%M:%S')} {shlex.join(argv)}\n".encode())
    read, write = os.pipe()  # neither end is inherited but as the child's stdout and stderr
    try:
        proc = subprocess.Popen(
            argv,
            stdin=subprocess.DEVNULL,
            stdout=write,
            stderr=subprocess.STDOUT,
            env=dict(env),
            start_new_session=True,  # a terminal's Ctrl-C reaches only us; we stop them
            preexec_fn=die_with_parent,
        )
    except BaseException:
        os.close(read)
        raise
    finally:
        os.close(write)  # the child holds it now: end of file when the child ends
    started = time.monotonic()
    return Child(name, argv, output.path, proc, started, output, pump(read, output, name))


def die_with_parent() -> None:
    """In the child before exec: get SIGTERM when the parent dies (Linux), so no orphans."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(_PR_SET_PDEATHSIG, signal.SIGTERM)
    except (OSError, AttributeError):
        pass


def popen_tied(argv: list[str], **options: Any) -> subprocess.Popen[bytes]:
    """`subprocess.Popen(argv, **options)` of a child that gets SIGTERM when this process ends,
    however it ends (`die_with_parent`). Linux ties that signal to the thread that started the
    child, so it is started on a thread of its own that lasts as long as the child.

    Raises:
        OSError: it could not be started.
    """
    started: list[subprocess.Popen[bytes] | BaseException] = []
    ready = threading.Event()

    def run() -> None:
        try:
            proc = subprocess.Popen(argv, preexec_fn=die_with_parent, **options)
        except BaseException as exc:
            started.append(exc)
            ready.set()
            return
        started.append(proc)
        ready.set()
        proc.wait()

    threading.Thread(target=run, name=f"tied {Path(argv[0]).name}", daemon=True).start()
    ready.wait()
    if isinstance(started[0], BaseException):
        raise started[0]
    return started[0]
