"""`report.png` of a session: readable at 60 rollouts, aborted attempts and resumes marked."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from protocol.journal_records import (
    AbortedRecord,
    DoneRecord,
    HeaderRecord,
    ProposedRecord,
    ResumedRecord,
)
from services.learner.algorithms.registry import make_learner
from services.learner.journal import Journal, JournalState, read_records
from services.learner.report import Interruptions, interruptions, write_report

THETA = [0.17, 0.0, -0.02]  # m


def _journal(
    directory: Path, rollouts: int, aborts: dict[int, list[str]], resumes: tuple[int, ...]
) -> Path:
    """A session of `rollouts` done rollouts; `aborts[p]` are the codes of the attempts aborted
    after done rollout p, `resumes` the done-rollout counts at which it was resumed."""
    learner = make_learner("power", np.array(THETA), rng=np.random.default_rng(3))
    header = HeaderRecord(
        session="s1",
        algorithm="power",
        seed=3,
        rollouts=rollouts,
        options=learner.options(),
        config={"hit_radius_m": 0.05},
        learner_state=learner.state_dict(),
    )
    rng = np.random.default_rng(0)
    index = 0
    with Journal.create(directory, header) as journal:
        for k in range(1, rollouts + 1):
            if k - 1 in resumes:
                journal.append(ResumedRecord(after=index))
            for code in aborts.get(k - 1, []):
                index += 1
                journal.append(ProposedRecord(index=index, theta=THETA))
                journal.append(
                    AbortedRecord(
                        index=index, theta=THETA, code=code, cause=code, retry_theta=THETA
                    )
                )
            index += 1
            journal.append(ProposedRecord(index=index, theta=THETA))
            r = rng.normal(0.0, 0.3 * np.exp(-k / 25) + 0.03, 2)
            distance = float(np.linalg.norm(r))
            journal.append(
                DoneRecord(
                    index=index,
                    rollout=k,
                    theta=THETA,
                    r_m=r.tolist(),
                    distance_m=distance,
                    hit=distance < 0.05,
                    truth_r_m=(r + 0.003).tolist(),
                    truth_distance_m=float(np.linalg.norm(r + 0.003)),
                    learner_state=learner.state_dict(),
                )
            )
    return directory / "journal.jsonl"


def _state(path: Path) -> JournalState:
    return JournalState.from_records(read_records(path)[0])


def test_aborts_and_resumes_are_placed_between_the_rollouts_they_fell_between(
    tmp_path: Path,
) -> None:
    aborts = {0: ["no_arrow"], 20: ["service_lost", "service_lost"], 41: ["no_arrow"]}
    path = _journal(tmp_path / "s1", 60, aborts, resumes=(20, 45))
    marks = interruptions(_state(path))
    assert marks == Interruptions(
        aborted=((0, "no_arrow"), (20, "service_lost"), (20, "service_lost"), (41, "no_arrow")),
        resumed=(20, 45),
    )


def test_a_session_without_interruptions_has_none(tmp_path: Path) -> None:
    marks = interruptions(_state(_journal(tmp_path / "s1", 5, {}, ())))
    assert marks == Interruptions(aborted=(), resumed=())


def test_the_report_of_a_60_rollout_session_with_aborts_and_resumes_is_written(
    tmp_path: Path,
) -> None:
    path = _journal(tmp_path / "s1", 60, {3: ["no_arrow"], 30: ["rig_error"]}, resumes=(30,))
    report = write_report(path)
    assert report == tmp_path / "s1" / "report.png"
    assert report.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and report.stat().st_size > 50_000
