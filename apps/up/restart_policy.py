"""When `archery up` restarts a child that exited: the restart policy as a pure function.

Like Docker Compose's `restart:` and systemd's `Restart=` with `StartLimitBurst`: a policy
(`always`, `on-failure`, `never`), a budget of restarts within a sliding window, and an
exponential back-off between restarts that starts afresh once a child has run long enough to
count as healthy. Exit status 2 is this project's "bad configuration": restarting cannot help,
so it ends supervision at once whatever the policy.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

from archery.protocol.errors import ConfigError

__all__ = ["POLICIES", "Decision", "RestartPolicy", "decide", "describe_status"]

POLICIES = ("always", "on-failure", "never")
BAD_CONFIG = 2


@dataclass(frozen=True)
class RestartPolicy:
    """How a child is restarted.

    Attributes:
        mode: "always" (any exit), "on-failure" (a non-zero status or a signal), "never".
        budget: restarts allowed within `window` s; one more ends supervision.
        window: the sliding window of the budget (s).
        backoff: delay before the first restart (s); doubles with each restart in the window.
        backoff_max: the longest delay (s).
        healthy_after: a child that ran this long (s) restarts after `backoff` again.
    """

    mode: Literal["always", "on-failure", "never"] = "on-failure"
    budget: int = 5
    window: float = 60.0
    backoff: float = 0.5
    backoff_max: float = 8.0
    healthy_after: float = 10.0

    def __post_init__(self) -> None:
        if self.mode not in POLICIES:
            raise ConfigError(f"restart policy {self.mode!r} is not one of {', '.join(POLICIES)}")
        if isinstance(self.budget, bool) or not isinstance(self.budget, int) or self.budget < 0:
            raise ConfigError(f"restart budget must be an integer ≥ 0, got {self.budget!r}")
        for name in ("window", "backoff", "backoff_max", "healthy_after"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int | float) or not value >= 0:
                raise ConfigError(f"restart {name} must be a number ≥ 0 s, got {value!r}")
            if value == float("inf"):
                raise ConfigError(f"restart {name} must be finite, got {value!r}")


@dataclass(frozen=True)
class Decision:
    """What to do about a child that exited.

    Attributes:
        action: "restart" (after `delay` s), "leave" (the policy keeps it down; the rest
            runs on), or "give_up" (stop everything: the budget is spent or it cannot work).
        delay: seconds to wait before the restart.
        reason: one line saying why, with the exit status.
    """

    action: Literal["restart", "leave", "give_up"]
    delay: float
    reason: str


def describe_status(status: int) -> str:
    """`exited with status N` or `was killed by signal N` (a negative Popen return code)."""
    return f"was killed by signal {-status}" if status < 0 else f"exited with status {status}"


def decide(
    policy: RestartPolicy,
    status: int,
    ran_for: float,
    now: float,
    restarts: Sequence[float],
) -> Decision:
    """Decide about a child that ended with `status` after running `ran_for` s.

    Args:
        policy: the child's restart policy.
        status: its exit status (negative: killed by that signal, as `Popen.returncode`).
        ran_for: how long it ran before it ended (s).
        now: the current time (s, monotonic clock).
        restarts: the times (same clock) of its earlier restarts.
    """
    how = describe_status(status)
    if status == BAD_CONFIG:
        return Decision("give_up", 0.0, f"{how} (a bad configuration: a restart cannot help)")
    if policy.mode == "never" or (policy.mode == "on-failure" and status == 0):
        return Decision("leave", 0.0, f"{how}; restart policy {policy.mode!r} keeps it down")
    recent = [t for t in restarts if now - t < policy.window]
    if len(recent) >= policy.budget:
        return Decision(
            "give_up",
            0.0,
            f"{how}; {len(recent)} restarts within {policy.window:g} s spent the budget "
            f"of {policy.budget}",
        )
    steps = 0 if ran_for >= policy.healthy_after else len(recent)
    delay = min(policy.backoff * 2**steps, policy.backoff_max)
    return Decision(
        "restart",
        delay,
        f"{how}; restart {len(recent) + 1} of {policy.budget} within {policy.window:g} s, "
        f"in {delay:g} s",
    )
