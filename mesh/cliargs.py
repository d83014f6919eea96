"""Argument checks every `archery` verb shares: seconds, counts, JSON without NaN, paths.

Each check fails with one line naming the bad value: argparse types raise
`argparse.ArgumentTypeError` (argparse prints usage and exits 2), the others `ConfigError`.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any, NoReturn

from archery.protocol.errors import ConfigError

__all__ = [
    "IMAGE_EXTENSIONS",
    "MAX_SECONDS",
    "ArgumentParser",
    "check_image_path",
    "check_new_file",
    "check_writable_dir",
    "clean_zenoh_error",
    "count",
    "int_in",
    "loads_finite",
    "nonnegative",
    "seconds",
    "seconds_or_zero",
]

# What OpenCV's imwrite writes in every build (the others depend on optional codecs).
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".ppm", ".pgm")
MAX_SECONDS = 1e7  # s: beyond it, waits overflow the clocks they are handed to
_RUST_LOCATION = re.compile(r"\s+at /\S+\.rs:\d+\.?")


def _finite(text: str, noun: str, positive: bool) -> float:
    """`text` as a finite float > 0 (`positive`) or >= 0, for argparse; `noun` names it."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a {noun}") from None
    if not math.isfinite(value) or value < 0 or (positive and value == 0):
        bound = f"positive, finite {noun}" if positive else f"finite {noun} >= 0"
        raise argparse.ArgumentTypeError(f"{text!r} is not a {bound}")
    return value


def _bounded_seconds(text: str, positive: bool) -> float:
    value = _finite(text, "number of seconds", positive=positive)
    if value > MAX_SECONDS:
        raise argparse.ArgumentTypeError(
            f"{text!r} s is beyond {MAX_SECONDS:.0f} s (116 days), the longest wait or duration"
        )
    return value


def seconds(text: str) -> float:
    """argparse type: a positive, finite number of seconds, at most `MAX_SECONDS`."""
    return _bounded_seconds(text, positive=True)


def seconds_or_zero(text: str) -> float:
    """argparse type: a finite number of seconds in [0, `MAX_SECONDS`] (0: do not wait)."""
    return _bounded_seconds(text, positive=False)


def nonnegative(text: str) -> float:
    """argparse type: a finite number >= 0."""
    return _finite(text, "number", positive=False)


def count(text: str) -> int:
    """argparse type: an integer >= 0."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"{text!r} is negative; give 0 or more")
    return value


def int_in(low: int, high: int, noun: str) -> Callable[[str], int]:
    """argparse type: an integer in low..high, called `noun` in the error."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not {noun}") from None
        if not low <= value <= high:
            raise argparse.ArgumentTypeError(f"{text!r} is not {noun} ({low}..{high})")
        return value

    return parse


def _refuse_constant(name: str) -> Any:
    raise ValueError(f"{name} is not a finite number; JSON numbers must be finite")


def loads_finite(text: str, what: str) -> Any:
    """`json.loads(text)`, refusing NaN, Infinity and -Infinity.

    Raises:
        ConfigError: not JSON, or a non-finite constant; the message names `what` and the value.
    """
    try:
        return json.loads(text, parse_constant=_refuse_constant)
    except json.JSONDecodeError as exc:
        raise ConfigError(f"{what} {text!r} is not valid JSON: {exc}") from None
    except ValueError as exc:
        raise ConfigError(f"{what} {text!r}: {exc}") from None


def check_image_path(path: str, flag: str = "--out") -> None:
    """Raise ConfigError unless `path` ends in an image extension and its folder exists."""
    suffix = Path(path).suffix.lower()
    if suffix not in IMAGE_EXTENSIONS:
        raise ConfigError(
            f"{flag} {path!r}: unknown image extension {suffix or '(none)'!r}; "
            f"use one of {', '.join(IMAGE_EXTENSIONS)}"
        )
    check_writable_dir(Path(path).parent, f"{flag} {path!r}: folder", create=False)


def check_writable_dir(path: Path, what: str, *, create: bool) -> None:
    """Raise ConfigError unless `path` is (or, with `create`, can be made) a writable folder."""
    path = Path(path) if str(path) else Path(".")
    if create:
        try:
            path.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise ConfigError(f"{what} {str(path)!r} cannot be created: {exc.strerror}") from None
    if not path.is_dir():
        raise ConfigError(f"{what} {str(path)!r} is not an existing folder")
    if not os.access(path, os.W_OK | os.X_OK):
        raise ConfigError(f"{what} {str(path)!r} is not writable")


def check_new_file(path: Path, flag: str) -> None:
    """Raise ConfigError when `path` exists but is not a folder (a folder of outputs is wanted)."""
    if path.exists() and not path.is_dir():
        raise ConfigError(f"{flag} {str(path)!r} is an existing file; give a folder")


def clean_zenoh_error(exc: BaseException | str) -> str:
    """A Zenoh error's text without the Rust source location (` at /…/x.rs:NNN.`)."""
    return _RUST_LOCATION.sub("", str(exc)).strip().rstrip(" .!")


class ArgumentParser(argparse.ArgumentParser):
    """An argparse parser whose errors are one line on stderr (exit status 2), not the usage."""

    def error(self, message: str) -> NoReturn:
        """Print `PROG: MESSAGE (PROG --help lists the options)` and exit 2."""
        self.exit(2, f"{self.prog}: {message} (`{self.prog} --help` lists the options)\n")
