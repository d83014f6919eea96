"""Each stream port's rate (messages/s) from its publisher's own message count, as the
services' `describe` replies report it: what the dashboard and the Foxglove bridge show."""

from __future__ import annotations

import threading
import time
from collections.abc import Mapping
from typing import Any

from archery.mesh.patterns import stream_type
from archery.protocol.messages import Describe

__all__ = ["PortRates", "stream_counts"]


def stream_counts(described: Mapping[str, Describe]) -> dict[str, int]:
    """{stream port key: messages its publisher sent} over every service's `describe` reply."""
    return {
        port.key: port.count
        for describe in described.values()
        for port in describe.ports
        if port.kind in ("pub", "events") and stream_type(port.key) is not None
    }


class PortRates:
    """Each stream port's rate from its publisher's message count, as the describe polls
    report it: the count's rise between two polls over the time between them (messages/s).

    Why counts (`PortInfo.count` in each service's `describe`) rather than subscribing to the
    streams: a subscriber would have the router forward every joint state and, for the
    camera's frames, make the camera render 1280×720 frames for nothing but a count.
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._counts: dict[str, tuple[float, int]] = {}  # key -> (when, count reported)
        self._rates: dict[str, float | None] = {}  # None: one report so far

    def update(self, counts: dict[str, int]) -> None:
        """One poll's counts {key: messages sent}; a key it lacks has lost its publisher."""
        now = time.monotonic()
        with self._lock:
            for key in self._rates.keys() - counts.keys():
                self._rates[key] = 0.0
                self._counts.pop(key, None)
            for key, total in counts.items():
                last = self._counts.get(key)
                self._counts[key] = (now, total)
                if last is None or total < last[1] or now <= last[0]:  # new, or restarted
                    self._rates[key] = None
                else:
                    self._rates[key] = (total - last[1]) / (now - last[0])

    def table(self) -> list[dict[str, Any]]:
        """Each stream port seen, with its rate (Hz; None until a second poll)."""
        with self._lock:
            rates = sorted(self._rates.items())
        return [{"key": k, "hz": None if v is None else round(v, 2)} for k, v in rates]
