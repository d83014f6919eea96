"""A child process's own peak memory: `archery ARGS` run under a small launcher.

Linux carries a process's peak RSS (`ru_maxrss`) across fork and exec: a child forked from a
big process (a test run, a benchmark holding data) reports at least its parent's RSS. So the
command is forked from a launcher of a few MiB (a bare Python) that waits for it with
`os.wait4` and reports the command's own peak.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from dataclasses import dataclass

__all__ = ["PeakRun", "run_with_peak"]

_LAUNCHER = """
import os, sys
report = int(sys.argv[1])
pid = os.fork()
if pid == 0:
    os.close(report)
    os.execv(sys.executable, [sys.executable, *sys.argv[2:]])
_, status, usage = os.wait4(pid, 0)
os.write(report, str(usage.ru_maxrss).encode())
sys.exit(os.waitstatus_to_exitcode(status))
"""


@dataclass(frozen=True)
class PeakRun:
    """What `run_with_peak` saw: exit status, output, and the command's peak RSS (MiB)."""

    status: int
    stdout: str
    stderr: str
    peak_mib: float


def run_with_peak(*args: str, timeout: float = 120.0) -> PeakRun:
    """`python -m archery.apps.cli ARGS` (the tree's own CLI) and its own peak RSS.

    Raises:
        subprocess.TimeoutExpired: still running after `timeout` s (it is killed).
    """
    read_end, write_end = os.pipe()
    os.set_inheritable(write_end, True)
    try:
        proc = subprocess.Popen(
            [sys.executable, "-c", _LAUNCHER, str(write_end), "-m", "archery.apps.cli", *args],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            stdin=subprocess.DEVNULL,
            pass_fds=(write_end,),
            start_new_session=True,
            text=True,
        )
    except BaseException:
        os.close(read_end)
        os.close(write_end)
        raise
    os.close(write_end)
    try:
        stdout, stderr = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.communicate()
        os.close(read_end)
        raise
    with os.fdopen(read_end, "rb") as report:
        kib = report.read().decode() or "0"
    return PeakRun(proc.returncode, stdout, stderr, int(kib) / 1024)  # ru_maxrss: KiB
