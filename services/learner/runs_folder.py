"""Where the learner's `start` may point: journals inside its runs folder, nowhere else.

`start` takes paths from whoever reaches the learner's port: `resume` (a journal or its session
directory) and `from_journal` (a session id, its directory or its journal). `journal_in_runs`
resolves each one inside the learner's `--runs` folder by the rules its docstring lists; a path
that breaks one is a `BadRequest` naming the rule, and the reply tells nothing about the
learner's other files.
"""

from __future__ import annotations

import errno
import os
import stat
from pathlib import Path

from archery.protocol.errors import BadRequest
from archery.protocol.text import shown
from archery.services.learner.journal import JOURNAL_NAME, MAX_JOURNAL_BYTES, JournalError

__all__ = ["journal_in_runs"]


def _inside(path: Path, folders: tuple[Path, ...]) -> bool:
    return any(path == folder or path.is_relative_to(folder) for folder in folders)


def journal_in_runs(target: str, runs: Path, what: str) -> Path:
    """The journal `target` names, resolved inside the runs folder `runs`, as a path under
    `runs` as the learner was given it. The rules:

    * a relative path is taken from the runs folder (a session id is its directory there);
    * the path must lie inside the runs folder both as written (`..` may not leave it) and once
      every symlink is followed (a symlink inside may not lead out): an absolute path too;
    * a directory stands for its journal, `DIR/journal.jsonl`, checked the same way;
    * the journal must be a regular file (not a FIFO, device, socket or directory) of at most
      `MAX_JOURNAL_BYTES`.

    One outside the runs folder is refused with the same words whether it exists or not
    (nothing outside is opened or stat'ed). A journal inside the folder that does not exist is
    a `JournalError` ("cannot read journal …"). Nothing here opens the file: reading it
    (`journal.read_records`) opens it without blocking and checks it again on the descriptor,
    so a file swapped for a FIFO in between cannot wedge the learner either.

    Args:
        target: the path (or session id) the request gave.
        runs: the learner's runs folder.
        what: the argument it came in (e.g. "resume"), for the messages.

    Raises:
        BadRequest: outside the runs folder, not a regular file, bigger than
            `MAX_JOURNAL_BYTES`, or not a path at all (a NUL in it); the message says which.
        JournalError: no such journal (or session) inside the runs folder, or it cannot be
            looked at (e.g. permissions).
    """
    quoted = f"{what} {shown(target)}"
    real_folder = Path(os.path.realpath(runs))
    real, info = _looked_up(target, runs, what)
    if stat.S_ISDIR(info.st_mode):  # a session's directory: its journal, looked up the same way
        real, info = _looked_up(os.path.join(target, JOURNAL_NAME), runs, what)
    if not stat.S_ISREG(info.st_mode):
        raise BadRequest(
            f"{quoted} is not a regular file: a journal must be one (not a FIFO, device, "
            f"socket or directory)"
        )
    if info.st_size > MAX_JOURNAL_BYTES:
        raise BadRequest(
            f"{quoted} holds {info.st_size} bytes: a journal holds at most {MAX_JOURNAL_BYTES} "
            f"bytes (about 2,000 rollouts)"
        )
    return Path(runs) / real.relative_to(real_folder)


def _looked_up(target: str, runs: Path, what: str) -> tuple[Path, os.stat_result]:
    """`target`'s real path inside the runs folder and what `os.stat` says of it (nothing
    outside the folder is stat'ed unless a symlink inside leads there, and then only to refuse
    it).

    Raises:
        BadRequest: outside the runs folder, or a NUL in the path.
        JournalError: nothing there, or it cannot be looked at.
    """
    quoted = f"{what} {shown(target)}"
    folder = Path(os.path.abspath(runs))
    real_folder = Path(os.path.realpath(runs))
    written = Path(os.path.normpath(folder / target))  # an absolute target replaces folder
    if not _inside(written, (folder, real_folder)):
        raise _outside(quoted, runs)
    try:
        real = Path(os.path.realpath(written))
        if not _inside(real, (real_folder,)):
            raise _outside(quoted, runs)
        return real, os.stat(real)
    except BadRequest:
        raise
    except ValueError:  # a NUL in the path
        raise BadRequest(f"{quoted}: a journal path holds no NUL character") from None
    except OSError as exc:
        why = (
            f"no such journal or session in the runs folder {runs}"
            if exc.errno in (errno.ENOENT, errno.ENOTDIR)
            else exc.strerror or str(exc)
        )
        raise JournalError(f"{what}: cannot read journal {shown(target)}: {why}") from None


def _outside(quoted: str, runs: Path) -> BadRequest:
    return BadRequest(
        f"{quoted} is outside the learner's runs folder {runs}: a journal path must lie "
        f"inside it as written and once symlinks are followed (a relative path is taken "
        f"from it)"
    )
