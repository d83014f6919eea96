"""The lease gate of every part: a command's lease checked at the edge where the
command arrives, and the lease verbs' replies.

A `command:i` payload is checked once, raw, on the thread that received it (`screen`: the
running lease, then the rate limit; see `gate`); what passes is decoded and applied without
being checked again. A positionMove or setRefSpeeds is checked once, by its handler (`check`),
before its job is queued. A command is accepted or refused there: a lease claimed while its job
waits in the queue (a few ms at most) does not undo it. Refusals are counted with the part's
command counters (`not_owner`, `rate_limited`), a refused setRefSpeeds aside (it is no
command). Every method may be called from any thread.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Mapping

from archery.protocol.verbs import robot as rv
from archery.services.robot.commands import PartCounters
from archery.services.robot.gate import NOT_OWNER, NotOwner, PartGate

__all__ = ["Leases"]

log = logging.getLogger("archery.robot")


class Leases:
    """Every part's gate (`gate.PartGate`: its lease and its command budget).

    Args:
        parts: the controlboard parts.
        rate: commands admitted per part and wall second in the long run (0: no limit).
        burst: commands admitted at once after a pause (≥ 1).
        counters: each part's command counters, where the refusals are counted.
    """

    def __init__(
        self,
        parts: Iterable[str],
        rate: float,
        burst: int,
        counters: Mapping[str, PartCounters],
    ) -> None:
        self._gates = {part: PartGate(part, rate, burst) for part in parts}
        self._counters = counters

    # -- the checks ----------------------------------------------------------------------------
    def screen(self, part: str, payload: bytes) -> bool:
        """Whether a raw `command:i` payload for `part` may go on to be decoded and applied:
        the part's gate refuses one without the running lease and drops one over the rate
        limit, both counted, before any decoding or job."""
        refused = self._gates[part].screen(payload)
        if refused is None:
            return True
        self.refuse(part, *refused)
        return False

    def check(self, part: str, lease: str, counted: bool = True) -> None:
        """A positionMove (`counted`) or setRefSpeeds carrying `lease` ("" for none) may move
        `part`: no lease runs, or it carries the running one.

        Raises:
            NotOwner: another client holds the part's lease.
        """
        refusal = self._gates[part].owner_refusal(lease)
        if refusal is None:
            return
        if counted:
            self.refuse(part, NOT_OWNER, refusal)
        raise NotOwner(refusal)

    def refuse(self, part: str, reason: str, message: str) -> None:
        """Count a refused command; logged sparingly (a flood is many)."""
        n = self._counters[part].reject(reason, message)
        if n <= 10 or n % 1000 == 0:
            log.warning("refused command #%d on %s (%s): %s", n, part, reason, message)

    # -- the lease verbs -----------------------------------------------------------------------
    def claim(self, part: str, owner: str, ttl: float, takeover: bool = False) -> rv.LeaseReply:
        """Give `owner` the lease of `part` for `ttl` wall s.

        Raises:
            NotOwner: another owner's lease runs and `takeover` is False."""
        lease, took_over = self._gates[part].claim(owner, ttl, takeover)
        return rv.LeaseReply(
            lease=lease.id,
            owner=lease.owner,
            ttl=lease.ttl,
            expires_in=lease.ttl,
            took_over=took_over,
        )

    def renew(self, part: str, lease_id: str) -> rv.LeaseReply:
        """Extend `part`'s running lease `lease_id` by its ttl (wall s) from now.

        Raises:
            NotOwner: that lease ended, was dropped or was taken over."""
        lease = self._gates[part].renew(lease_id)
        return rv.LeaseReply(lease=lease.id, owner=lease.owner, ttl=lease.ttl, expires_in=lease.ttl)

    def drop(self, part: str, lease_id: str) -> rv.ClaimReply:
        """End `part`'s lease `lease_id` (nothing if it had ended); who holds the part now.

        Raises:
            NotOwner: another client's lease runs."""
        self._gates[part].drop(lease_id)
        return self.holder(part)

    def holder(self, part: str) -> rv.ClaimReply:
        """Who holds `part` and for how long (wall s); never the lease id."""
        lease, left = self._gates[part].holder()
        if lease is None:
            return rv.ClaimReply(held=False, owner="", ttl=0.0, expires_in=0.0)
        return rv.ClaimReply(held=True, owner=lease.owner, ttl=lease.ttl, expires_in=left)

    def owner(self, part: str) -> str:
        """Who holds `part` ("" if nobody)."""
        lease, _ = self._gates[part].holder()
        return lease.owner if lease is not None else ""
