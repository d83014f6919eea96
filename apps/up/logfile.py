"""A child's output in a bounded set of rotating files: `LOGS/NAME.log` (the newest),
`NAME.log.1`, … `NAME.log.{files-1}` (the oldest).

`archery up`'s children write to a pipe; one thread per child (`pump`) copies what comes out into
the child's `RotatingLog`, so a child's logs never take more than `files × file_bytes` on disk
(by default 3 × 8 MiB = 24 MiB: the last tens of thousands of lines), however much it writes,
and the journals that share the disk keep their room. A restarted child writes to the same
`RotatingLog` as the one before it.
"""

from __future__ import annotations

import os
import threading
from pathlib import Path

__all__ = ["LOG_FILES", "LOG_FILE_BYTES", "RotatingLog", "pump", "read_tail"]

LOG_FILE_BYTES = 8 * 1024 * 1024  # bytes of one log file at most
LOG_FILES = 3  # files per child: NAME.log and NAME.log.1 .. NAME.log.2
_TAIL_BYTES = 64 * 1024  # bytes read from the end of the logs for `read_tail`
_CHUNK = 64 * 1024  # bytes read from a child's pipe at a time


def _rotated(path: Path, index: int) -> Path:
    return path if index == 0 else path.with_name(f"{path.name}.{index}")


class RotatingLog:
    """Appends a child's output to `path`, rotating it through `files` files of at most
    `file_bytes` bytes each (thread-safe).

    When the live file would pass `file_bytes`, it becomes `NAME.log.1` (the older ones move up
    one and the oldest is dropped) and a new `NAME.log` begins, at a line's end where one falls
    within the bound.

    Args:
        path: the live file, `LOGS/NAME.log`.
        file_bytes: bytes per file at most (≥ 1).
        files: files kept, the live one included (≥ 2).

    Attributes:
        written: bytes of output taken in so far (on disk, rotated away or dropped).
        dropped: bytes of output lost because the disk refused them.
    """

    def __init__(
        self, path: Path, file_bytes: int = LOG_FILE_BYTES, files: int = LOG_FILES
    ) -> None:
        if file_bytes < 1 or files < 2:
            raise ValueError(
                f"a rotating log needs file_bytes >= 1 and files >= 2, got {file_bytes} and {files}"
            )
        self.path = path
        self.file_bytes = file_bytes
        self.files = files
        self.written = 0
        self.dropped = 0
        self._lock = threading.Lock()
        self._fd: int | None = None
        self._size = 0

    @property
    def paths(self) -> list[Path]:
        """Every file of this log, the live one first."""
        return [_rotated(self.path, i) for i in range(self.files)]

    def _open(self) -> int:
        if self._fd is None:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_APPEND | os.O_CLOEXEC)
            self._fd, self._size = fd, os.fstat(fd).st_size
            if self._size > self.file_bytes:  # written without this bound: keep its end
                os.lseek(fd, -self.file_bytes, os.SEEK_END)
                end = os.read(fd, self.file_bytes)
                os.ftruncate(fd, 0)
                os.write(fd, end)
                self._size = len(end)
        return self._fd

    def _rotate(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None
        for i in range(self.files - 1, 0, -1):
            older = _rotated(self.path, i - 1)
            if older.exists():
                os.replace(older, _rotated(self.path, i))
        self._size = 0

    def write(self, data: bytes) -> None:
        """Append `data`, rotating as needed; never raises for a full or failing disk (the
        bytes are counted in `dropped`)."""
        with self._lock:
            self.written += len(data)
            try:
                self._write(data)
            except OSError:
                self.dropped += len(data)
                if self._fd is not None:
                    os.close(self._fd)
                    self._fd = None

    def _write(self, data: bytes) -> None:
        while data:
            fd = self._open()
            room = self.file_bytes - self._size
            if len(data) <= room:
                os.write(fd, data)  # an O_APPEND write of a regular file writes it all
                self._size += len(data)
                return
            if room > 0:
                end = data.rfind(b"\n", 0, room) + 1  # rotate at a line's end if one fits
                if end == 0 and self._size == 0:
                    end = room  # one line longer than a whole file: cut it
                if end:
                    os.write(fd, data[:end])
                    data = data[end:]
            self._rotate()

    def close(self) -> None:
        """Close the live file (a later write opens it again)."""
        with self._lock:
            if self._fd is not None:
                os.close(self._fd)
                self._fd = None

    def tail(self, lines: int = 12) -> str:
        """The last `lines` lines written (`read_tail`)."""
        return read_tail(self.path, lines, self.files)


def read_tail(path: Path, lines: int = 12, files: int = LOG_FILES) -> str:
    """The last `lines` lines of the log `path` and its rotated files before it, reading at
    most 64 KiB of each from its end (undecodable bytes replaced)."""
    chunks: list[bytes] = []
    for i in range(files):
        try:
            with open(_rotated(path, i), "rb") as f:
                f.seek(0, os.SEEK_END)
                f.seek(max(0, f.tell() - _TAIL_BYTES))
                chunks.insert(0, f.read(_TAIL_BYTES))
        except OSError:
            continue  # not there (yet): the live file in the midst of a rotation
        if b"".join(chunks).count(b"\n") > lines:
            break
    text = b"".join(chunks).decode(errors="replace")
    return "\n".join(text.rstrip().splitlines()[-lines:])


def pump(source: int, log: RotatingLog, name: str) -> threading.Thread:
    """Start a thread that copies everything read from the descriptor `source` (a child's
    pipe) into `log` until end of file, then closes `source`. The pump never stops reading:
    when the disk refuses a write, that output is dropped (and counted,
    `RotatingLog.dropped`), so a child never blocks on a full pipe."""

    def run() -> None:
        try:
            while chunk := os.read(source, _CHUNK):
                log.write(chunk)
        except OSError:
            pass
        finally:
            os.close(source)

    thread = threading.Thread(target=run, name=f"log {name}", daemon=True)
    thread.start()
    return thread
