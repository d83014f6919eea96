"""Supervision of `archery up`'s children: a child that exits is restarted, left down or ends
everything, as its restart policy decides (`apps.up.restart_policy.decide`).

Each decision is reported as one line ("camera was killed by signal 9; restart 1 of 5 within
60 s, in 0.5 s"). A restart waits out its back-off without blocking the others' supervision.
The router is supervised like the services and restarted on the same endpoint; the services
are not restarted for it: as Zenoh clients they reconnect by themselves and re-declare their
liveliness tokens and subscriptions. A supervised observer (the YARP bridge) whose policy gives
up is left down instead: its end is not the mesh's.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

from archery.apps.up.child import Child
from archery.apps.up.restart_policy import Decision, RestartPolicy, decide
from archery.protocol.errors import ArcheryError

__all__ = ["GiveUp", "Supervisor"]


class Launcher(Protocol):
    """What supervision needs of `apps.up.launcher.Launcher`: its children by name, each one's
    restart policy, and a way to start one again."""

    children: dict[str, Child]

    def policy(self, name: str) -> RestartPolicy:
        """The restart policy of the child `name`."""
        ...

    def restart(self, name: str) -> None:
        """Start the child `name` again."""
        ...


@dataclass(frozen=True)
class GiveUp:
    """Supervision ended: `child` exited and its policy says stop everything (`decision`)."""

    child: Child
    decision: Decision

    def line(self) -> str:
        """One line: which child, how it ended (its exit status) and why supervision ends."""
        return f"{self.child.name} {self.decision.reason}"


@dataclass
class Supervisor:
    """Watches a Launcher's children and applies their restart policies.

    Args:
        launcher: the children and how to restart them.
        report: called with one line per decision (restart, left down, a failed restart).
        clock: a monotonic clock (s).
    """

    launcher: Launcher
    report: Callable[[str], None] = print
    clock: Callable[[], float] = time.monotonic
    restarts: dict[str, list[float]] = field(default_factory=dict)
    pending: dict[str, float] = field(default_factory=dict)
    left: dict[str, str] = field(default_factory=dict)

    def step(self) -> GiveUp | None:
        """Decide about the children that exited and run the restarts that are due."""
        now = self.clock()
        for name, child in list(self.launcher.children.items()):
            status = child.returncode
            if status is None or name in self.pending or name in self.left:
                continue
            times = self.restarts.setdefault(name, [])
            decision = decide(self.launcher.policy(name), status, now - child.started, now, times)
            if decision.action == "give_up" and name in getattr(self.launcher, "observers", {}):
                # an observer's end is not the mesh's: it stays down, the rest runs on
                decision = Decision("leave", 0.0, f"{decision.reason}; left down, the mesh runs on")
            if decision.action == "give_up":
                return GiveUp(child, decision)
            self.report(f"{name} {decision.reason}")
            if decision.action == "leave":
                self.left[name] = decision.reason
            else:
                times.append(now)
                self.pending[name] = now + decision.delay
        for name, due in sorted(self.pending.items(), key=lambda item: item[1]):
            if due > self.clock():
                continue
            del self.pending[name]
            try:
                self.launcher.restart(name)
            except (ArcheryError, OSError) as exc:  # it counts as a failed run: decided next step
                self.report(f"{name}: restart failed: {exc}")
        return None

    def run(self, stop: threading.Event, poll: float = 0.1) -> GiveUp | None:
        """Supervise until `stop` is set (None) or a policy gives up (why)."""
        while not stop.is_set():
            outcome = self.step()
            if outcome is not None:
                return outcome
            stop.wait(poll)
        return None

    def restart_count(self) -> int:
        """Restarts so far, all children together."""
        return sum(len(t) for t in self.restarts.values())
