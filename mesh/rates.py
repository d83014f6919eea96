"""How often each caller identity may ask for an expensive read: a token bucket per identity.

A server whose verb costs real work per call (the camera's `grab` a render, the detector's
`frame` a PNG of its colour maps) takes at most `rate` calls a second from one identity, with
bursts of `burst`; past that the call is refused `busy` at once, so one identity's flood costs
the server almost nothing and takes nothing from the others (each has its own bucket). The
identity is the one the call's key names (`mesh.rpc_server.caller_or_anonymous`: vouched for
by the router in secure mode; every call that names none shares one bucket).
"""

from __future__ import annotations

import threading
import time

from archery.protocol.errors import Busy
from archery.protocol.text import shown

__all__ = ["MAX_IDENTITIES", "RateLimit"]

MAX_IDENTITIES = 256  # buckets kept at most (the least recently used forgotten first)


class RateLimit:
    """At most `rate` calls per second per identity, in bursts of up to `burst` calls.

    Args:
        what: the call, for the refusal's message (e.g. "detector frame").
        rate: calls per second one identity may keep up (> 0).
        burst: calls one identity may make at once after a pause (≥ 1).
    """

    def __init__(self, what: str, rate: float, burst: int) -> None:
        if rate <= 0 or burst < 1:
            raise ValueError(f"a rate limit needs rate > 0 and burst ≥ 1, not {rate}, {burst}")
        self.what = what
        self.rate = rate
        self.burst = burst
        self.refused = 0  # calls refused so far (all identities)
        self._lock = threading.Lock()
        self._tokens: dict[str, tuple[float, float]] = {}  # identity: (tokens, monotonic s)

    def take(self, identity: str) -> None:
        """Count one call of `identity`.

        Raises:
            Busy: `identity` is past its rate; the message says the limit and when to retry.
        """
        now = time.monotonic()
        with self._lock:
            tokens, then = self._tokens.pop(identity, (float(self.burst), now))
            tokens = min(float(self.burst), tokens + (now - then) * self.rate)
            if tokens >= 1.0:
                self._tokens[identity] = (tokens - 1.0, now)
                self._forget()
                return
            self._tokens[identity] = (tokens, now)
            self.refused += 1
        retry = (1.0 - tokens) / self.rate
        raise Busy(
            f"{self.what}: busy, {shown(identity)} is past its rate of {self.rate:g} calls/s "
            f"(bursts of {self.burst}); try again in {retry:.2g} s"
        )

    def _forget(self) -> None:
        """Keep at most `MAX_IDENTITIES` buckets: drop the least recently used (a bucket
        forgotten is a full one again, which only ever allows more)."""
        while len(self._tokens) > MAX_IDENTITIES:
            del self._tokens[next(iter(self._tokens))]
