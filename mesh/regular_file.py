"""Reading a file a user names, bounded: a regular file only (a FIFO, a device or a folder is
refused without a blocking open or an endless read), of at most a given size, checked on the
open file. The callers (the learner's journal, a demonstration) word the refusal."""

from __future__ import annotations

import os
import stat
from typing import Literal

__all__ = ["FileRefused", "file_kind", "open_regular", "read_regular"]

Problem = Literal["cannot_open", "not_regular", "too_large", "grew"]


class FileRefused(Exception):
    """A file that is not read: `problem` says why, `detail` the OS's reason or what the file
    is (`file_kind`), `size` its bytes (too_large) or the cap it passed (grew)."""

    def __init__(self, problem: Problem, detail: str = "", size: int = 0) -> None:
        super().__init__(problem, detail, size)
        self.problem, self.detail, self.size = problem, detail, size


def file_kind(mode: int) -> str:
    """What a file of `mode` (`st_mode`) is, in a word or two: "a folder", "a FIFO", …"""
    kinds = (
        (stat.S_ISREG, "a regular file"),
        (stat.S_ISDIR, "a folder"),
        (stat.S_ISFIFO, "a FIFO"),
        (stat.S_ISCHR, "a character device"),
        (stat.S_ISBLK, "a block device"),
        (stat.S_ISSOCK, "a socket"),
    )
    return next((name for test, name in kinds if test(mode)), f"of mode {oct(mode)}")


def open_regular(path: str | os.PathLike[str], flags: int, max_bytes: int) -> int:
    """A descriptor of the regular file `path`, opened with `flags` and O_NONBLOCK (a FIFO or a
    device cannot block the open) and checked on the open file: at most `max_bytes` bytes.

    Raises:
        FileRefused: it cannot be opened (cannot_open), is not a regular file (not_regular)
            or is bigger than `max_bytes` (too_large).
    """
    try:
        fd = os.open(path, flags | os.O_NONBLOCK | os.O_NOCTTY | os.O_CLOEXEC)
    except OSError as exc:
        raise FileRefused("cannot_open", exc.strerror or str(exc)) from None
    try:
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode):
            raise FileRefused("not_regular", file_kind(info.st_mode))
        if info.st_size > max_bytes:
            raise FileRefused("too_large", size=info.st_size)
    except BaseException:
        os.close(fd)
        raise
    return fd


def read_regular(path: str | os.PathLike[str], max_bytes: int) -> bytes:
    """The bytes of the regular file `path` (`open_regular`), never more than `max_bytes` + 1
    read.

    Raises:
        FileRefused: as `open_regular`; cannot_open also for a failed read, grew for a file
            that passed `max_bytes` while being read.
    """
    fd = open_regular(path, os.O_RDONLY, max_bytes)
    try:
        with os.fdopen(fd, "rb", closefd=False) as f:
            data = f.read(max_bytes + 1)
    except OSError as exc:
        raise FileRefused("cannot_open", exc.strerror or str(exc)) from None
    finally:
        os.close(fd)
    if len(data) > max_bytes:
        raise FileRefused("grew", size=max_bytes)
    return data
