"""The joint-state history: every part's encoder positions at each point of the joint-state grid
(`--state-rate` per simulated second), kept for the last `HISTORY_SPAN` s of simulated time,
whatever the rtf (`getHistory`).

At rtf 0 the `state:o` streams go out at most `--state-rate` times per wall second
(`pacing.due`): a movement that runs 50 times faster than the wall clock leaves most grid
points unpublished, and a recording sampled from the streams is too sparse for the DMPs that
learn from it. The grid points are kept here instead, at no cost to the streams' subscribers,
and a recording reads them once the movement is over. Simulation thread only (the loop's jobs
read it).
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np

from archery.protocol.verbs.robot import HISTORY_SPAN, MAX_HISTORY_POINTS

__all__ = ["StateHistory"]


class StateHistory:
    """A ring of (sim time, every part's positions) rows, one per joint-state period.

    Args:
        widths: each part's number of joints, in the order of a row.
        period: the joint-state period (s of simulated time).
        span: how long (s of simulated time) the rows are kept.
    """

    def __init__(self, widths: Mapping[str, int], period: float, span: float = HISTORY_SPAN):
        self._slices: dict[str, slice] = {}
        start = 0
        for part, width in widths.items():
            self._slices[part] = slice(start, start + width)
            start += width
        self._size = min(MAX_HISTORY_POINTS, math.ceil(span / period) + 1)
        self._times = np.zeros(self._size)
        self._rows = np.zeros((self._size, start))
        self._count = 0  # rows held
        self._next = 0  # where the next row goes

    def add(self, sim_time: float, row: np.ndarray) -> None:
        """Keep `row` (every part's positions, rad) at `sim_time` (s); a time not after the
        last one kept (the state at rest, repeated) is not kept again."""
        if self._count and sim_time <= self._times[(self._next - 1) % self._size]:
            return
        self._times[self._next] = sim_time
        self._rows[self._next] = row
        self._next = (self._next + 1) % self._size
        self._count = min(self._count + 1, self._size)

    def clear(self) -> None:
        """Forget every row (a reset: simulated time starts again at 0)."""
        self._count = 0
        self._next = 0

    def since(self, part: str, since: float) -> tuple[list[float], list[list[float]]]:
        """`part`'s times (s) and positions (rad) from `since` (s of simulated time) on."""
        order = (np.arange(self._count) + self._next - self._count) % self._size
        times = self._times[order]
        keep = order[times >= since]
        return self._times[keep].tolist(), self._rows[keep, self._slices[part]].tolist()
