"""The restart policy of `archery up`, table-driven."""

from __future__ import annotations

import pytest

from archery.apps.up.restart_policy import RestartPolicy, decide
from archery.protocol.errors import ConfigError

ON_FAILURE = RestartPolicy()
ALWAYS = RestartPolicy(mode="always")
NEVER = RestartPolicy(mode="never")


@pytest.mark.parametrize(
    ("policy", "status", "ran_for", "restarts", "action", "delay", "reason"),
    [
        (ON_FAILURE, 1, 1.0, [], "restart", 0.5, "exited with status 1; restart 1 of 5"),
        (ON_FAILURE, -9, 1.0, [], "restart", 0.5, "was killed by signal 9"),
        (ON_FAILURE, 0, 1.0, [], "leave", 0.0, "policy 'on-failure' keeps it down"),
        (ALWAYS, 0, 1.0, [], "restart", 0.5, "exited with status 0; restart 1"),
        (NEVER, -9, 1.0, [], "leave", 0.0, "policy 'never' keeps it down"),
        (ALWAYS, 2, 1.0, [], "give_up", 0.0, "a bad configuration"),
        # back-off doubles with each restart in the window...
        (ON_FAILURE, 1, 1.0, [95.0], "restart", 1.0, "restart 2 of 5"),
        (ON_FAILURE, 1, 1.0, [90.0, 95.0, 99.0], "restart", 4.0, "restart 4 of 5"),
        # ...is capped...
        (RestartPolicy(budget=20), 1, 1.0, [99.0] * 10, "restart", 8.0, "restart 11 of 20"),
        # ...and starts afresh after a healthy run
        (ON_FAILURE, 1, 30.0, [90.0, 95.0], "restart", 0.5, "restart 3 of 5"),
        # the budget counts restarts in the window only
        (ON_FAILURE, 1, 1.0, [10.0, 20.0, 30.0, 35.0, 39.0], "restart", 0.5, "restart 1 of 5"),
        (ON_FAILURE, 1, 1.0, [50.0, 60.0, 70.0, 80.0, 90.0], "give_up", 0.0, "spent the budget"),
        (RestartPolicy(budget=0), -15, 1.0, [], "give_up", 0.0, "0 restarts within 60 s"),
    ],
)
def test_decisions(
    policy: RestartPolicy,
    status: int,
    ran_for: float,
    restarts: list[float],
    action: str,
    delay: float,
    reason: str,
) -> None:
    decision = decide(policy, status, ran_for, now=100.0, restarts=restarts)
    assert (decision.action, decision.delay) == (action, delay)
    assert reason in decision.reason


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"mode": "sometimes"}, "not one of always, on-failure, never"),
        ({"budget": -1}, "budget must be an integer"),
        ({"budget": True}, "budget must be an integer"),
        ({"window": float("nan")}, "window must be a number"),
        ({"backoff": float("inf")}, "backoff must be finite"),
        ({"backoff_max": -1.0}, "backoff_max must be a number"),
    ],
)
def test_bad_policies_are_refused(kwargs: dict, match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        RestartPolicy(**kwargs)
