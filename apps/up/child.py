"""One child process of `archery up` and its log file."""

from __future__ import annotations

import ctypes
import signal
import subprocess
from dataclasses import dataclass, field
from pathlib import Path

__all__ = ["Child", "die_with_parent"]

_PR_SET_PDEATHSIG = 1


@dataclass
class Child:
    """One child process and its log file."""

    name: str
    argv: list[str]
    log: Path
    proc: subprocess.Popen[bytes] | None = None
    started: float = field(default=0.0)

    def tail(self, lines: int = 12) -> str:
        """The last lines of its log."""
        try:
            text = self.log.read_text(errors="replace")
        except OSError:
            return ""
        return "\n".join(text.rstrip().splitlines()[-lines:])

    @property
    def returncode(self) -> int | None:
        """Its exit status once it has ended (negative: killed by that signal)."""
        return None if self.proc is None else self.proc.poll()


def die_with_parent() -> None:
    """In the child before exec: get SIGTERM when the parent dies (Linux), so no orphans."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(_PR_SET_PDEATHSIG, signal.SIGTERM)
    except (OSError, AttributeError):
        pass
