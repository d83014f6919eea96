"""Logging of every process: ours and Zenoh's, on stderr only, with one `--log-level` flag.

Stdout carries data (the JSON lines of `learn`, `read`, `rpc`...), so every log line, Python's
and Zenoh's, goes to stderr, without ANSI colour codes unless stderr is a terminal. The level is
a `RUST_LOG`-style spec (`configure` says how it is read, and how Zenoh's logger is kept off
stdout).
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
from typing import Any

import zenoh

from archery.protocol.errors import ConfigError
from archery.protocol.text import cut

__all__ = ["DEFAULT_SPEC", "LEVELS", "add_log_args", "configure", "parse_spec"]

LEVELS = {
    "trace": 5,
    "debug": logging.DEBUG,
    "info": logging.INFO,
    "warn": logging.WARNING,
    "error": logging.ERROR,
    "off": logging.CRITICAL + 10,
}
DEFAULT_SPEC = "info"
_ZENOH_DEFAULT = "error"
_stdout_moved = False
_zenoh_configured = False


def _level(word: str, spec: str) -> str:
    level = word.strip().lower()
    if level == "warning":
        level = "warn"
    if level not in LEVELS:
        raise ConfigError(
            f"--log-level {spec!r}: {word!r} is not a level; levels: {', '.join(LEVELS)}"
        )
    return level


def parse_spec(spec: str) -> tuple[str, dict[str, str]]:
    """The default level and the per-target levels of a `RUST_LOG`-style spec.

    Raises:
        ConfigError: an unknown level or an empty target, naming the spec.
    """
    default = DEFAULT_SPEC
    targets: dict[str, str] = {}
    for item in spec.split(","):
        if not item.strip():
            continue
        if "=" in item:
            target, word = item.split("=", 1)
            if not target.strip():
                raise ConfigError(f"--log-level {spec!r}: {item!r} names no target")
            targets[target.strip()] = _level(word, spec)
        else:
            default = _level(item, spec)
    return default, targets


def _zenoh_spec(default: str, targets: dict[str, str]) -> str:
    """The Zenoh (tracing) filter for a parsed spec."""
    zenoh_targets = {t: lvl for t, lvl in targets.items() if t.startswith("zenoh")}
    base = default if default in ("trace", "debug", "off") else _ZENOH_DEFAULT
    if "zenoh" in zenoh_targets:
        base = zenoh_targets.pop("zenoh")
    return ",".join([base, *(f"{t}={lvl}" for t, lvl in zenoh_targets.items())])


def _move_stdout_to_stderr() -> None:
    """Point descriptor 1 at stderr; `sys.stdout` keeps writing to the original stdout."""
    global _stdout_moved
    if _stdout_moved:
        return
    sys.stdout.flush()
    data = os.dup(1)
    os.dup2(2, 1)
    sys.stdout = os.fdopen(data, "w", buffering=1, encoding="utf-8", errors="replace")
    _stdout_moved = True


FOREIGN_LINE_LIMIT = 1000  # characters of a log line another library writes


class _ForeignOnOneLine(logging.Filter):
    """Other libraries' records (the Foxglove SDK's, whose errors quote what a client sent) on
    one line, cut short, through the project's quoting (`protocol.text.cut`): a newline in a
    received value cannot forge a log line. The project's own loggers quote what they received
    with `shown` already."""

    def filter(self, record: logging.LogRecord) -> bool:
        if not record.name.startswith("archery"):
            record.msg = cut(record.getMessage(), FOREIGN_LINE_LIMIT)
            record.args = None
        return True


class _StderrHandler(logging.StreamHandler):  # type: ignore[type-arg]  # generic in typeshed only
    """Writes to whatever `sys.stderr` is when a record is emitted (not the stream of the moment
    logging was configured, which may since have been closed or replaced)."""

    def __init__(self) -> None:
        super().__init__(sys.stderr)

    @property  # read-only here: always the current sys.stderr
    def stream(self) -> Any:
        return sys.stderr

    @stream.setter
    def stream(self, value: Any) -> None:
        pass


def configure(spec: str = DEFAULT_SPEC) -> None:
    """Set up this process's logging from a `--log-level` spec.

    The spec is a default level, then `TARGET=LEVEL` items separated by commas, e.g. `info`,
    `debug`, `info,zenoh=debug`, `warn,archery.robot=debug`. The default level is that of our
    loggers (`archery.*`); other Python libraries log their warnings and errors only, unless a
    target names them (`info,OpenGL=debug`). Targets starting with `zenoh` set the level of
    Zenoh's own (Rust) logs; any other target is a Python logger name. Zenoh logs at `error`
    unless the spec names it or its default is `debug`, `trace` or `off`. A `RUST_LOG`
    variable in the environment, when set, still wins for Zenoh's logs, as Zenoh documents.
    Zenoh's logger can be set up once per process: the first `configure` decides.

    Zenoh's logger writes to the process's file descriptor 1. To keep it off stdout, the first
    call of `configure` in a process that sets Zenoh's logger up moves descriptor 1 to stderr
    and gives Python's `sys.stdout` a descriptor of its own on the original stdout: `print`
    still writes data there.

    Raises:
        ConfigError: the spec is malformed.
    """
    default, targets = parse_spec(spec)
    handler = _StderrHandler()
    handler.addFilter(_ForeignOnOneLine())
    handler.setFormatter(logging.Formatter("%(asctime)s %(name)s %(levelname)s: %(message)s"))
    logging.basicConfig(level=max(LEVELS[default], LEVELS["warn"]), handlers=[handler], force=True)
    logging.getLogger("archery").setLevel(LEVELS[default])
    for target, level in targets.items():
        if not target.startswith("zenoh"):
            logging.getLogger(target).setLevel(LEVELS[level])
    global _zenoh_configured
    zenoh_spec = _zenoh_spec(default, targets)
    if _zenoh_configured or (zenoh_spec.split(",")[0] == "off" and "RUST_LOG" not in os.environ):
        return
    try:
        if sys.stdout.fileno() != 1:
            return  # stdout is not this process's descriptor 1 (captured): leave it alone
    except (AttributeError, ValueError, OSError):
        return
    if not sys.stderr.isatty():
        os.environ.setdefault("NO_COLOR", "1")
    _move_stdout_to_stderr()
    zenoh.init_log_from_env_or(zenoh_spec)
    _zenoh_configured = True


def add_log_args(parser: argparse.ArgumentParser) -> None:
    """Add `--log-level SPEC`."""
    parser.add_argument(
        "--log-level",
        default=DEFAULT_SPEC,
        metavar="SPEC",
        help="log verbosity, RUST_LOG-style: LEVEL[,TARGET=LEVEL...] with levels "
        f"{', '.join(LEVELS)}; e.g. debug or info,zenoh=debug (default {DEFAULT_SPEC}; "
        "logs go to stderr)",
    )
