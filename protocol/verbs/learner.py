"""Verbs of the learner, `ROBOT/learner/rpc:i`: start (or resume), stop, status, confirm (the
operator did what the session waits for).

Which algorithms exist, whether θ0 lies in the bounds and whether a journal can be resumed are
checked by the learner itself.
"""

from __future__ import annotations

from typing import Annotated, Any

from msgspec import UNSET, Meta, UnsetType

from archery.protocol.theta import Theta, ThetaBox
from archery.protocol.verbs.base import Args, NoArgs, Reply, Verb, VerbTable

__all__ = ["LEARNER_VERBS", "MAX_ROLLOUTS"]

MAX_ROLLOUTS = 10_000  # the budget of done rollouts a session may ask for


class Scenario(Args, frozen=True):
    theta0: Theta | UnsetType = UNSET
    bounds: ThetaBox | UnsetType | None = UNSET
    hit_radius: Annotated[float, Meta(ge=0.001, le=0.25, description="m")] | UnsetType = UNSET
    reset: bool | UnsetType = UNSET


class StartArgs(Args, frozen=True):
    algo: Annotated[str, Meta(description="archer, power, …")] | UnsetType = UNSET
    rollouts: Annotated[int, Meta(ge=1, le=MAX_ROLLOUTS)] | UnsetType = UNSET
    seed: Annotated[int, Meta(ge=0, le=2**32 - 1)] | UnsetType = UNSET
    until_hit: bool | UnsetType = UNSET
    scenario: Scenario | UnsetType = UNSET
    options: Annotated[dict[str, Any], Meta(description="learner options")] | UnsetType = UNSET
    resume: Annotated[str, Meta(min_length=1, description="journal path")] | UnsetType = UNSET
    session: str | UnsetType | None = UNSET
    from_journal: (
        Annotated[
            str,
            Meta(min_length=1, description="start from this session's learned model (id or path)"),
        ]
        | UnsetType
    ) = UNSET


class OperatorRequest(Reply, frozen=True):
    """What a session waits for the operator to do (a real robot's nock or reset by hand), until
    `confirm` tells it done."""

    request: Annotated[int, Meta(ge=1, description="its number in the learner's life")]
    verb: Annotated[str, Meta(description="the robot's verb done by hand: nock, grasp, reset")]
    message: str
    since: Annotated[float, Meta(description="wall s (epoch) it was asked")]
    limit: Annotated[float, Meta(description="s the session waits before it stops")]


class ConfirmArgs(Args, frozen=True):
    request: (
        Annotated[int, Meta(ge=1, description="the request confirmed; absent: the current")] | None
    ) = None


class LearnerStatusReply(Reply, frozen=True):
    """{"state": "idle"} before any session; else the session's counts and results."""

    state: str
    session: str | UnsetType = UNSET
    algorithm: str | UnsetType = UNSET
    seed: int | UnsetType = UNSET
    budget: int | UnsetType = UNSET
    rollouts: int | UnsetType = UNSET
    aborted: int | UnsetType = UNSET
    hit_at: int | UnsetType | None = UNSET
    final_distance_m: float | UnsetType | None = UNSET
    best_distance_m: float | UnsetType | None = UNSET
    ended: str | UnsetType | None = UNSET
    cause: str | UnsetType = UNSET
    waiting_for: list[str] | UnsetType = UNSET
    journal: str | UnsetType = UNSET
    directory: str | UnsetType = UNSET
    last_theta: Theta | UnsetType | None = UNSET
    last_r_m: list[float] | UnsetType | None = UNSET
    report: str | UnsetType | None = UNSET
    hit_frame: str | UnsetType | None = UNSET
    stopping: bool | UnsetType = UNSET
    operator: OperatorRequest | UnsetType | None = UNSET


START = Verb("start", StartArgs, LearnerStatusReply, "start a session, or resume a journal")

STOP = Verb("stop", NoArgs, LearnerStatusReply, "stop the session after its current rollout")

STATUS = Verb(
    "status",
    NoArgs,
    LearnerStatusReply,
    "the running or last session's status",
    blocking=False,
    reads=True,
)

CONFIRM = Verb(
    "confirm",
    ConfirmArgs,
    OperatorRequest,
    "the operator did what the session waits for (status: operator); its request",
    blocking=False,
)

LEARNER_VERBS = VerbTable(
    "learner",
    ("learner/rpc:i",),
    (
        START,
        STOP,
        STATUS,
        CONFIRM,
    ),
)
