"""`archery ARGS…` as a child process that says when it is set up (tests and benchmarks)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

__all__ = ["spawn"]


def spawn(
    *args: str, ready: str, env: dict[str, str] | None = None, cwd: Path | None = None
) -> subprocess.Popen[str]:
    """`archery ARGS…` as a child process (text pipes; `env`, `cwd`: its environment and
    working folder, default this process's), returned once its first stdout line, which must
    start with `ready`, says it is set up (tests and benchmarks).

    Raises:
        RuntimeError: it printed something else first, or ended; with its stderr.
    """
    proc = subprocess.Popen(
        [sys.executable, "-m", "archery.apps.cli", *args],
        stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
        cwd=cwd,
    )
    assert proc.stdout is not None and proc.stderr is not None
    line = proc.stdout.readline()
    if not line.startswith(ready):
        proc.kill()
        raise RuntimeError(f"archery {args[0]} did not start: {line!r} {proc.stderr.read()}")
    return proc
