"""The shape every service's `main()` shares: parse flags, build a frozen config, run until a
signal, exit 0 on a clean stop and 2 with a clear message on a bad configuration."""

from __future__ import annotations

import argparse
import logging
import sys
import threading
from collections.abc import Callable
from typing import TypeVar

from archery.mesh.cliargs import ArgumentParser
from archery.mesh.netflags import NetConfig, add_network_args
from archery.mesh.signals import shutdown_on_signals
from archery.protocol.errors import ArcheryError, DuplicateService

__all__ = ["service_main"]

C = TypeVar("C")


def service_main(
    argv: list[str] | None,
    *,
    prog: str,
    description: str,
    add_arguments: Callable[[argparse.ArgumentParser], None],
    make_config: Callable[[argparse.Namespace, NetConfig], C],
    run: Callable[[C, threading.Event], None],
) -> int:
    """Run a service from the command line.

    `add_arguments` adds the service's own flags (the network flags are added here),
    `make_config` turns the parsed flags into the service's frozen config (raising
    `ArcheryError` subclasses for bad values) and `run(config, stop)` serves until `stop` is set
    by SIGINT/SIGTERM.

    Returns:
        0 after a clean stop, 2 for a bad configuration or when the service runs already
        (without --replace), 1 when the service fails.
    """
    parser = ArgumentParser(prog=f"archery {prog}", description=description)
    add_network_args(parser)
    parser.add_argument(
        "--replace",
        action="store_true",
        help="if this service runs already (same robot), ask it to stop and take its place",
    )
    add_arguments(parser)
    args = parser.parse_args(argv)
    log = logging.getLogger(f"archery.{prog}")
    try:
        config = make_config(args, NetConfig.from_args(args))
    except ArcheryError as exc:
        print(f"archery {prog}: {exc}", file=sys.stderr)
        return 2
    stop = shutdown_on_signals()
    try:
        run(config, stop)
    except ArcheryError as exc:
        print(f"archery {prog}: {exc}", file=sys.stderr)  # one line; also in a log file
        return 2 if isinstance(exc, DuplicateService) else 1
    log.info("stopped")
    return 0
