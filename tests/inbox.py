"""What one Zenoh subscriber of a test received, with waits on conditions (never on sleeps)."""

from __future__ import annotations

import threading

import zenoh

__all__ = ["Inbox"]


class Inbox:
    """The samples one subscriber received (a subscriber's callback), in order.

    Args:
        probe: a key whose samples only show that the subscription reached the router;
            `received` leaves them out unless asked.
    """

    def __init__(self, probe: str = "") -> None:
        self.probe = probe
        self.items: list[tuple[str, bytes]] = []
        self._cond = threading.Condition()

    def __call__(self, sample: zenoh.Sample) -> None:
        with self._cond:
            self.items.append((str(sample.key_expr), sample.payload.to_bytes()))
            self._cond.notify_all()

    def payloads(self) -> list[bytes]:
        """The payloads received, in order."""
        return [p for _, p in self.items]

    def received(self, probe: str = "") -> list[str]:
        """The keys received, in order (the probe's only when `probe` names it)."""
        return [k for k, _ in self.items if k != self.probe or k == probe]

    def wait_for(self, payload: bytes, timeout: float = 10.0) -> bool:
        """Whether `payload` has arrived (waiting up to `timeout` s)."""
        with self._cond:
            return self._cond.wait_for(lambda: payload in self.payloads(), timeout)

    def wait_for_key(self, key: str, n: int = 1, timeout: float = 10.0) -> bool:
        """Whether `n` samples on `key` have arrived (waiting up to `timeout` s)."""
        with self._cond:
            return self._cond.wait_for(lambda: self.received(key).count(key) >= n, timeout)
