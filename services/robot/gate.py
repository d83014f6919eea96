"""The gate in front of a part's commands: who may command it (a lease) and how often (a rate
limit).

It runs on whichever thread delivers a command (a Zenoh callback), on the raw payload before it
is decoded (`PartGate.screen`), so a refused or excess command costs a lock and a byte search
(~1 µs), never a decoding or a job: a flood cannot make the simulation loop fall behind. It is
where a command's lease is checked: what passes is not checked again. `PartGate` tells the
lease's rules. Pure: no Zenoh, no MuJoCo. Times are monotonic wall seconds.
"""

from __future__ import annotations

import logging
import math
import secrets
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import msgspec

from archery.protocol.errors import ArcheryError

__all__ = ["NOT_OWNER", "RATE_LIMITED", "Lease", "NotOwner", "PartGate", "lease_field"]

NOT_OWNER = "not_owner"
RATE_LIMITED = "rate_limited"

log = logging.getLogger("archery.robot")


class NotOwner(ArcheryError):
    """A client that does not hold a part's lease asked to move it, to renew or drop the lease,
    or to claim the part while another owner's lease runs."""

    code = NOT_OWNER


@dataclass(frozen=True)
class Lease:
    """One part's lease.

    Attributes:
        id: the random id its owner carries in its commands.
        owner: who claimed it (a service or a person).
        ttl: how long it lasts from a claim or a renewal (wall s).
        expires: when it ends unless renewed (monotonic wall s).
    """

    id: str
    owner: str
    ttl: float
    expires: float


def _new_id() -> str:
    return secrets.token_hex(8)


def lease_field(lease_id: str) -> bytes:
    """A `JointCommand`'s lease field as msgpack writes it: the key "lease", then the id."""
    return msgspec.msgpack.encode("lease") + msgspec.msgpack.encode(lease_id)


class PartGate:
    """The lease and the command budget of one part; every method may be called from any thread.

    Ownership (wall clock): `claim` gives the claimer a lease, a random id that lasts `ttl` s
    unless renewed (`renew`). While a lease runs the part obeys only commands that carry its
    id; the others are refused (`not_owner`), counted and never applied. A lease that is not
    renewed ends by itself, so a client that died frees the part. Another client's claim is
    refused while the lease runs, unless it asks for a takeover (the operator's explicit
    override); a claim by the owner that holds the part (the same name: a restarted
    controller) replaces its lease. With no lease held, a part takes commands from anyone
    (`archery write` by hand, a teleoperation client). When a lease ends, is dropped or taken
    over, the part keeps its last accepted targets: nothing moves by itself.

    Args:
        part: the controlboard part, e.g. "left_arm" (for messages).
        rate: commands admitted per wall second in the long run (0: no limit).
        burst: commands admitted at once after a pause (≥ 1).
        clock: monotonic wall seconds (tests pass their own).
        new_id: makes a lease id.
    """

    def __init__(
        self,
        part: str,
        rate: float,
        burst: int,
        clock: Callable[[], float] = time.monotonic,
        new_id: Callable[[], str] = _new_id,
    ) -> None:
        if not (math.isfinite(rate) and rate >= 0):
            raise ValueError(f"rate must be a finite number >= 0 per s, got {rate!r}")
        if burst < 1:
            raise ValueError(f"burst must be at least 1 command, got {burst!r}")
        self.part = part
        self.rate = rate
        self.burst = burst
        self._clock = clock
        self._new_id = new_id
        self._lock = threading.Lock()
        self._tokens = float(burst)
        self._refilled = clock()
        self._too_many = (
            f"{part} takes at most {rate:g} commands/s (bursts of {burst}): this one was "
            "dropped; the part keeps its last accepted targets"
        )
        # the running lease, its lease field's bytes (sought in raw payloads), the refusal message
        self._lease: Lease | None = None
        self._token = b""
        self._not_owner = ""

    # -- ownership (under the lock) ----------------------------------------------------------
    def _hold(self, lease: Lease | None) -> None:
        self._lease = lease
        if lease is None:
            self._token, self._not_owner = b"", ""
        else:
            self._token = lease_field(lease.id)
            self._not_owner = (
                f"{self.part} is held by {lease.owner!r}: only commands that carry its lease "
                "move it (claim the part with takeover to take it over)"
            )

    def _current(self, now: float) -> Lease | None:
        """The running lease; one that has run out is forgotten here."""
        lease = self._lease
        if lease is not None and now >= lease.expires:
            log.info(
                "%s: the lease of %r ended (not renewed for %g s)",
                self.part,
                lease.owner,
                lease.ttl,
            )
            self._hold(None)
            return None
        return lease

    def _held_by(self, lease: Lease, now: float) -> str:
        return (
            f"{self.part} is held by {lease.owner!r} for {max(0.0, lease.expires - now):.2f} s "
            "more unless renewed"
        )

    def _not_this(self, current: Lease | None, now: float) -> str:
        if current is None:
            return f"that lease of {self.part} has ended: nobody holds the part; claim it again"
        return f"that lease of {self.part} is not the running one: {self._held_by(current, now)}"

    # -- ownership ---------------------------------------------------------------------------
    def claim(self, owner: str, ttl: float, takeover: bool = False) -> tuple[Lease, str]:
        """Give `owner` a new lease of `ttl` wall s; (the lease, the owner whose running lease
        a takeover ended or "").

        Raises:
            NotOwner: another owner's lease runs and `takeover` is False.
        """
        now = self._clock()
        with self._lock:
            current = self._current(now)
            took_over = ""
            if current is not None and current.owner != owner:
                if not takeover:
                    raise NotOwner(
                        f"{self._held_by(current, now)}; claim with takeover to take it over"
                    )
                took_over = current.owner
            lease = Lease(self._new_id(), owner, ttl, now + ttl)
            self._hold(lease)
        if took_over:
            log.warning("%s: %r took the part over from %r", self.part, owner, took_over)
        else:
            log.info("%s: claimed by %r for %g s", self.part, owner, ttl)
        return lease, took_over

    def renew(self, lease_id: str) -> Lease:
        """Extend the running lease `lease_id` by its ttl from now.

        Raises:
            NotOwner: that lease is not the running one (it ended, was dropped or taken over).
        """
        now = self._clock()
        with self._lock:
            current = self._current(now)
            if current is None or current.id != lease_id:
                raise NotOwner(self._not_this(current, now))
            renewed = Lease(current.id, current.owner, current.ttl, now + current.ttl)
            self._hold(renewed)
        return renewed

    def drop(self, lease_id: str) -> None:
        """End the running lease `lease_id`; dropping a lease that already ended does nothing.

        Raises:
            NotOwner: another lease runs (this one was taken over).
        """
        now = self._clock()
        with self._lock:
            current = self._current(now)
            if current is None:
                return
            if current.id != lease_id:
                raise NotOwner(self._not_this(current, now))
            self._hold(None)
        log.info("%s: released by %r", self.part, current.owner)

    def holder(self) -> tuple[Lease | None, float]:
        """The running lease (None if none) and the wall s it has left."""
        now = self._clock()
        with self._lock:
            lease = self._current(now)
        return lease, (max(0.0, lease.expires - now) if lease is not None else 0.0)

    def owner_refusal(self, lease_id: str) -> str | None:
        """Why a command or move carrying `lease_id` ("" for none) may not move the part, or
        None if it may: no lease runs, or it carries the running one."""
        now = self._clock()
        with self._lock:
            current = self._current(now)
            if current is None or current.id == lease_id:
                return None
            return self._not_owner

    # -- a command -----------------------------------------------------------------------------
    def screen(self, payload: bytes) -> tuple[str, str] | None:
        """Whether a raw `command:i` payload may go on to be decoded: None if it may, else
        (reason, message), `not_owner` or `rate_limited`. Cheap: a flood goes through here.

        While a lease runs, the payload must hold the lease field with the running id (msgpack
        writes a map's key and a string's bytes as they are, so a search finds the field
        without decoding): the command's lease is checked here, exactly, and nowhere else.

        Then the rate limit (wall clock): a token bucket, `burst` commands at once, refilled at
        `rate` per second. A command over the limit is dropped (`rate_limited`, counted by the
        caller); the part keeps its last accepted targets. The owner check comes first, so
        another client's flood never uses up the owner's budget. Rate 0 switches the limit off.
        """
        now = self._clock()
        with self._lock:
            held = self._lease is not None and self._current(now) is not None
            if held and self._token not in payload:
                return NOT_OWNER, self._not_owner
            if self.rate <= 0:
                return None
            tokens = self._tokens + (now - self._refilled) * self.rate
            self._refilled = now
            if tokens < 1.0:
                self._tokens = tokens
                return RATE_LIMITED, self._too_many
            self._tokens = min(float(self.burst), tokens) - 1.0
        return None
