"""The liveliness tokens under one key expression, kept current: who is alive, and waiting
for a condition on that set (by liveliness events, never by polling)."""

from __future__ import annotations

import threading
from collections.abc import Callable

import zenoh

__all__ = ["TokenSet"]


class TokenSet:
    """The last key segments (service names, instance ids…) of the live tokens matching
    `key_expr`. Use as a context manager, or `close()` it.

    Args:
        session: the Zenoh session to subscribe with.
        key_expr: e.g. `ROBOT/alive/*` (service names) or `ROBOT/alive/NAME/*` (instances).
        history: also receive the tokens declared before the subscription.
    """

    def __init__(self, session: zenoh.Session, key_expr: str, history: bool = True) -> None:
        self._present: set[str] = set()
        self._cond = threading.Condition()
        self._sub: zenoh.Subscriber[None] | None = session.liveliness().declare_subscriber(
            key_expr, self._on_token, history=history
        )

    def _on_token(self, sample: zenoh.Sample) -> None:
        segment = str(sample.key_expr).rsplit("/", 1)[-1]
        with self._cond:
            if sample.kind == zenoh.SampleKind.PUT:
                self._present.add(segment)
            else:
                self._present.discard(segment)
            self._cond.notify_all()

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
