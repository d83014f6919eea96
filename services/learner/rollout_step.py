"""One attempt of a learning session, step by step over a `Rig`: the θ to run, the shot
(posture, release, measurement), the abort policy's decision and the journal record of the
outcome. No threads, no waiting, no journal: the runner (`services.learner.session`) journals
and publishes each record, waits for lost services and saves the frame of a hit.

An attempt ends `Measured` (tells the learner (θ, r), becomes a done record: `done_record`) or
`Failed` with an abort code (`shoot` lists them; becomes an aborted record, the learner not
told: `aborted_record`). θ, r and distances are in m, times in s.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
from msgspec import UNSET, UnsetType

from archery.protocol.journal_records import AbortedRecord, DoneRecord
from archery.services.learner.abort_policy import (
    NO_ARROW,
    NOT_REACHED,
    SERVICE_LOST,
    AbortDecision,
    after_abort,
)
from archery.services.learner.algorithms.base import Learner
from archery.services.learner.config import SessionConfig
from archery.services.learner.errors import RigError, ServiceLost
from archery.services.learner.journal import JournalState
from archery.services.learner.rig_protocol import Measurement, PostureResult, Rig, Shot

__all__ = [
    "Attempt",
    "Failed",
    "Measured",
    "aborted_record",
    "done_record",
    "next_attempt",
    "planar_distance",
    "shoot",
]


def planar_distance(r: list[float]) -> float:
    """‖r‖ (m) of an r (m) on the target plane."""
    return float(np.hypot(r[0], r[1]))


@dataclass(frozen=True)
class Attempt:
    """One attempt: its index (1-based), θ (m), whether it re-runs an attempt a crash left open
    (its proposed record is journaled already), when it started (`time.perf_counter`, s) and
    the timing of its steps so far (s)."""

    index: int
    theta: np.ndarray
    rerun: bool
    started: float
    timing: dict[str, float]

    def timed(self, **steps: float) -> Attempt:
        """This attempt with more steps timed (s)."""
        return dataclasses.replace(self, timing=self.timing | steps)


@dataclass(frozen=True)
class Measured:
    """A shot the detector measured: the controller's, robot's and detector's answers, r (m)
    and the robot's ground truth r (m, None if unknown; for the log only)."""

    posture: PostureResult
    shot: Shot
    measurement: Measurement
    r_m: list[float]
    truth_r_m: list[float] | None


@dataclass(frozen=True)
class Failed:
    """An attempt that ended without a measurement: its abort `code` and `cause`; when the
    detector refused the frame, the robot's ground truth r (m) and the detector's reply."""

    code: str
    cause: str
    truth_r_m: list[float] | UnsetType | None = UNSET
    detection: dict[str, Any] | UnsetType = UNSET


def next_attempt(learner: Learner, state: JournalState) -> Attempt:
    """The attempt after what the journal says so far: the open one again, or the next index
    with the learner's proposal (the retry θ instead, after an abort).

    An attempt (`index`, 1-based, aborted attempts included) runs θ from the learner, or the
    retry θ an abort left; an attempt a crash left open re-runs its journaled θ (the learner is
    asked anyway, so its generator is where the first run left it)."""
    start = time.perf_counter()
    proposal = learner.ask()  # asked even when its θ is not run: the generator moves on alike
    if state.open is not None:  # left open by a crash: the learner was never told
        index, theta, rerun = state.open.index, np.array(state.open.theta), True
    else:
        retry = state.retry_theta
        index, theta, rerun = (
            state.last_index + 1,
            proposal if retry is None else np.array(retry),
            False,
        )
    return Attempt(index, theta, rerun, start, {"ask_s": time.perf_counter() - start})


def shoot(rig: Rig, theta: np.ndarray) -> Measured | Failed:
    """Posture for θ (m), release and measure; a failed call, an unreached posture, a service
    missing before the release or a refused frame is `Failed`.

    The abort codes: `not_reached` (the posture was not reached in time), `service_lost` (a
    service lost during a call, or missing before the release: no arrow is released then),
    `rpc_error`, `wrong_replier` and the other service error codes, `no_target`, `no_arrow`.
    """
    try:
        posture = rig.move_to(theta)
        if not posture.reached:
            return Failed(NOT_REACHED, f"posture not reached: {posture.reason}")
        missing = rig.missing()
        if missing:  # nobody could measure (or release) the arrow: do not shoot
            cause = f"{', '.join(missing)}: not alive before the shot; no arrow released"
            return Failed(SERVICE_LOST, cause)
        shot = rig.shoot()
        measurement = rig.measure(shot)
    except ServiceLost as exc:
        return Failed(exc.code, f"{exc.service}: {exc.message}")
    except RigError as exc:
        return Failed(exc.code, exc.message)
    truth = rig.truth(shot)
    if measurement.status == NO_ARROW:
        cause = f"the detector saw no arrow on the target (robot: {shot.outcome})"
        return Failed(NO_ARROW, cause, truth, measurement.detection)
    if measurement.status != "ok" or measurement.r_m is None:
        reason = measurement.detection.get("reason", "")
        cause = f"the detector says {measurement.status} {reason}".strip()
        return Failed(measurement.status, cause, truth, measurement.detection)
    r = [float(x) for x in measurement.r_m]
    return Measured(posture, shot, measurement, r, truth)


def aborted_record(
    learner: Learner, state: JournalState, config: SessionConfig, attempt: Attempt, failed: Failed
) -> tuple[AbortedRecord, AbortDecision]:
    """The aborted record of a failed attempt, with the θ the abort policy
    (`services.learner.abort_policy`) picks for the next one, and the policy's decision (go on,
    wait for the services, or fail)."""
    best = state.best
    redraw = learner.redraw((config.seed, attempt.index)) if failed.code == NO_ARROW else None
    decision = after_abort(
        failed.code,
        attempt.theta,
        best_theta=None if best is None else best.theta,
        theta0=config.theta0,
        bounds=learner.bounds,
        redraw=redraw,
    )
    cause = failed.cause
    if failed.code == NO_ARROW:
        cause += (
            "; next θ drawn afresh"
            if redraw is not None
            else "; next θ backs off halfway towards the best θ"
        )
    record = AbortedRecord(
        index=attempt.index,
        theta=attempt.theta.tolist(),
        code=failed.code,
        cause=cause,
        retry_theta=list(decision.retry_theta),
        truth_r_m=failed.truth_r_m,
        detection=failed.detection,
    )
    return record, decision


def done_record(
    learner: Learner,
    state: JournalState,
    config: SessionConfig,
    attempt: Attempt,
    measured: Measured,
) -> DoneRecord:
    """Tell the learner (θ, r) and return the done record: the next done-rollout number, r,
    return, ‖r‖ and hit, the ground truth, the detector's reply and the timing of the steps (s)
    (the learner's state goes into the journal's checkpoints, `session`)."""
    told = time.perf_counter()
    big_return = learner.tell(attempt.theta, np.array(measured.r_m))
    timing = (
        attempt.timing
        | measured.posture.timing
        | measured.shot.timing
        | measured.measurement.timing
        | {"learner_s": time.perf_counter() - told}
    )
    distance = planar_distance(measured.r_m)
    truth = measured.truth_r_m
    return DoneRecord(
        index=attempt.index,
        rollout=state.n_done + 1,
        theta=attempt.theta.tolist(),
        theta_measured=measured.posture.theta_measured,
        theta_launched=(
            UNSET if measured.shot.theta_launched is None else measured.shot.theta_launched
        ),
        r_m=measured.r_m,
        ret=float(big_return),
        distance_m=distance,
        hit=distance < config.hit_radius,
        shot=measured.shot.shot,
        outcome=measured.shot.outcome,
        truth_r_m=truth,
        truth_distance_m=None if truth is None else planar_distance(truth),
        detection=measured.measurement.detection,
        timing=timing,
    )
