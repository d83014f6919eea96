"""Which parts of a YARP robot answer: a part whose encoders stay silent for the body's
`timeout` (its `yarpdev` stopped, its cable out) is lost: said once, its verbs refused
(`PartLost`), the robot service's liveliness token withdrawn (so a session waits for the robot
as for any lost service), its board opened again every `REOPEN_EVERY` s; once it reads again it
is back, said once, and the token returns. A reading refused (NaN, past the limits) is said
once per part and not published."""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections.abc import Callable, Iterator
from types import TracebackType

from archery.protocol.errors import PartLost
from archery.services.robot.jobs import SimUnavailable

__all__ = ["REOPEN_EVERY", "BoardsLock", "Presence"]

log = logging.getLogger("archery.robot")

REOPEN_EVERY = 1.0  # wall s between two attempts to open a lost part's board again


class BoardsLock:
    """The lock of a YARP body's calls: once `closing` has closed the boards, entering it raises
    `SimUnavailable` instead of calling a closed board."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._closed = False

    def __enter__(self) -> BoardsLock:
        self._lock.acquire()
        if self._closed:
            self._lock.release()
            raise SimUnavailable("the robot service stopped: its control boards are closed")
        return self

    def __exit__(
        self, kind: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self._lock.release()

    @contextlib.contextmanager
    def closing(self) -> Iterator[None]:
        """Hold the lock to close the boards; every later entry is refused."""
        with self._lock:
            self._closed = True
            yield


class Presence:
    """The parts' last readings and losses (the loop's lock held by every caller).

    Args:
        parts: the robot's parts.
        timeout: wall s of silence after which a part is lost.
        whole: called with False when a first part is lost, True when the last one is back.
    """

    def __init__(self, parts: tuple[str, ...], timeout: float, whole: Callable[[bool], None]):
        now = time.monotonic()
        self.timeout = timeout
        self.whole = whole
        self.read_at = dict.fromkeys(parts, now)  # monotonic s of each part's last reading
        self.lost: dict[str, float] = {}  # part → monotonic s it was found lost
        self.opened: dict[str, float] = {}  # lost parts opened again → monotonic s, not read yet
        self._refused: dict[str, str] = {}
        self._tried = 0.0

    def check(self, part: str) -> None:
        """Raises `PartLost` when `part` is lost."""
        if part in self.lost:
            raise PartLost(
                f"{part} is lost: its board has given no encoder reading for "
                f"{time.monotonic() - self.lost[part] + self.timeout:.1f} s; waiting for it"
            )

    def reads(self, part: str) -> bool:
        """Whether `part` is to be read now: not lost, or opened again."""
        return part not in self.lost or part in self.opened

    def read(self, part: str, now: float) -> bool:
        """`part` read at `now` (monotonic s); True when that makes it back (its targets are
        then where it stands)."""
        self.read_at[part] = now
        self._refused.pop(part, None)
        if part not in self.lost:
            return False
        del self.lost[part], self.opened[part]
        log.info("%s is back: its board answers and reads within its limits", part)
        if not self.lost:
            self.whole(True)
        return True

    def silent(self, part: str, board: str, now: float) -> None:
        """`part` gave no reading at `now`: lost once silent for `timeout` (opened again and
        still silent: to be opened again)."""
        if part in self.opened and now - self.opened[part] >= self.timeout:
            del self.opened[part]
        if part in self.lost or now - self.read_at[part] < self.timeout:
            return
        first = not self.lost
        self.lost[part] = now
        log.error(
            "%s is lost: %s has given no encoder reading for %.1f s (its yarpdev stopped?); "
            "its states stop, its verbs are refused, the robot is not alive until it is back",
            part,
            board,
            now - self.read_at[part],
        )
        if first:
            self.whole(False)

    def refused(self, part: str, reason: str) -> None:
        """`part`'s reading refused: said once until it reads again."""
        if self._refused.get(part) != reason:
            self._refused[part] = reason
            log.error("joint states of %s not published: %s", part, reason)

    def due(self, now: float) -> list[str]:
        """The lost parts to try to open again now (every `REOPEN_EVERY` s)."""
        waiting = [part for part in self.lost if part not in self.opened]
        if not waiting or now - self._tried < REOPEN_EVERY:
            return []
        self._tried = now
        return waiting

    def reopened(self, part: str, now: float) -> None:
        """`part`'s board is open again: back once it reads (`read`)."""
        self.opened[part] = now
        log.info("%s: its board opens again; back once it reads", part)
