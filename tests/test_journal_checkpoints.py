"""Long sessions: a journal whose records do not grow with the session (the learner's state in
checkpoints, without its history), and a resume that rebuilds the learner from the latest
checkpoint and the rollouts after it, shooting exactly the θ an uninterrupted session shoots,
wherever the learner was killed. A corrupt checkpoint is skipped for the one before it, named;
a journal edited by hand after its checkpoint is refused at the first rollout that differs."""

from __future__ import annotations

import json
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from msgspec import UnsetType

from archery.protocol.journal_records import (
    CHECKPOINT_EVERY,
    AbortedRecord,
    CheckpointRecord,
    DoneRecord,
    ResumedRecord,
)
from archery.protocol.verbs.learner import MAX_ROLLOUTS
from archery.services.learner import journal as journal_module
from archery.services.learner.algorithms.registry import restore_learner
from archery.services.learner.config import SessionConfig
from archery.services.learner.journal import (
    JOURNAL_NAME,
    MAX_JOURNAL_BYTES,
    ROLLOUT_BYTES,
    JournalError,
    read_records,
)
from archery.services.learner.session import Session
from tests.test_learner_service_session import Crash, FakeRig

ROLLOUTS = 2 * CHECKPOINT_EVERY + 15  # past two checkpoints


def _config(algorithm: str) -> SessionConfig:
    # random search puts most arrows off the fake target: aborts and redrawn θ, many in a row
    return SessionConfig(
        algorithm=algorithm, rollouts=ROLLOUTS, until_hit=False, seed=7, max_aborts=100
    )


def _shots(path: Path) -> list[tuple[str, int, list[float]]]:
    """Every attempt's outcome in order: (kind, index, θ in m)."""
    return [
        (r.kind, r.index, r.theta)
        for r in read_records(path)[0]
        if isinstance(r, DoneRecord | AbortedRecord)
    ]


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """One uninterrupted session per algorithm: its journal."""
    runs = tmp_path_factory.mktemp("whole")
    journals = {}
    for algorithm in ("archer", "power", "cma", "hill", "random"):
        session = Session.create(_config(algorithm), FakeRig(), runs, session_id=algorithm)
        assert session.run(threading.Event()).state == "finished"
        journals[algorithm] = session.journal.path
    return journals


@pytest.mark.parametrize("algorithm", ["archer", "power", "cma", "hill", "random"])
def test_a_session_killed_again_and_again_shoots_what_an_uninterrupted_one_does(
    algorithm: str, uninterrupted: dict[str, Path], tmp_path: Path
) -> None:
    # Killed mid-attempt (its proposed record journaled, no outcome): early, just after the
    # first checkpoint, between checkpoints and after the second one.
    kills = [23, CHECKPOINT_EVERY + 1, CHECKPOINT_EVERY + 57, 2 * CHECKPOINT_EVERY + 3]
    with pytest.raises(Crash):
        Session.create(
            _config(algorithm), FakeRig(crash_at=kills[0]), tmp_path, session_id=algorithm
        ).run(threading.Event())
    journal = tmp_path / algorithm / JOURNAL_NAME
    for crash in [*kills[1:], None]:
        attempts = sum(1 for r in read_records(journal)[0] if r.kind == "proposed")
        rig = FakeRig(crash_at=None if crash is None else crash - attempts + 1)
        resumed = Session.resume(journal, rig)
        if crash is None:
            assert resumed.run(threading.Event()).state == "finished"
        else:
            with pytest.raises(Crash):
                resumed.run(threading.Event())
    assert _shots(journal) == _shots(uninterrupted[algorithm])
    records = read_records(journal)[0]
    assert [r.rollout for r in records if isinstance(r, CheckpointRecord)] == [
        CHECKPOINT_EVERY,
        2 * CHECKPOINT_EVERY,
        ROLLOUTS,
    ]
    assert all(r.skipped is None or not r.skipped for r in records if isinstance(r, ResumedRecord))


def test_records_do_not_grow_with_the_session(uninterrupted: dict[str, Path]) -> None:
    for algorithm, path in uninterrupted.items():
        lines = path.read_bytes().splitlines(keepends=True)
        kinds = [json.loads(line)["record"] for line in lines]
        per_rollout = [
            len(lines[i - 1]) + len(line)
            for i, (kind, line) in enumerate(zip(kinds, lines, strict=True))
            if kind == "done" and kinds[i - 1] == "proposed"
        ]
        assert max(per_rollout) <= ROLLOUT_BYTES, algorithm
        assert max(per_rollout[-20:]) <= max(per_rollout[:20]) + 64, algorithm  # flat
        checkpoints = [
            len(line) for kind, line in zip(kinds, lines, strict=True) if kind == "checkpoint"
        ]
        assert max(checkpoints) <= ROLLOUT_BYTES, algorithm
        assert path.stat().st_size <= ROLLOUTS * ROLLOUT_BYTES, algorithm


def _cut_after_rollout(source: Path, folder: Path, rollout: int) -> Path:
    """A copy of a journal up to done rollout `rollout` (a learner killed right after it)."""
    lines = source.read_bytes().splitlines(keepends=True)
    (end,) = [
        i
        for i, line in enumerate(lines)
        if (record := json.loads(line))["record"] == "done" and record["rollout"] == rollout
    ]
    folder.mkdir()
    path = folder / JOURNAL_NAME
    path.write_bytes(b"".join(lines[: end + 1]))
    return path


def _edit(path: Path, change: dict[str, object], **where: object) -> None:
    """Rewrite every line whose fields match `where` with `change` applied (a hand edit)."""
    lines = []
    for line in path.read_text().splitlines():
        record = json.loads(line)
        if all(record.get(k) == v for k, v in where.items()):
            record = {**record, **change}
        lines.append(json.dumps(record, separators=(",", ":")) + "\n")
    path.write_text("".join(lines))


def test_a_corrupt_checkpoint_is_skipped_for_the_one_before_it(
    uninterrupted: dict[str, Path], tmp_path: Path
) -> None:
    path = _cut_after_rollout(uninterrupted["archer"], tmp_path / "archer", CHECKPOINT_EVERY + 30)
    checkpoint = next(
        r for r in read_records(path)[0] if isinstance(r, CheckpointRecord)
    ).learner_state
    _edit(path, {"learner_state": {**checkpoint, "rng": "torn"}}, record="checkpoint")
    Session.resume(path, FakeRig()).run(threading.Event())
    assert _shots(path) == _shots(uninterrupted["archer"])
    (resumed,) = [r for r in read_records(path)[0] if isinstance(r, ResumedRecord)]
    assert isinstance(resumed.skipped, str)
    assert f"(after rollout {CHECKPOINT_EVERY})" in resumed.skipped, resumed.skipped
    assert "random generator state: 'torn'" in resumed.skipped


def test_a_journal_edited_after_its_checkpoint_is_refused_naming_the_rollout(
    uninterrupted: dict[str, Path], tmp_path: Path
) -> None:
    path = _cut_after_rollout(uninterrupted["power"], tmp_path / "power", CHECKPOINT_EVERY + 30)
    before = path.read_bytes()
    done = next(
        r
        for r in read_records(path)[0]
        if isinstance(r, DoneRecord) and r.rollout == CHECKPOINT_EVERY + 12
    )
    theta = [done.theta[0] + 0.001, *done.theta[1:]]
    _edit(path, {"theta": theta}, index=done.index)  # its proposed and done records alike
    with pytest.raises(JournalError, match=rf"rollout {CHECKPOINT_EVERY + 12} \(attempt"):
        Session.resume(path, FakeRig())
    assert path.read_bytes() != before  # the edit stays, nothing was appended
    assert b'"resumed"' not in path.read_bytes()


def test_a_version_1_journal_resumes_from_its_last_done_state(tmp_path: Path) -> None:
    """Version 1 kept the learner's whole state in each done record: the last one restores, and
    the session goes on in checkpoints."""
    old = Path(__file__).parent / "journals" / "old_format.jsonl"
    lines = old.read_text().splitlines(keepends=True)
    assert json.loads(lines[0])["version"] == 1 and json.loads(lines[-1])["record"] == "end"
    header = json.loads(lines[0])
    header["rollouts"] = 9  # 3 more than it ran: its end record taken off
    (tmp_path / "old").mkdir()
    path = tmp_path / "old" / JOURNAL_NAME
    path.write_text(json.dumps(header, separators=(",", ":")) + "\n" + "".join(lines[1:-1]))
    last = [r for r in read_records(path)[0] if isinstance(r, DoneRecord)][-1]
    expected = restore_learner(last.learner_state).ask().tolist()
    rig = FakeRig()
    status = Session.resume(path, rig).run(threading.Event())
    assert status.state == "finished" and status.rollouts == 9, status
    records = read_records(path)[0]
    new = [r for r in records if isinstance(r, DoneRecord) and r.rollout > last.rollout]
    assert new[0].theta == expected and len(new) == 3
    assert all(isinstance(r.learner_state, UnsetType) for r in new)
    assert [r.rollout for r in records if isinstance(r, CheckpointRecord)] == [9]


def test_a_resume_that_would_pass_the_bound_is_refused_before_it_starts(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    assert MAX_JOURNAL_BYTES >= 4 * MAX_ROLLOUTS * ROLLOUT_BYTES  # a whole budget, with margin
    config = SessionConfig(rollouts=50, until_hit=False, seed=1)
    with pytest.raises(Crash):
        Session.create(config, FakeRig(crash_at=4), tmp_path, session_id="s").run(threading.Event())
    path = tmp_path / "s" / JOURNAL_NAME
    before = path.read_bytes()
    monkeypatch.setattr(journal_module, "MAX_JOURNAL_BYTES", len(before) + 10 * ROLLOUT_BYTES)
    with pytest.raises(JournalError, match="47 more rollouts would take it to about"):
        Session.resume(path, FakeRig())
    assert path.read_bytes() == before  # refused before anything was written


BAD_STATES = {
    # a generator state that is a 10 MB integer (its hex string, as `rng_state` tags big ints)
    "10 MB generator integer": (
        "archer",
        lambda s: {**s, "rng": {**s["rng"], "state": {"state": {"__int__": "f" * 10**7}}}},
        "not a saved random generator state",
    ),
    "unknown bit generator": (
        "archer",
        lambda s: {**s, "rng": {**s["rng"], "bit_generator": "RandomState"}},
        "not a saved random generator state",
    ),
    "pending far outside the θ box": (
        "archer",
        lambda s: {**s, "pending": [1e308] * 3},
        "pending θ [1e+308, 1e+308, 1e+308] m lies outside the θ box",
    ),
    "explore_std 1e308": (
        "archer",
        lambda s: {**s, "options": {**s["options"], "explore_std": 1e308}},
        "explore_std (m) must be finite and in [0, 1.0], got 1e+308",
    ),
    "a million CMA-ES proposals to replay": (
        "cma",
        lambda s: {**s, "extra": {**s["extra"], "events": s["extra"]["events"] + "p" * 10**6}},
        "and at most one 'p' more",
    ),
    "PoWER variance 1e308": (
        "power",
        lambda s: {**s, "extra": {**s["extra"], "variance": [1e308] * 3}},
        "PoWER variance [1e+308, 1e+308, 1e+308] m² is outside",
    ),
    "hill-climber std 1e308": (
        "hill",
        lambda s: {**s, "extra": {k: [1e308] * 3 for k in s["extra"]}},
        "hill-climber 'std' [1e+308, 1e+308, 1e+308] m is outside",
    ),
}


@pytest.mark.parametrize(("algorithm", "corrupt", "says"), BAD_STATES.values(), ids=BAD_STATES)
def test_a_checkpoint_out_of_its_algorithms_ranges_is_skipped_for_the_one_before_it(
    uninterrupted: dict[str, Path],
    tmp_path: Path,
    algorithm: str,
    corrupt: Callable[[dict[str, Any]], dict[str, Any]],
    says: str,
) -> None:
    path = _cut_after_rollout(uninterrupted[algorithm], tmp_path / algorithm, CHECKPOINT_EVERY + 30)
    checkpoint = next(
        r for r in read_records(path)[0] if isinstance(r, CheckpointRecord)
    ).learner_state
    _edit(path, {"learner_state": corrupt(dict(checkpoint))}, record="checkpoint")
    Session.resume(path, FakeRig()).run(threading.Event())  # no traceback: the header's state
    assert _shots(path) == _shots(uninterrupted[algorithm])
    (resumed,) = [r for r in read_records(path)[0] if isinstance(r, ResumedRecord)]
    assert isinstance(resumed.skipped, str)
    assert f"(after rollout {CHECKPOINT_EVERY}): " in resumed.skipped, resumed.skipped
    assert says in resumed.skipped and len(resumed.skipped) < 600, resumed.skipped
