"""Validation of joint position commands for one controlboard part, and its counters.

The same rules hold for `command:i` messages and the `positionMove` RPC (`check_command` lists
them); before them, the part's gate (`gate`) refuses a command from a client that does not hold
the part's running lease (`not_owner`) and drops one over the part's rate limit
(`rate_limited`); both are counted here with the others (`PartCounters`).

Pure: no Zenoh, no MuJoCo. Units: radians.
"""

from __future__ import annotations

import math
import threading
from collections import Counter
from dataclasses import dataclass
from typing import Any

import numpy as np

from archery.protocol.errors import BadRequest
from archery.protocol.text import shown

__all__ = ["REJECTION_REASONS", "CommandRejected", "PartCounters", "PartLimits", "check_command"]

REJECTION_REASONS = (
    "wrong_part",
    "wrong_length",
    "unknown_joint",
    "duplicate_joint",
    "bad_value",
    "out_of_range",
    "not_owner",
    "rate_limited",
    "busy",
)


class CommandRejected(BadRequest):
    """A joint command that breaks a rule; `reason` is one of `REJECTION_REASONS`."""

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason


@dataclass(frozen=True)
class PartLimits:
    """A part's joint names (YARP order) and software limits (rad), with the clamp tolerance.

    Attributes:
        part: the controlboard part, e.g. "left_arm".
        names: joint names in YARP order.
        lower, upper: software limits (rad), one per joint.
        tolerance: how far beyond a limit a value may be and still be clamped (rad, ≥ 0).
    """

    part: str
    names: tuple[str, ...]
    lower: tuple[float, ...]
    upper: tuple[float, ...]
    tolerance: float

    def __post_init__(self) -> None:
        n = len(self.names)
        if len(self.lower) != n or len(self.upper) != n:
            raise ValueError(
                f"{self.part}: {n} names but {len(self.lower)} lower and {len(self.upper)} "
                "upper limits"
            )
        if not (math.isfinite(self.tolerance) and self.tolerance >= 0):
            raise ValueError(f"tolerance must be a finite number >= 0 rad, got {self.tolerance!r}")


def _fmt(values: Any) -> str:
    return "[" + ", ".join(f"{v:.4g}" for v in values) + "]"


def check_command(
    limits: PartLimits,
    current: np.ndarray,
    position: Any,
    names: Any = None,
    part: str | None = None,
) -> tuple[np.ndarray, bool]:
    """Validate a command and return (the part's new targets in YARP order (rad), clamped?).

    Rules (the same for `command:i` messages and the `positionMove` RPC):

    * the command's part must be the port's part (`wrong_part`);
    * without names, one value per joint of the part, in YARP order (`wrong_length`); with
      names, each must be a joint of the part, at most once (`unknown_joint`,
      `duplicate_joint`), and the joints not named keep their current targets;
    * every value must be a finite number (`bad_value`; the codec already drops NaN on the
      wire);
    * a value beyond a software limit by more than `tolerance` rad is `out_of_range`: the whole
      command is rejected and nothing of it is applied; a value beyond a limit by at most
      `tolerance` is clamped onto the limit (the command is counted as `clamped`).

    Args:
        limits: the part's names, limits and clamp tolerance.
        current: the part's current targets (rad, YARP order): joints not named keep them.
        position: the commanded values (rad).
        names: the joints they are for (None: every joint, in YARP order).
        part: the part the command says it is for (None: not stated, e.g. an RPC on the port).

    Raises:
        CommandRejected: the command breaks a rule; the message names the bad value and what is
            valid. Nothing is applied.
    """
    where = limits.part
    if part is not None and part != where:
        raise CommandRejected(
            "wrong_part",
            f"a command for part {shown(part)} arrived on {where}'s port; send it to "
            f"the {shown(part)} port, or set part={where!r}",
        )
    if not isinstance(position, list | tuple | np.ndarray):
        raise CommandRejected(
            "wrong_length",
            f"{where} position must be a list of numbers (rad), got {shown(position)}",
        )
    values = list(position)
    if names is None:
        if len(values) != len(limits.names):
            raise CommandRejected(
                "wrong_length",
                f"{where} takes {len(limits.names)} values ({', '.join(limits.names)}), got "
                f"{len(values)}; or give names for a subset",
            )
        index = list(range(len(limits.names)))
    else:
        names = list(names)
        if len(names) != len(values):
            raise CommandRejected(
                "wrong_length", f"{where}: {len(names)} names but {len(values)} values"
            )
        lookup = {name: i for i, name in enumerate(limits.names)}
        unknown = [n for n in names if n not in lookup]
        if unknown:
            raise CommandRejected(
                "unknown_joint",
                f"{where} has no joint {shown(unknown[0])}; its joints: {', '.join(limits.names)}",
            )
        repeated = sorted(n for n, times in Counter(names).items() if times > 1)  # O(n)
        if repeated:
            raise CommandRejected(
                "duplicate_joint", f"{where}: joint {shown(repeated[0])} is named more than once"
            )
        index = [lookup[n] for n in names]
    odd = [v for v in values if isinstance(v, bool | np.bool_ | str | bytes)]
    if odd:  # numpy would read true as 1 rad and "0.1" as 0.1 rad
        raise CommandRejected(
            "bad_value",
            f"{where} position must be numbers (rad), not {shown(odd[0])}: got {shown(values)}",
        )
    try:
        wanted = np.array(values, dtype=float)
    except (TypeError, ValueError):
        raise CommandRejected(
            "bad_value", f"{where} position must be numbers (rad), got {shown(values)}"
        ) from None
    if wanted.ndim != 1 or not np.all(np.isfinite(wanted)):
        raise CommandRejected(
            "bad_value", f"{where} position must be finite numbers (rad), got {shown(values)}"
        )
    lower = np.array(limits.lower)[index]
    upper = np.array(limits.upper)[index]
    beyond = (wanted < lower - limits.tolerance) | (wanted > upper + limits.tolerance)
    if beyond.any():
        i = int(np.flatnonzero(beyond)[0])
        joint = limits.names[index[i]]
        raise CommandRejected(
            "out_of_range",
            f"{where} joint {joint} = {wanted[i]:.4g} rad is outside its limits "
            f"[{lower[i]:.4g}, {upper[i]:.4g}] rad by more than the {limits.tolerance:g} rad "
            f"tolerance; limits of {where}: min {_fmt(limits.lower)}, max {_fmt(limits.upper)}",
        )
    clipped = np.clip(wanted, lower, upper)
    targets = np.array(current, dtype=float, copy=True)
    targets[index] = clipped
    return targets, bool(np.any(clipped != wanted))


class PartCounters:
    """What happened to a part's commands since the service started. Thread-safe: the gate
    counts its refusals on the thread that delivered the command, the simulation thread the
    rest.

    Attributes:
        accepted: commands applied (stream and positionMove).
        clamped: accepted commands with at least one value clamped onto a limit.
        rejected: commands refused, by reason (see `REJECTION_REASONS`).
        watchdog_trips: streams that went stale and were frozen at the measured positions.
        last_rejection: the message of the latest refusal ("" if none).
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.accepted = 0
        self.clamped = 0
        self.rejected: Counter[str] = Counter()
        self.watchdog_trips = 0
        self.last_rejection = ""

    def accept(self, clamped: bool) -> None:
        """Count an applied command (`clamped`: a value of it was clamped onto a limit)."""
        with self._lock:
            self.accepted += 1
            self.clamped += int(clamped)

    def reject(self, reason: str, message: str) -> int:
        """Count a refused command; returns how many were refused for `reason` so far."""
        with self._lock:
            self.rejected[reason] += 1
            self.last_rejection = message
            return self.rejected[reason]

    def tripped(self) -> None:
        """Count a watchdog hold."""
        with self._lock:
            self.watchdog_trips += 1

    def to_dict(self) -> dict[str, Any]:
        """Plain data for an RPC reply."""
        with self._lock:
            return {
                "accepted": self.accepted,
                "clamped": self.clamped,
                "rejected": sum(self.rejected.values()),
                "rejected_by_reason": {r: self.rejected.get(r, 0) for r in REJECTION_REASONS},
                "watchdog_trips": self.watchdog_trips,
                "last_rejection": self.last_rejection,
            }
