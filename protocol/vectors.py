"""The check of the small fixed-size vectors the project passes around: positions and θ (m),
wind (m/s), axis-angles (unit axis, then rad), reward vectors (m).

`finite_vector` turns a value (a list, a tuple or a numeric numpy array) into a read-only float
array of the expected size, or raises the caller's own exception class with one message that
names the field, the size and the unit; `parse_vector` does the same for the text of a
command-line flag ("x,y,z"). Callers keep their exception classes (a bad request, a config error,
a bad command), so the code a reply carries and the exit status of a program stay theirs.

A string is not a vector (even of digits), nor is a bool a number. The value shown in a message
is cut short, so that a huge value cannot flood a log line or a reply.
"""

from __future__ import annotations

import numpy as np

from archery.protocol.text import shown

__all__ = ["MAX_SHOWN", "finite_vector", "parse_vector"]

MAX_SHOWN = 80  # characters of a rejected value quoted in a message, at most


def _message(name: str, size: int, unit: str, numbers: str, quoted: str) -> str:
    return f"{name} must be a finite {size}-vector ({unit}): {size} {numbers}, got {quoted}"


def _check_size(size: int) -> None:
    if isinstance(size, bool) or not isinstance(size, int) or size < 1:
        raise ValueError(f"size must be an integer >= 1, got {size!r}")


def _is_number(item: object) -> bool:
    return isinstance(item, int | float | np.integer | np.floating) and not isinstance(item, bool)


def finite_vector(
    name: str, value: object, error: type[Exception], *, size: int = 3, unit: str = "m"
) -> np.ndarray:
    """`value` as a read-only float array of shape (size,), every component finite.

    Args:
        name: the field, as the caller's user knows it (e.g. "θ", "scenario.theta0", "wind").
        value: a list or tuple of numbers (not bools, not strings), or a numpy array of integers
            or floats. The result is a copy: later changes to `value` do not reach it.
        error: the exception class to raise, called with the message alone.
        size: the number of components (>= 1).
        unit: the unit of the components, for the message (e.g. "m", "m/s").

    Returns:
        A new float64 array of shape (size,), not writable, in the unit `value` was given in.

    Raises:
        error: `value` is not `size` finite numbers, with the message
            "{name} must be a finite {size}-vector ({unit}): {size} finite numbers, got {value!r}"
            (the value cut to `MAX_SHOWN` characters).
        ValueError: `size` is not a positive integer (a mistake of the caller's code).
    """
    _check_size(size)
    array: np.ndarray | None = None
    if isinstance(value, np.ndarray):
        if value.dtype.kind in "iuf" and value.shape == (size,):
            array = np.array(value, dtype=float)
    elif isinstance(value, list | tuple) and len(value) == size and all(map(_is_number, value)):
        try:
            array = np.array(value, dtype=float)
        except OverflowError:  # an integer beyond the float range
            array = None
    if array is None or not np.all(np.isfinite(array)):
        raise error(_message(name, size, unit, "finite numbers", shown(value, MAX_SHOWN)))
    array.setflags(write=False)
    return array


def parse_vector(
    flag: str, text: str, error: type[Exception], *, size: int = 3, unit: str = "m"
) -> np.ndarray:
    """The vector the text of a command-line flag gives: `size` comma-separated numbers, e.g.
    "0.2,0,-0.03" or "0.2, 0, -0.03" (spaces around the commas are allowed).

    Args:
        flag: the flag, as typed (e.g. "--wind"); the message names it.
        text: the flag's value.
        error: the exception class to raise (what the program turns into its exit status).
        size: the number of components (>= 1).
        unit: the unit of the components, for the message (e.g. "m", "m/s").

    Returns:
        A read-only float64 array of shape (size,), see `finite_vector`.

    Raises:
        error: `text` is not `size` comma-separated finite numbers, with the message
            "{flag} must be a finite {size}-vector ({unit}): {size} comma-separated finite
            numbers, got {text!r}" (the text cut to `MAX_SHOWN` characters).
        ValueError: `size` is not a positive integer (a mistake of the caller's code).
    """
    _check_size(size)
    if isinstance(text, str):
        try:
            values = [float(part) for part in text.split(",")]
            return finite_vector(flag, values, ValueError, size=size, unit=unit)
        except ValueError:
            pass
    numbers = "comma-separated finite numbers"
    raise error(_message(flag, size, unit, numbers, shown(text, MAX_SHOWN)))
