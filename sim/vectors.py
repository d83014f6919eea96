"""Validation of the 3-vectors that configure the simulations (positions, wind; m, m/s)."""

from __future__ import annotations

import numpy as np

__all__ = ["vector3"]


def vector3(name: str, value: object, error: type[Exception]) -> tuple[float, float, float]:
    """`value` as 3 finite floats (x, y, z); raises `error` naming `name` otherwise."""
    try:
        array = np.asarray(value, dtype=float)
    except (TypeError, ValueError) as exc:
        raise error(f"{name} must be 3 numbers (x, y, z), got {value!r}") from exc
    if array.shape != (3,) or not np.all(np.isfinite(array)):
        raise error(f"{name} must be 3 finite numbers (x, y, z), got {value!r}")
    return (float(array[0]), float(array[1]), float(array[2]))
