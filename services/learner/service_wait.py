"""How a session waits for lost services: until every one is alive again, bounded in time.

A lost service (crashed, frozen past its lease, cut off) is waited for within the same session:
before each attempt, and again after an attempt aborted `service_lost`. While it waits, the
session shows what for ("waiting for camera (lost 3.2 s ago)", logged every few seconds). The
wait is bounded: `limit` s after the loss began (the first `service_lost` abort or wait since
the last done rollout) the session fails (`SessionFailed`), resumably.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable

from archery.services.learner.errors import ServiceLost, SessionFailed
from archery.services.learner.rig_protocol import Rig

__all__ = ["WAIT_LOG_EVERY", "WAIT_SLICE", "ServiceWait"]

log = logging.getLogger("archery.learner")
WAIT_SLICE = 1.0  # s between looks at the services while waiting for them
WAIT_LOG_EVERY = 5.0  # s between the log lines of a wait


class ServiceWait:
    """The waits of one session over `rig`.

    Args:
        rig: the services.
        limit: how long a loss may last before the session fails (s).
        show: called with the services waited for while it waits, and with [] once every
            service is alive (the session's phase follows it).
        name: the session id, for the log.
    """

    def __init__(
        self, rig: Rig, limit: float, show: Callable[[list[str]], None], name: str
    ) -> None:
        self.rig = rig
        self.limit = limit
        self.show = show
        self.name = name
        self.since: float | None = None  # monotonic start of the loss being waited out (s)

    def lost(self) -> None:
        """A service was lost: the clock of the loss starts now, unless it runs already."""
        if self.since is None:
            self.since = time.monotonic()

    def recovered(self) -> None:
        """A rollout was done: the loss, if any, is over."""
        self.since = None

    def note(self, missing: list[str]) -> str:
        """What a wait is for: "waiting for camera (lost 3.2 s ago), robot"."""
        names = []
        for name in missing:
            ago = self.rig.lost_ago(name)
            names.append(name if ago is None else f"{name} (lost {ago:.1f} s ago)")
        return "waiting for " + ", ".join(names)

    def until_alive(self, stop: threading.Event) -> None:
        """Wait until every service is alive or `stop` is set, showing what for.

        Raises:
            SessionFailed: the loss has lasted `limit` s.
        """
        missing = self.rig.missing()
        if self.since is not None or missing:
            self.since = self.since or time.monotonic()
            if time.monotonic() - self.since > self.limit:
                raise SessionFailed(self._for_good(missing))
        if not missing:
            self.show([])
            return
        logged = None
        while not stop.is_set():
            self.show(missing)
            now = time.monotonic()
            if logged is None or now - logged >= WAIT_LOG_EVERY:
                log.warning("session %s: %s", self.name, self.note(missing))
                logged = now
            assert self.since is not None  # set above: services are missing
            remaining = self.since + self.limit - now
            if remaining <= 0:
                raise SessionFailed(self._for_good(missing))
            try:
                if self.rig.wait_services(min(WAIT_SLICE, remaining), stop):
                    log.info("session %s: every service is alive again", self.name)
                    break
            except ServiceLost:
                missing = self.rig.missing() or missing
        self.show([])

    def _for_good(self, missing: list[str]) -> str:
        what = ", ".join(missing) + " still not alive" if missing else "services kept failing"
        return (
            f"{what} {self.limit:g} s after a service was lost; restart them and resume the session"
        )
