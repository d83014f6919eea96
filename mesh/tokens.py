"""The liveliness tokens under one key expression, kept current: who is alive, since when a
token is gone, and waiting for a condition on that set (by liveliness events, never by
polling). Every liveliness wait of the project uses it."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import zenoh

__all__ = ["TokenSet", "last_segment"]


def last_segment(key: str) -> str:
    """A token's key's last segment (a service name, an instance id)."""
    return key.rsplit("/", 1)[-1]


class TokenSet:
    """The names of the live tokens matching `key_expr`: by default their keys' last segments
    (service names, instance ids…). Use as a context manager, or `close()` it.

    Args:
        session: the Zenoh session to subscribe with.
        key_expr: e.g. `ROBOT/alive/*` (service names) or `ROBOT/alive/NAME/*` (instances).
        history: also receive the tokens declared before the subscription.
        name: a token's name from its key (`last_segment`; `str` keeps whole keys).
    """

    def __init__(
        self,
        session: zenoh.Session,
        key_expr: str,
        history: bool = True,
        name: Callable[[str], str] = last_segment,
    ) -> None:
        self._present: set[str] = set()
        self._gone_at: dict[str, float] = {}  # name -> monotonic s its token went
        self._name = name
        self._cond = threading.Condition()
        self._sub: zenoh.Subscriber[None] | None = session.liveliness().declare_subscriber(
            key_expr, self._on_token, history=history
        )

    def _on_token(self, sample: zenoh.Sample) -> None:
        name = self._name(str(sample.key_expr))
        with self._cond:
            if sample.kind == zenoh.SampleKind.PUT:
                self._present.add(name)
                self._gone_at.pop(name, None)
            else:
                self._present.discard(name)
                self._gone_at[name] = time.monotonic()
            self._cond.notify_all()

    def gone_for(self, name: str) -> float | None:
        """Seconds since `name`'s token went (None: alive, or not seen going)."""
        with self._cond:
            gone = self._gone_at.get(name)
        return None if gone is None else time.monotonic() - gone

    def present(self) -> set[str]:
        """The segments alive now (a copy)."""
        with self._cond:
            return set(self._present)

    def add(self, segments: set[str]) -> None:
        """Merge segments learnt otherwise (e.g. a liveliness query made before subscribing)."""
        with self._cond:
            self._present |= segments
            self._cond.notify_all()

    def wait_for(self, predicate: Callable[[set[str]], bool], timeout: float) -> bool:
        """Wait until `predicate(present)` holds; False after `timeout` s."""
        with self._cond:
            return self._cond.wait_for(lambda: predicate(self._present), timeout=timeout)

    def close(self) -> None:
        """Undeclare the subscriber (idempotent)."""
        if self._sub is not None:
            self._sub.undeclare()
            self._sub = None

    def __enter__(self) -> TokenSet:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
