"""One child process of `archery up` and its log file."""

from __future__ import annotations

import subprocess
from dataclasses import dataclass, field
from pathlib import Path

__all__ = ["Child"]


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
