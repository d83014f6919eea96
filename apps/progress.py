"""The progress bar every long-running tool shows on stderr (stdout stays for data)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from rich.progress import Progress

__all__ = ["progress_bar"]


def progress_bar(*info: Any, disable: bool = False, transient: bool = False) -> Progress:
    """A rich progress bar on stderr: the task's description, the bar, done of total, then the
    columns `info` (e.g. a `TextColumn` of rollouts/s), else the time elapsed. rich is imported
    here, not at module import, so a command that never shows a bar does not pay for it."""
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TimeElapsedColumn

    return Progress(
        "[progress.description]{task.description}",
        BarColumn(),
        MofNCompleteColumn(),
        *(info or (TimeElapsedColumn(),)),
        console=Console(stderr=True),
        disable=disable,
        transient=transient,
    )
