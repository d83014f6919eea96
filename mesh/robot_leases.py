"""The leases a client of the robot holds (`mesh/robot_client.py`): taken, renewed, dropped.

A lease lets one owner's commands move a part for `ttl` wall s unless renewed; meanwhile the
part obeys no other client (`services/robot/leases.py`).
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np

from archery.protocol.errors import RobotError, RobotLost, RpcError
from archery.protocol.verbs import robot as rv
from archery.protocol.verbs.base import Args, Verb

__all__ = ["Claim", "PartCall"]

#: a call of one part's verb: (part, verb, args) -> its typed reply, errors as `RobotError`
PartCall = Callable[[str, Verb[Any, Any], Args], Any]


class Claim:
    """The leases of some parts under one owner, renewed every quarter of their `ttl` while held
    (a lease that ran out is claimed again unless another client took the part: then `lost`
    says so and every move under it ends with `not_owner`); `RobotClient.claim` drops them.
    `leases` {part: id} ("" from a robot that keeps none: it takes anyone's commands)."""

    def __init__(self, call: PartCall, drops: ThreadPoolExecutor, owner: str, ttl: float) -> None:
        self.call, self.drops, self.owner, self.ttl = call, drops, owner, ttl
        self.leases: dict[str, str] = {}
        self.lost = ""  # why a part was taken over ("" while every lease holds)
        self._renew_at = time.monotonic() + ttl / 4

    def take(self, part: str, speeds: Sequence[float] | np.ndarray | float | None = None) -> str:
        """Claim `part`, setting its reference speeds (rad/s) in the same round trip when given.

        Raises:
            RobotError: kind `not_owner` ("cannot move PART: " and the robot's reason) when
                another client holds the part.
        """
        claim = rv.ClaimArgs(owner=self.owner, ttl=self.ttl)
        try:
            if speeds is None:
                reply: Any = self.call(part, rv.CLAIM, claim)
            else:
                value = speeds if isinstance(speeds, float | int) else [float(s) for s in speeds]
                args = rv.SetRefSpeedsArgs(speeds=value, claim=claim)
                reply = self.call(part, rv.SET_REF_SPEEDS, args)
        except RobotError as exc:
            if exc.kind != "not_owner":
                raise
            message = f"cannot move {part}: {exc.message}"
            raise RobotError(message, kind=exc.kind, code=exc.code) from exc
        self.leases[part] = reply.lease
        return str(reply.lease)

    def renew_due(self) -> float:
        """Renew the leases if a quarter of their ttl has passed; wall s until the next renewal.

        Raises:
            RobotError: a part was taken over (kind `not_owner`; also kept in `lost`).
        """
        now = time.monotonic()
        if now >= self._renew_at:
            self._renew_at = now + self.ttl / 4
            self.renew()
        if self.lost:
            raise RobotError(self.lost, kind="not_owner")
        return max(0.0, self._renew_at - time.monotonic())

    def renew(self) -> None:
        """Renew every lease (one the robot does not answer in time is tried at the next)."""
        for part, lease in list(self.leases.items()):
            if not lease:
                continue
            try:
                self.call(part, rv.RENEW_CLAIM, rv.LeaseArgs(lease=lease))
            except RobotLost:
                continue
            except RobotError as exc:
                if exc.kind != "not_owner":
                    raise
                try:
                    claim = rv.ClaimArgs(owner=self.owner, ttl=self.ttl)
                    self.leases[part] = self.call(part, rv.CLAIM, claim).lease
                except RobotError as again:
                    if again.kind != "not_owner":
                        raise
                    self.lost = f"{part} was taken over during the move: {again.message}"

    def drop(self, *, wait: bool = True) -> None:
        """Drop the leases (best effort: one the robot no longer knows runs out by itself);
        `wait=False` drops them on the client's dropping thread."""
        held = {p: lease for p, lease in self.leases.items() if lease}
        self.leases = {}
        if held:
            if wait:
                self._drop_now(held)
            else:
                self.drops.submit(self._drop_now, held)

    def _drop_now(self, leases: Mapping[str, str]) -> None:
        for part, lease in leases.items():
            with contextlib.suppress(RpcError):  # taken over, or the robot is gone
                self.call(part, rv.DROP_CLAIM, rv.LeaseArgs(lease=lease))
