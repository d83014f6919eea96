"""The abort policy, one row per abort code and situation: the θ the next attempt runs, whether
the session waits for its services, and when it fails."""

from __future__ import annotations

import numpy as np
import pytest

from archery.protocol.journal_records import AbortedRecord
from archery.protocol.robotspec import THETA0
from archery.protocol.theta import ThetaBox
from archery.services.learner.abort_policy import AbortDecision, after_abort, streak_failure

BOX = ThetaBox(low=(0.10, -0.05, -0.05), high=(0.30, 0.05, 0.05))
START = (0.17, 0.006, -0.026)  # θ0 of the session (m)
MISS = (0.21, 0.02, 0.01)  # the aborted attempt's θ (m)
BEST = (0.19, 0.0, -0.01)  # the closest rollout's θ so far (m)

# code, θ, best θ so far, expected retry θ, waits for services, fails
ROWS = [
    ("service_lost", MISS, None, MISS, True, False),
    ("service_lost", MISS, BEST, MISS, True, False),
    ("rpc_error", MISS, BEST, MISS, False, False),
    ("bad_reply", MISS, None, MISS, False, False),
    ("not_reached", MISS, BEST, MISS, False, False),
    ("no_target", MISS, BEST, MISS, False, False),
    ("bad_request", MISS, None, MISS, False, False),  # any other service error code
    # A miss backs off halfway towards the best θ so far…
    ("no_arrow", MISS, BEST, (0.20, 0.01, 0.0), False, False),
    # …or towards θ0 before any rollout…
    ("no_arrow", MISS, None, (0.19, 0.013, -0.008), False, False),
    # …and fails the session when there is nowhere to back off to.
    ("no_arrow", START, None, START, False, True),
    ("no_arrow", BEST, BEST, BEST, False, True),
    # The back-off θ is clipped into the box (the anchor lies outside it here).
    ("no_arrow", (0.30, 0.05, 0.05), (0.30, 0.09, 0.05), (0.30, 0.05, 0.05), False, True),
    ("no_arrow", (0.29, 0.05, 0.0), (0.29, 0.09, 0.0), (0.29, 0.05, 0.0), False, True),
    ("no_arrow", (0.25, 0.0, 0.0), (0.15, 0.09, 0.0), (0.20, 0.045, 0.0), False, False),
]


@pytest.mark.parametrize(("code", "theta", "best", "retry", "waits", "fails"), ROWS)
def test_after_abort(
    code: str,
    theta: tuple[float, ...],
    best: tuple[float, ...] | None,
    retry: tuple[float, ...],
    waits: bool,
    fails: bool,
) -> None:
    decision = after_abort(code, theta, best_theta=best, theta0=START, bounds=BOX)
    assert isinstance(decision, AbortDecision)
    np.testing.assert_allclose(decision.retry_theta, retry, atol=1e-12)
    assert decision.await_services is waits
    assert (decision.failure is not None) is fails
    if fails:
        assert str([float(v) for v in theta]) in decision.failure
        assert str(list(THETA0)) in decision.failure  # names a θ0 that lands


@pytest.mark.parametrize(("theta", "best"), [(MISS, BEST), (MISS, None), (START, None)])
def test_a_learner_that_redraws_runs_its_draw_after_a_miss_and_never_fails(
    theta: tuple[float, ...], best: tuple[float, ...] | None
) -> None:
    fresh = (0.25, -0.02, 0.04)
    decision = after_abort(
        "no_arrow", theta, best_theta=best, theta0=START, bounds=BOX, redraw=fresh
    )
    assert decision == AbortDecision(fresh)
    outside = after_abort(
        "no_arrow", theta, best_theta=best, theta0=START, bounds=BOX, redraw=(0.5, 0.0, 0.0)
    )
    assert outside.retry_theta == (0.30, 0.0, 0.0)  # clipped into the box


def test_every_code_the_session_raises_has_a_row() -> None:
    codes = {row[0] for row in ROWS}
    assert {"service_lost", "rpc_error", "bad_reply", "not_reached", "no_target", "no_arrow"} <= (
        codes
    )


def test_decision_is_frozen_and_plain() -> None:
    decision = after_abort("no_arrow", MISS, best_theta=BEST, theta0=START, bounds=BOX)
    assert all(type(v) is float for v in decision.retry_theta)
    with pytest.raises(AttributeError):
        decision.retry_theta = START  # type: ignore[misc]  # frozen: the test writes on purpose


@pytest.mark.parametrize(
    ("in_row", "max_aborts", "fails"),
    [
        ({}, 1, False),
        ({"no_target": 2}, 3, False),
        ({"no_target": 3}, 3, True),
        ({"no_target": 1, "service_lost": 1, "no_arrow": 1}, 3, False),
        ({"no_target": 1, "service_lost": 1, "no_arrow": 2}, 3, True),
        ({"service_lost": 50}, 3, False),
        ({"rpc_error": 9}, 8, True),
    ],
)
def test_streak_failure(in_row: dict[str, int], max_aborts: int, fails: bool) -> None:
    last = AbortedRecord(
        index=1, theta=list(MISS), code="no_target", cause="lights off", retry_theta=list(MISS)
    )
    failure = streak_failure(in_row, max_aborts, last if in_row else None)
    assert (failure is not None) is fails
    if fails:
        total = sum(n for code, n in in_row.items() if code != "service_lost")
        assert failure == (
            f"{total} attempts in a row were aborted; the last at θ {list(MISS)} m: "
            "[no_target] lights off"
        )
