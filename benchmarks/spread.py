"""How every benchmark writes a figure measured over repeats: the median and the spread."""

from __future__ import annotations

import statistics
from collections.abc import Sequence

__all__ = ["median_spread"]


def median_spread(values: Sequence[float], spec: str = ".2f", unit: str = "") -> str:
    """`median [min, max]` of `values`, each formatted with `spec` and followed by `unit`."""
    median, low, high = statistics.median(values), min(values), max(values)
    return f"{median:{spec}}{unit} [{low:{spec}}, {high:{spec}}]"
