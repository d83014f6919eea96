"""Liveliness as a node sees it: which services of the robot hold their tokens now, waiting
for some to appear or one to go (by events, never by sleeping).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterable

import zenoh

from mesh.tokens import TokenSet
from protocol.errors import (
    RpcTimeout,
)
from protocol.keys import ALIVE_EVERY_ROBOT, Keys

__all__ = ["Liveliness"]


class Liveliness:
    """The liveliness half of a `Node`: what it needs is the node's session and keys."""

    session: zenoh.Session
    keys: Keys

    def alive(self, timeout: float = 1.0) -> set[str]:
        """Names of the services of this robot whose liveliness token is up now."""
        names = set()
        for reply in self.session.liveliness().get(self.keys.alive_all(), timeout=timeout):
            if reply.ok is not None:
                names.add(str(reply.ok.key_expr).rsplit("/", 1)[-1])
        return names

    def alive_robots(self, timeout: float = 1.0) -> dict[str, set[str]]:
        """Every robot prefix with a service alive on this router: {prefix: service names}."""
        robots: dict[str, set[str]] = {}
        for reply in self.session.liveliness().get(ALIVE_EVERY_ROBOT, timeout=timeout):
            if reply.ok is not None:
                robot, _, name = str(reply.ok.key_expr).split("/", 2)
                robots.setdefault(robot, set()).add(name)
        return robots

    def wait_alive(self, services: Iterable[str], timeout: float = 30.0) -> None:
        """Block until every named service is alive (by liveliness, never by sleeping).

        Raises:
            RpcTimeout: some are still missing after `timeout` seconds; the message lists them.
        """
        wanted = set(services)
        with TokenSet(self.session, self.keys.alive_all()) as alive:
            if not alive.wait_for(lambda seen: wanted <= seen, timeout):
                missing = ", ".join(sorted(wanted - alive.present()))
                raise RpcTimeout(
                    f"services not alive after {timeout:g} s: {missing} (robot {self.keys.robot!r})"
                )

    def wait_gone(self, service: str, timeout: float = 30.0) -> None:
        """Block until the service's liveliness token disappears.

        Raises:
            RpcTimeout: still alive after `timeout` seconds.
        """
        deadline = time.monotonic() + timeout
        gone = threading.Event()

        def on_token(sample: zenoh.Sample) -> None:
            if sample.kind == zenoh.SampleKind.DELETE:
                gone.set()

        sub = self.session.liveliness().declare_subscriber(self.keys.alive(service), on_token)
        try:
            if service not in self.alive():
                return
            if not gone.wait(max(0.0, deadline - time.monotonic())):
                raise RpcTimeout(f"service {service!r} still alive after {timeout:g} s")
        finally:
            sub.undeclare()
