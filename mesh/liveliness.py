"""Liveliness as a node sees it: which services of the robot hold their tokens now, waiting
for some to appear or one to go (by events, never by sleeping).

A wait for services takes an optional `on_wait(what, limit)` (`OnWait`): called once, the
moment a wait actually begins (some service is not alive yet), with what it waits for ("the
services: robot, camera", only those missing) and its limit (s). The mesh layer never prints;
a program passes a callback that does (`apps.waits.announce`).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterable

import zenoh

from archery.mesh.tokens import TokenSet
from archery.protocol.errors import (
    RpcTimeout,
)
from archery.protocol.keys import ALIVE_EVERY_ROBOT, Keys

__all__ = ["Liveliness", "OnWait"]

#: Called once when a wait begins: (what is waited for, a noun phrase; the limit, s).
OnWait = Callable[[str, float], None]


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

    def wait_alive(
        self, services: Iterable[str], timeout: float = 30.0, on_wait: OnWait | None = None
    ) -> None:
        """Block until every named service is alive (by liveliness, never by sleeping).

        Args:
            timeout: the limit (s).
            on_wait: called once with the services not alive yet and `timeout`, when some are
                not alive at once (see the module docstring); not called when all are.

        Raises:
            RpcTimeout: some are still missing after `timeout` seconds; the message lists them.
        """
        missing = self.missing_after(services, timeout, on_wait)
        if missing:
            raise RpcTimeout(
                f"services not alive after {timeout:g} s: {', '.join(sorted(missing))} "
                f"(robot {self.keys.robot!r})"
            )

    def missing_after(
        self, services: Iterable[str], timeout: float, on_wait: OnWait | None = None
    ) -> list[str]:
        """Wait up to `timeout` s until every named service is alive; those still missing then
        (in the order given; empty: all alive). `on_wait` as `wait_alive`'s."""
        wanted = list(dict.fromkeys(services))
        deadline = time.monotonic() + timeout
        absent = wanted
        if on_wait is not None and wanted:
            # One query says at once who is alive now (a subscription's history streams in one
            # token at a time), asked before subscribing (a query just after it may miss them),
            # so that the line names only those not alive yet.
            now = self.alive(timeout=max(0.01, min(1.0, timeout)))
            absent = [name for name in wanted if name not in now]
        with TokenSet(self.session, self.keys.alive_all()) as alive:
            if on_wait is not None and absent:
                on_wait(f"the services: {', '.join(absent)}", timeout)
            left = max(0.0, deadline - time.monotonic())
            alive.wait_for(lambda seen: set(wanted) <= seen, left)
            present = alive.present()
        return [name for name in wanted if name not in present]

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
