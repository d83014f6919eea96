"""Argument checks every `archery` verb shares: seconds, counts, JSON without NaN, paths.

Each check fails with one line naming the bad value: argparse types raise
`argparse.ArgumentTypeError` (argparse prints usage and exits 2), the others `ConfigError`.
A path a verb writes is checked before any work (`check_output_file`, `check_new_folder`,
`check_writable_dir`): nothing is created or replaced by the check.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import stat
import tempfile
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, NoReturn

from archery.mesh.regular_file import file_kind
from archery.protocol.errors import ConfigError

__all__ = [
    "IMAGE_EXTENSIONS",
    "MAX_SECONDS",
    "ArgumentParser",
    "add_force_arg",
    "check_new_file",
    "check_new_folder",
    "check_output_file",
    "check_results_folder",
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


def _folder_refusal(folder: Path) -> str | None:
    """Why nothing can be written in `folder`, or None: it is missing, not a folder, or a
    probe file cannot be created in it (so a read-only mount or /proc refuses root too)."""
    shown = repr(str(folder))
    if not folder.exists():
        return f"no folder {shown}; create it first or give another path"
    if not folder.is_dir():
        return f"{shown} is not a folder; give a path in an existing folder"
    if not os.access(folder, os.W_OK | os.X_OK):
        return f"the folder {shown} is not writable; give a path in a writable folder"
    try:
        fd, probe = tempfile.mkstemp(prefix=".archery-probe-", dir=folder)
    except OSError as exc:
        reason = exc.strerror or str(exc)
        return f"cannot create a file in the folder {shown} ({reason}); give a writable folder"
    os.close(fd)
    os.unlink(probe)
    return None


def add_force_arg(parser: argparse.ArgumentParser, what: str = "an existing output file") -> None:
    """The `--force` flag of a verb that writes a file: without it, `check_output_file`
    refuses to replace one."""
    parser.add_argument("--force", action="store_true", help=f"replace {what}")


def check_output_file(
    path: str | os.PathLike[str], flag: str, extensions: Sequence[str], *, force: bool
) -> Path:
    """`path` as a Path, when it is a place to write a file of one of `extensions` (lower
    case, with their dot): not a folder, its extension one of them, its folder existing and
    writable, and no file there unless `force` (then a regular file that may be replaced).
    Checked before any work; nothing is created or replaced.

    Raises:
        ConfigError: one line naming `flag`, the value and what to give instead.
    """
    out = Path(path)
    named = f"{flag} {str(path)!r}"
    endings = ", ".join(extensions[:-1]) + (" or " if len(extensions) > 1 else "") + extensions[-1]
    if out.is_dir():
        example = str(out / f"NAME{extensions[0]}")
        raise ConfigError(f"{named} is a folder; give a file name, e.g. {example!r}")
    if out.suffix.lower() not in extensions:
        raise ConfigError(
            f"{named}: give a file name ending in {endings} (not {out.suffix or '(none)'!r})"
        )
    why = _folder_refusal(out.parent if str(out.parent) else Path("."))
    if why is not None:
        raise ConfigError(f"{named}: {why}")
    try:
        mode = os.stat(out).st_mode
    except FileNotFoundError:
        return out
    except OSError as exc:
        raise ConfigError(f"{named}: {exc.strerror or exc}; give another name") from None
    if not stat.S_ISREG(mode):
        raise ConfigError(f"{named} is {file_kind(mode)}; give a regular file's name")
    if not force:
        raise ConfigError(f"{named} exists; give --force to replace it, or another name")
    if not os.access(out, os.W_OK):
        raise ConfigError(f"{named} exists and is not writable; give another name")
    return out


def check_new_folder(path: str | os.PathLike[str], flag: str) -> Path:
    """`path` as a Path, when it is a folder to create: nothing there yet (a file or folder is
    refused), its parent an existing, writable folder. Nothing is created.

    Raises:
        ConfigError: one line naming `flag`, the value and what to give instead.
    """
    out = Path(path)
    named = f"{flag} {str(path)!r}"
    if out.is_dir():
        raise ConfigError(f"{named}: a folder of that name exists; give a new folder")
    if out.exists():
        raise ConfigError(f"{named} is an existing file; give a new folder")
    why = _folder_refusal(out.parent if str(out.parent) else Path("."))
    if why is not None:
        raise ConfigError(f"{named}: {why}")
    return out


def check_results_folder(out: Path, flag: str, results: Sequence[str], *, force: bool) -> None:
    """Refuse (ConfigError, one line) a folder `out` that already holds one of `results` (file
    names) unless `force`: a second run never writes over the first one's results silently."""
    held = [name for name in results if (out / name).exists()]
    if held and not force:
        raise ConfigError(
            f"{flag} {str(out)!r} holds the results of an earlier run ({', '.join(held)}); "
            "choose another folder, or give --force to replace them"
        )


def clean_zenoh_error(exc: BaseException | str) -> str:
    """A Zenoh error's text without the Rust source location (` at /…/x.rs:NNN.`)."""
    return _RUST_LOCATION.sub("", str(exc)).strip().rstrip(" .!")


class ArgumentParser(argparse.ArgumentParser):
    """An argparse parser whose errors are one line on stderr (exit status 2), not the usage."""

    def error(self, message: str) -> NoReturn:
        """Print `PROG: MESSAGE (PROG --help lists the options)` and exit 2."""
        self.exit(2, f"{self.prog}: {message} (`{self.prog} --help` lists the options)\n")
