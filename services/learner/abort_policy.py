"""What a learning session does after an aborted attempt: a pure policy, no I/O.

An attempt aborts when it ends without a measurement; the learner is not told and the attempt
is not counted as a rollout. `after_abort` picks the next attempt's θ (m) by the abort's code,
`streak_failure` fails the session after `max_aborts` aborts in a row (`service_lost` aside).
docs/learning.md tells the codes from the user's side.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from archery.protocol.journal_records import AbortedRecord
from archery.protocol.robotspec import THETA0
from archery.protocol.theta import ThetaBox

__all__ = [
    "BACK_OFF_FRACTION",
    "NOT_REACHED",
    "NO_ARROW",
    "SERVICE_LOST",
    "AbortDecision",
    "after_abort",
    "streak_failure",
]

SERVICE_LOST = "service_lost"
NO_ARROW = "no_arrow"
NOT_REACHED = "not_reached"  # a posture, or a waypoint of the whole shot, not reached in time

#: After a miss, the next θ is anchor + this × (θ − anchor): halfway back towards the anchor.
BACK_OFF_FRACTION = 0.5


@dataclass(frozen=True)
class AbortDecision:
    """What to do after one aborted attempt.

    Attributes:
        retry_theta: θ (m) the next attempt runs (journaled as the abort's `retry_theta`).
        await_services: wait until every service is alive before the next attempt.
        failure: why the session must fail now, after journaling the abort; None to go on.
    """

    retry_theta: tuple[float, ...]
    await_services: bool = False
    failure: str | None = None


def after_abort(
    code: str,
    theta: Sequence[float] | np.ndarray,
    *,
    best_theta: Sequence[float] | None,
    theta0: Sequence[float],
    bounds: ThetaBox,
    redraw: Sequence[float] | np.ndarray | None = None,
) -> AbortDecision:
    """The decision after an attempt at `theta` (m) aborted with `code`:

    * `service_lost` (a service did not answer or vanished, or a service's upstream did): wait
      until every service is alive again, then re-run the same θ. Waiting out a lost service is
      not a failure of the attempts: these aborts do not count towards `max_aborts` (the
      session bounds the wait by time instead, `service_wait`).
    * `rpc_error`, `bad_reply` or any service error code, `not_reached` (the posture was not
      reached in time), `no_target` (the detector sees no target: camera or lighting, not θ):
      re-run the same θ.
    * `no_arrow` (no arrow on the target face: θ missed it): no r is invented; the next attempt
      runs halfway from θ back towards the best θ so far (θ0 before any rollout), clipped into
      the θ box; or, for a learner whose proposals ignore the rewards (uniform random search,
      `redraw`), a θ drawn afresh. A `no_arrow` whose back-off θ is θ itself (θ is θ0, or the
      best θ, with nothing better known) fails the session at once: re-running it would miss
      again.

    Args:
        code: the abort's code.
        theta: θ of the aborted attempt (m).
        best_theta: θ of the closest rollout so far (m), None before any rollout.
        theta0: the session's starting θ (m), the back-off anchor before any rollout.
        bounds: the session's θ box; a back-off θ is clipped into it.
        redraw: after a `no_arrow`, run this θ (m, clipped into the box) instead of backing off:
            the learner's fresh draw (`Learner.redraw`), None for a back-off.
    """
    current = np.asarray(theta, dtype=float)
    if code == SERVICE_LOST:
        return AbortDecision(_tuple(current), await_services=True)
    if code != NO_ARROW:
        return AbortDecision(_tuple(current))
    if redraw is not None:
        return AbortDecision(_tuple(bounds.clip(redraw)))
    anchor = np.asarray(theta0 if best_theta is None else best_theta, dtype=float)
    retry = bounds.clip(anchor + BACK_OFF_FRACTION * (current - anchor))
    failure = None
    if np.allclose(retry, current, atol=1e-9):  # the anchor itself, with nothing better known
        failure = (
            f"θ = {current.tolist()} m puts no arrow on the target face (the detector saw "
            f"none) and no θ so far did better; start from another scenario.theta0 "
            f"(the default {list(THETA0)} m lands on the face)"
        )
    return AbortDecision(_tuple(retry), failure=failure)


def streak_failure(
    aborts_in_row: Mapping[str, int], max_aborts: int, last: AbortedRecord | None
) -> str | None:
    """Why the session fails after `aborts_in_row` (count by code since the last rollout or
    resume; `service_lost` ones are not counted) reached `max_aborts`, naming the `last` aborted
    record; None below the limit."""
    in_row = sum(n for code, n in aborts_in_row.items() if code != SERVICE_LOST)
    if in_row < max_aborts or last is None:
        return None
    return f"{in_row} attempts in a row were aborted; the last at θ {last.theta} m: {last.note()}"


def _tuple(theta: np.ndarray) -> tuple[float, ...]:
    return tuple(float(v) for v in theta)
