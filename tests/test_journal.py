"""The session journal: durable JSON lines, torn last lines, replay rules, resume, and a writer
killed mid-stream."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from services.learner.algorithms.registry import make_learner, restore_learner
from services.learner.journal import (
    JOURNAL_NAME,
    JOURNAL_VERSION,
    Journal,
    JournalError,
    JournalState,
    read_records,
)


def _learner() -> Any:
    return make_learner("archer", np.array([0.17, 0.0, -0.02]), rng=np.random.default_rng(3))


def _header(session: str = "s1") -> dict[str, Any]:
    learner = _learner()
    return {
        "session": session,
        "algorithm": "archer",
        "seed": 3,
        "rollouts": 10,
        "options": learner.options(),
        "config": {"hit_radius_m": 0.05},
        "learner_state": learner.state_dict(),
    }


def _done(journal: Journal, index: int, theta: list[float], rollout: int) -> None:
    journal.append(
        "done",
        index=index,
        rollout=rollout,
        theta=theta,
        r_m=[0.01, 0.02],
        distance_m=0.0224,
        hit=True,
        learner_state=_learner().state_dict(),
    )


def test_create_append_and_read_back(tmp_path: Path) -> None:
    with Journal.create(tmp_path / "s1", _header()) as journal:
        journal.append("proposed", index=1, theta=[0.17, 0.0, -0.02])
        _done(journal, 1, [0.17, 0.0, -0.02], 1)
        journal.append("proposed", index=2, theta=[0.18, 0.0, -0.02])
        journal.append(
            "aborted",
            index=2,
            theta=[0.18, 0.0, -0.02],
            code="no_arrow",
            cause="no arrow seen",
            retry_theta=[0.175, 0.0, -0.02],
        )
    records, size = read_records(tmp_path / "s1" / JOURNAL_NAME)
    assert size == (tmp_path / "s1" / JOURNAL_NAME).stat().st_size
    assert [r["record"] for r in records] == ["header", "proposed", "done", "proposed", "aborted"]
    assert all(r["session"] == "s1" for r in records)
    assert records[0]["version"] == JOURNAL_VERSION
    state = JournalState.from_records(records)
    assert state.last_index == 2 and state.open is None
    assert state.retry_theta == [0.175, 0.0, -0.02]
    assert state.aborts_in_row == {"no_arrow": 1}
    assert state.summary()["rollouts"] == 1 and state.summary()["aborted"] == 1
    assert state.hit_at() == 1


def test_each_record_is_one_fsynced_line(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    synced: list[int] = []
    real = os.fsync
    monkeypatch.setattr(os, "fsync", lambda fd: (synced.append(fd), real(fd)))
    journal = Journal.create(tmp_path / "s1", _header())
    before = len(synced)
    journal.append("proposed", index=1, theta=[0.17, 0.0, -0.02])
    assert len(synced) == before + 1
    lines = (tmp_path / "s1" / JOURNAL_NAME).read_bytes().split(b"\n")
    assert lines[-1] == b"" and len(lines) == 3


@pytest.mark.parametrize(
    "tail", [b'{"record": "done", "ses', b'{"record":"stopped"}', b"\x00\x00\x00"]
)
def test_torn_last_line_is_ignored_then_cut_on_resume(tmp_path: Path, tail: bytes) -> None:
    with Journal.create(tmp_path / "s1", _header()) as journal:
        journal.append("proposed", index=1, theta=[0.17, 0.0, -0.02])
    path = tmp_path / "s1" / JOURNAL_NAME
    intact = path.read_bytes()
    path.write_bytes(intact + tail)
    records, size = read_records(path)
    assert len(records) == 2 and size == len(intact)
    with Journal.resume(path, "s1") as journal:
        assert path.read_bytes() == intact
        assert journal.state.open is not None and journal.state.open["index"] == 1
        _done(journal, 1, [0.17, 0.0, -0.02], 1)
    assert [r["record"] for r in read_records(path)[0]] == ["header", "proposed", "done"]


def test_zero_filled_last_line_with_newline_is_torn(tmp_path: Path) -> None:
    Journal.create(tmp_path / "s1", _header()).close()
    path = tmp_path / "s1" / JOURNAL_NAME
    path.write_bytes(path.read_bytes() + b"\x00\x00\n")
    assert len(read_records(path)[0]) == 1


def test_damaged_middle_line_is_an_error_and_untouched(tmp_path: Path) -> None:
    with Journal.create(tmp_path / "s1", _header()) as journal:
        journal.append("proposed", index=1, theta=[0.17, 0.0, -0.02])
    path = tmp_path / "s1" / JOURNAL_NAME
    lines = path.read_bytes().split(b"\n")
    damaged = b"\n".join([lines[0][:20], *lines[1:]])
    path.write_bytes(damaged)
    with pytest.raises(JournalError, match="line 1 is not JSON"):
        Journal.resume(path)
    assert path.read_bytes() == damaged


def _rewrite_header(path: Path, **changes: Any) -> bytes:
    lines = path.read_bytes().split(b"\n")
    header = json.loads(lines[0]) | changes
    data = b"\n".join([json.dumps(header).encode(), *lines[1:]])
    path.write_bytes(data)
    return data


def test_other_version_or_session_is_refused_untouched(tmp_path: Path) -> None:
    with Journal.create(tmp_path / "s1", _header()) as journal:
        journal.append("proposed", index=1, theta=[0.17, 0.0, -0.02])
    path = tmp_path / "s1" / JOURNAL_NAME
    with pytest.raises(JournalError, match="belongs to session 's1', not 's2'"):
        Journal.resume(path, "s2")
    data = _rewrite_header(path, version=JOURNAL_VERSION + 1)
    with pytest.raises(JournalError, match=f"version {JOURNAL_VERSION + 1}"):
        Journal.resume(path)
    assert path.read_bytes() == data


def test_record_of_another_session_is_refused(tmp_path: Path) -> None:
    Journal.create(tmp_path / "s1", _header()).close()
    path = tmp_path / "s1" / JOURNAL_NAME
    other = {"record": "proposed", "session": "s9", "index": 1, "theta": [0.1, 0.0, 0.0]}
    path.write_bytes(path.read_bytes() + json.dumps(other).encode() + b"\n")
    with pytest.raises(JournalError, match="belongs to session 's9'"):
        Journal.resume(path)


def test_rules_refuse_before_writing(tmp_path: Path) -> None:
    journal = Journal.create(tmp_path / "s1", _header())
    path = journal.path
    journal.append("proposed", index=1, theta=[0.17, 0.0, -0.02])
    before = path.read_bytes()
    bad = [
        ("proposed", {"index": 2, "theta": [0.17, 0.0, -0.02]}, "still open"),
        (
            "done",
            {
                "index": 2,
                "rollout": 1,
                "theta": [0.17, 0.0, -0.02],
                "r_m": [0, 0],
                "learner_state": {},
            },
            "open rollout is 1",
        ),
        (
            "done",
            {
                "index": 1,
                "rollout": 1,
                "theta": [0.2, 0.0, -0.02],
                "r_m": [0, 0],
                "learner_state": {},
            },
            "proposed",
        ),
        (
            "done",
            {
                "index": 1,
                "rollout": 2,
                "theta": [0.17, 0.0, -0.02],
                "r_m": [0, 0],
                "learner_state": {},
            },
            "expected 1",
        ),
        (
            "done",
            {
                "index": 1,
                "rollout": 1,
                "theta": [0.17, 0.0, -0.02],
                "r_m": [float("nan"), 0],
                "learner_state": {},
            },
            "NaN",
        ),
        (
            "aborted",
            {"index": 1, "theta": [0.17, 0.0, -0.02], "cause": "x", "retry_theta": [1.0]},
            "without a code",
        ),
        ("end", {"reason": "budget"}, "open"),
        ("header", {}, "not one of"),
    ]
    for kind, fields, message in bad:
        with pytest.raises(JournalError, match=message):
            journal.append(kind, **fields)
    assert path.read_bytes() == before
    _done(journal, 1, [0.17, 0.0, -0.02], 1)
    with pytest.raises(JournalError, match="open rollout is None"):
        _done(journal, 1, [0.17, 0.0, -0.02], 2)
    journal.append("end", reason="hit")
    with pytest.raises(JournalError, match="after the session's end"):
        journal.append("proposed", index=2, theta=[0.17, 0.0, -0.02])
    journal.close()
    with pytest.raises(JournalError, match="has ended"):
        Journal.resume(path)


def test_create_refuses_an_existing_journal(tmp_path: Path) -> None:
    Journal.create(tmp_path / "s1", _header()).close()
    data = (tmp_path / "s1" / JOURNAL_NAME).read_bytes()
    with pytest.raises(JournalError, match="exists already"):
        Journal.create(tmp_path / "s1", _header())
    assert (tmp_path / "s1" / JOURNAL_NAME).read_bytes() == data


def test_header_must_be_complete(tmp_path: Path) -> None:
    header = _header()
    del header["learner_state"]
    with pytest.raises(JournalError, match="learner_state"):
        Journal.create(tmp_path / "s1", header)
    assert not (tmp_path / "s1").exists()


def test_learner_state_restores_the_next_proposal(tmp_path: Path) -> None:
    learner = _learner()
    journal = Journal.create(tmp_path / "s1", _header())
    world = np.array([[8.0, -11.0, -1.0], [2.0, -4.0, -12.0]])  # m of r per m of θ
    for k in range(1, 6):
        theta = learner.ask()
        journal.append("proposed", index=k, theta=theta.tolist())
        r = world @ (theta - np.array([0.16, 0.0, -0.017]))
        learner.tell(theta, r)
        journal.append(
            "done",
            index=k,
            rollout=k,
            theta=theta.tolist(),
            r_m=r.tolist(),
            distance_m=float(np.linalg.norm(r)),
            hit=False,
            learner_state=learner.state_dict(),
        )
    journal.close()
    state = Journal.resume(journal.path).state
    restored = restore_learner(state.learner_state)
    np.testing.assert_array_equal(restored.ask(), learner.ask())


_WRITER = """
import sys
from pathlib import Path
from services.learner.journal import Journal
journal = Journal.create(Path(sys.argv[1]), {"session": "k", "algorithm": "archer", "seed": 0,
    "rollouts": 10**6, "options": {}, "config": {}, "learner_state": {"pad": "x" * 4000}})
print("ready", flush=True)
k = 0
while True:
    k += 1
    journal.append("proposed", index=k, theta=[0.1, 0.0, 0.0])
    journal.append("aborted", index=k, theta=[0.1, 0.0, 0.0], code="test", cause="x" * 3000,
                   retry_theta=[0.1, 0.0, 0.0])
"""


def test_writer_killed_mid_stream_leaves_a_readable_journal(tmp_path: Path) -> None:
    child = subprocess.Popen(
        [sys.executable, "-c", _WRITER, str(tmp_path / "k")], stdout=subprocess.PIPE
    )
    assert child.stdout is not None and child.stdout.readline().strip() == b"ready"
    time.sleep(0.3)
    child.send_signal(signal.SIGKILL)
    child.wait(timeout=10)
    path = tmp_path / "k" / JOURNAL_NAME
    journal = Journal.resume(path, "k")
    state = journal.state
    assert state.last_index > 2
    # No rollout lost or doubled: indices are 1..n, each proposed once, finished at most once.
    proposed = [r["index"] for r in state.records if r["record"] == "proposed"]
    assert proposed == list(range(1, state.last_index + 1))
    if state.open is not None:  # the kill came between a proposed and its aborted record
        journal.append(
            "aborted",
            index=state.last_index,
            theta=[0.1, 0.0, 0.0],
            code="test",
            cause="",
            retry_theta=[0.1, 0.0, 0.0],
        )
    journal.append("end", reason="test")
    journal.close()
    assert read_records(path)[1] == path.stat().st_size
