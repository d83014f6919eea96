"""`archery report PATH...`: draw `report.png` beside session journals, after the fact.

A learner service draws a session's report when the session ends; an experiment over a fleet
(`archery experiment --world mesh`) journals hundreds of sessions and draws none. This verb
draws them from the journals alone: each PATH is a `journal.jsonl`, a session's folder, or an
experiment's folder (every `sessions/*/journal.jsonl` under it). It prints the path of each
report written, one a line; a journal that cannot be read is named on stderr with the reason,
the others are still drawn, and the exit status is 1. A PATH that holds no journal exits 2
before anything is drawn.
"""

from __future__ import annotations

import sys
from argparse import ArgumentParser
from pathlib import Path

from archery.services.learner.journal import JournalError

__all__ = ["find_journals", "main"]

JOURNAL = "journal.jsonl"


def find_journals(path: Path) -> list[Path]:
    """The journals a PATH names (a journal, a session's folder, an experiment's folder).

    Raises:
        FileNotFoundError: the path does not exist or holds no journal (the message names it).
    """
    if path.is_file():
        return [path]
    if not path.is_dir():
        raise FileNotFoundError(f"{path}: no such file or folder")
    if (path / JOURNAL).is_file():
        return [path / JOURNAL]
    found = sorted(path.glob(f"sessions/*/{JOURNAL}")) or sorted(path.glob(f"*/{JOURNAL}"))
    if not found:
        raise FileNotFoundError(
            f"{path}: no {JOURNAL} in it, in its sessions/*/ or in its */ folders"
        )
    return found


def main(argv: list[str] | None = None) -> int:
    """Draw the reports; exit status 0, 1 (a journal could not be drawn) or 2 (bad PATH)."""
    parser = ArgumentParser(
        prog="archery report",
        description="draw report.png beside session journals (a journal, a session's folder, "
        "or an experiment's folder with sessions/*/journal.jsonl)",
    )
    parser.add_argument("path", nargs="+", type=Path, help="journals or folders")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    args = parser.parse_args(argv)
    try:
        journals = [j for path in args.path for j in find_journals(path)]
    except FileNotFoundError as exc:
        print(f"archery report: {exc}", file=sys.stderr)
        return 2
    from archery.apps.progress import progress_bar
    from archery.services.learner.report import write_report

    status = 0
    with progress_bar(disable=args.no_progress or len(journals) < 2) as bar:
        task = bar.add_task("reports", total=len(journals))
        for journal in journals:
            try:
                print(write_report(journal), flush=True)
            except (JournalError, OSError) as exc:
                print(f"archery report: {journal}: {exc}", file=sys.stderr)
                status = 1
            except (KeyError, TypeError, ValueError) as exc:  # JSON lines, but not a session's
                print(
                    f"archery report: {journal}: not a session journal ({type(exc).__name__}: "
                    f"{exc})",
                    file=sys.stderr,
                )
                status = 1
            bar.advance(task)
    return status
