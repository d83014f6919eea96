"""The steps of one attempt, without a runner: the θ to run, each way a shot ends, and the
records built from it (a fake rig, a journal state in memory: no threads, no journal file)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from msgspec import UNSET

from archery.protocol.journal_records import DoneRecord, HeaderRecord, ProposedRecord
from archery.services.learner.abort_policy import NO_ARROW, SERVICE_LOST
from archery.services.learner.algorithms.base import Learner
from archery.services.learner.algorithms.registry import make_learner
from archery.services.learner.config import SessionConfig
from archery.services.learner.errors import RigError
from archery.services.learner.journal import JournalState
from archery.services.learner.rig_protocol import Measurement, PostureResult, Shot
from archery.services.learner.rollout_step import (
    Failed,
    Measured,
    aborted_record,
    done_record,
    next_attempt,
    shoot,
)
from tests.test_learner_service_session import AIM, BOX, FakeRig

CONFIG = SessionConfig(seed=1)
THETA = [0.17, 0.006, -0.026]  # m


def _setup() -> tuple[Learner, JournalState]:
    learner = make_learner(
        "archer", np.array(CONFIG.theta0), rng=np.random.default_rng(1), bounds=BOX
    )
    header = HeaderRecord(
        session="s",
        algorithm="archer",
        seed=1,
        rollouts=3,
        options=learner.options(),
        config={},
        learner_state=learner.state_dict(),
    )
    return learner, JournalState.from_records([header])


def test_the_next_attempt_is_the_learners_proposal_the_retry_or_the_open_one() -> None:
    learner, state = _setup()
    first = next_attempt(learner, state)
    assert (first.index, first.rerun) == (1, False) and "ask_s" in first.timing
    state.apply(ProposedRecord(session="s", index=1, theta=first.theta.tolist()))
    again = next_attempt(learner, state)  # left open by a crash: the same θ, run again
    assert (again.index, again.rerun) == (1, True) and again.theta.tolist() == first.theta.tolist()
    state.retry_theta, state.open = THETA, None  # as an abort leaves it
    retry = next_attempt(learner, state)
    assert (retry.index, retry.rerun) == (2, False) and retry.theta.tolist() == THETA


class Rig(FakeRig):
    """A FakeRig whose calls end as each test says."""

    def __init__(self, **fail: object) -> None:
        super().__init__()
        self.fail = fail

    def move_to(self, theta: np.ndarray) -> PostureResult:
        if "posture" in self.fail:
            return PostureResult(False, "too slow", list(theta))
        return super().move_to(theta)

    def shoot(self) -> Shot:
        if "shoot" in self.fail:
            raise RigError("release: busy")
        return super().shoot()

    def measure(self, shot: Shot) -> Measurement:
        if "measure" in self.fail:
            return Measurement(str(self.fail["measure"]), None, {"reason": "dark"})
        return super().measure(shot)


@pytest.mark.parametrize(
    ("rig", "code", "cause"),
    [
        (Rig(posture=True), "not_reached", "posture not reached: too slow"),
        (Rig(shoot=True), "rpc_error", "release: busy"),
        (Rig(measure="no_target"), "no_target", "the detector says no_target dark"),
        (Rig(measure="no_arrow"), NO_ARROW, "the detector saw no arrow on the target"),
    ],
)
def test_each_way_a_shot_fails(rig: Rig, code: str, cause: str) -> None:
    failed = shoot(rig, np.array(THETA))
    assert isinstance(failed, Failed) and failed.code == code and failed.cause.startswith(cause)
    assert (failed.detection == {"reason": "dark"}) is ("measure" in rig.fail)


def test_no_shot_while_a_service_is_missing() -> None:
    rig = Rig()
    rig.gone.add("camera")
    failed = shoot(rig, np.array(THETA))
    assert isinstance(failed, Failed) and failed.code == SERVICE_LOST
    assert failed.cause == "camera: not alive before the shot; no arrow released"
    assert rig.shots == 0


def test_a_failed_attempt_becomes_an_aborted_record_with_the_policys_theta() -> None:
    learner, state = _setup()
    attempt = next_attempt(learner, state)
    failed = Failed(NO_ARROW, "no arrow", [0.3, 0.0], {"status": "no_arrow"})
    record, decision = aborted_record(learner, state, CONFIG, attempt, failed)
    assert record.index == 1 and record.code == NO_ARROW and record.theta == attempt.theta.tolist()
    assert record.retry_theta == list(decision.retry_theta) != record.theta  # backed off
    assert record.cause == "no arrow; next θ backs off halfway towards the best θ"
    assert record.truth_r_m == [0.3, 0.0] and record.detection == {"status": "no_arrow"}
    assert decision.failure is None and not decision.await_services


def test_a_measured_attempt_tells_the_learner_and_becomes_a_done_record() -> None:
    learner, state = _setup()
    attempt = next_attempt(learner, state).timed(journal_proposed_s=0.001)
    attempt = dataclasses.replace(
        attempt, theta=AIM + np.array([0.002, 0.0, 0.0])
    )  # on the target face
    measured = shoot(FakeRig(), attempt.theta)
    assert isinstance(measured, Measured)
    record = done_record(learner, state, CONFIG, attempt, measured)
    assert isinstance(record, DoneRecord) and (record.index, record.rollout) == (1, 1)
    assert record.r_m == measured.r_m and record.distance_m == pytest.approx(
        float(np.hypot(*measured.r_m))
    )
    assert record.hit is (record.distance_m < CONFIG.hit_radius)
    assert list(record.timing or {}) == [
        "ask_s",
        "journal_proposed_s",
        "posture_s",
        "release_s",
        "learner_s",
    ]
    # told, and the record holds no state of it (the session's checkpoints do)
    assert record.learner_state is UNSET and learner.n_rollouts == 1
