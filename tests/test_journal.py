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

import msgspec
import numpy as np
import pytest
from msgspec import UNSET

from archery.protocol.journal_records import (
    JOURNAL_VERSION,
    AbortedRecord,
    CheckpointRecord,
    DoneRecord,
    EndRecord,
    HeaderRecord,
    JournalRecord,
    ProposedRecord,
    ResumedRecord,
    SessionRecord,
    StoppedRecord,
)
from archery.services.learner import journal as journal_module
from archery.services.learner.algorithms.registry import make_learner
from archery.services.learner.journal import (
    JOURNAL_NAME,
    MAX_JOURNAL_BYTES,
    Journal,
    JournalError,
    JournalState,
    check_invariants,
    encode_record,
    read_records,
)
from archery.services.learner.replay import rebuild_learner


def _learner() -> Any:
    return make_learner("archer", np.array([0.17, 0.0, -0.02]), rng=np.random.default_rng(3))


def _header(session: str = "s1") -> HeaderRecord:
    learner = _learner()
    return HeaderRecord(
        session=session,
        algorithm="archer",
        seed=3,
        rollouts=10,
        options=learner.options(),
        config={"hit_radius_m": 0.05},
        learner_state=learner.state_dict(),
    )


def _proposed(index: int, theta: list[float]) -> ProposedRecord:
    return ProposedRecord(index=index, theta=theta)


def _done_record(index: int, theta: list[float], rollout: int, **fields: Any) -> DoneRecord:
    values: dict[str, Any] = {
        "r_m": [0.01, 0.02],
        "distance_m": 0.0224,
        "hit": True,
        "learner_state": _learner().state_dict(),
    }
    return DoneRecord(index=index, rollout=rollout, theta=theta, **(values | fields))


def _done(journal: Journal, index: int, theta: list[float], rollout: int) -> None:
    journal.append(_done_record(index, theta, rollout))


def test_create_append_and_read_back(tmp_path: Path) -> None:
    with Journal.create(tmp_path / "s1", _header()) as journal:
        journal.append(_proposed(1, [0.17, 0.0, -0.02]))
        _done(journal, 1, [0.17, 0.0, -0.02], 1)
        journal.append(_proposed(2, [0.18, 0.0, -0.02]))
        journal.append(
            AbortedRecord(
                index=2,
                theta=[0.18, 0.0, -0.02],
                code="no_arrow",
                cause="no arrow seen",
                retry_theta=[0.175, 0.0, -0.02],
            )
        )
    records, size = read_records(tmp_path / "s1" / JOURNAL_NAME)
    assert size == (tmp_path / "s1" / JOURNAL_NAME).stat().st_size
    assert [r.kind for r in records] == ["header", "proposed", "done", "proposed", "aborted"]
    assert all(isinstance(r, HeaderRecord | SessionRecord) and r.session == "s1" for r in records)
    assert isinstance(records[0], HeaderRecord) and records[0].version == JOURNAL_VERSION
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
    journal.append(_proposed(1, [0.17, 0.0, -0.02]))
    assert len(synced) == before + 1
    lines = (tmp_path / "s1" / JOURNAL_NAME).read_bytes().split(b"\n")
    assert lines[-1] == b"" and len(lines) == 3


@pytest.mark.parametrize(
    "tail", [b'{"record": "done", "ses', b'{"record":"stopped"}', b"\x00\x00\x00"]
)
def test_torn_last_line_is_ignored_then_cut_on_resume(tmp_path: Path, tail: bytes) -> None:
    with Journal.create(tmp_path / "s1", _header()) as journal:
        journal.append(_proposed(1, [0.17, 0.0, -0.02]))
    path = tmp_path / "s1" / JOURNAL_NAME
    intact = path.read_bytes()
    path.write_bytes(intact + tail)
    records, size = read_records(path)
    assert len(records) == 2 and size == len(intact)
    with Journal.resume(path, "s1") as journal:
        assert path.read_bytes() == intact
        assert journal.state.open is not None and journal.state.open.index == 1
        _done(journal, 1, [0.17, 0.0, -0.02], 1)
    assert [r.kind for r in read_records(path)[0]] == ["header", "proposed", "done"]


def test_zero_filled_last_line_with_newline_is_torn(tmp_path: Path) -> None:
    Journal.create(tmp_path / "s1", _header()).close()
    path = tmp_path / "s1" / JOURNAL_NAME
    path.write_bytes(path.read_bytes() + b"\x00\x00\n")
    assert len(read_records(path)[0]) == 1


def test_damaged_middle_line_is_an_error_and_untouched(tmp_path: Path) -> None:
    with Journal.create(tmp_path / "s1", _header()) as journal:
        journal.append(_proposed(1, [0.17, 0.0, -0.02]))
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
        journal.append(_proposed(1, [0.17, 0.0, -0.02]))
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
    journal.append(_proposed(1, [0.17, 0.0, -0.02]))
    before = path.read_bytes()
    state: dict[str, Any] = {}
    bad: list[tuple[JournalRecord, str]] = [
        (_proposed(2, [0.17, 0.0, -0.02]), "still open"),
        (
            _done_record(2, [0.17, 0.0, -0.02], 1, r_m=[0, 0], learner_state=state),
            "open rollout is 1",
        ),
        (_done_record(1, [0.2, 0.0, -0.02], 1, r_m=[0, 0], learner_state=state), "proposed"),
        (
            _done_record(1, [0.17, 0.0, -0.02], 2, r_m=[0, 0], learner_state=state),
            "expected 1",
        ),
        (
            _done_record(1, [0.17, 0.0, -0.02], 1, r_m=[float("nan"), 0], learner_state=state),
            "NaN",
        ),
        (CheckpointRecord(rollout=0, learner_state={}), "checkpoint while rollout 1 is open"),
        (
            AbortedRecord(index=1, theta=[0.17, 0.0, -0.02], code="", cause="x", retry_theta=[1.0]),
            r"new aborted record: aborted record: .* at `\$\.code`",
        ),
        (
            DoneRecord(
                index="1",  # type: ignore[arg-type]  # a wrong type, on purpose
                rollout=1,
                theta=[0.17, 0.0, -0.02],
                r_m=[0.0, 0.0],
                distance_m=0.0,
                hit=False,
                learner_state=state,
            ),
            r"new done record: done record: Expected `int`, got `str` - at `\$\.index`",
        ),
        (EndRecord(reason="budget", summary={}), "open"),
        (_header(), "not one of"),
    ]
    for record, message in bad:
        with pytest.raises(JournalError, match=message):
            journal.append(record)
    assert path.read_bytes() == before
    _done(journal, 1, [0.17, 0.0, -0.02], 1)
    with pytest.raises(JournalError, match="open rollout is None"):
        _done(journal, 1, [0.17, 0.0, -0.02], 2)
    journal.append(EndRecord(reason="hit", summary={}))
    with pytest.raises(JournalError, match="after the session's end"):
        journal.append(_proposed(2, [0.17, 0.0, -0.02]))
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
    header = msgspec.structs.replace(_header(), learner_state=None)
    with pytest.raises(JournalError, match=r"header: .* at `\$\.learner_state`"):
        Journal.create(tmp_path / "s1", header)
    assert not (tmp_path / "s1").exists()
    # A header line without its learner state is refused where it is read.
    Journal.create(tmp_path / "s1", _header()).close()
    path = tmp_path / "s1" / JOURNAL_NAME
    line = json.loads(path.read_bytes())
    del line["learner_state"]
    path.write_text(json.dumps(line) + "\n")
    with pytest.raises(JournalError, match=r"line 1: header record: .* `learner_state`"):
        Journal.resume(path)


def test_learner_state_restores_the_next_proposal(tmp_path: Path) -> None:
    learner = _learner()
    journal = Journal.create(tmp_path / "s1", _header())
    world = np.array([[8.0, -11.0, -1.0], [2.0, -4.0, -12.0]])  # m of r per m of θ
    for k in range(1, 6):
        theta = learner.ask()
        journal.append(_proposed(k, theta.tolist()))
        r = world @ (theta - np.array([0.16, 0.0, -0.017]))
        learner.tell(theta, r)
        journal.append(
            DoneRecord(
                index=k,
                rollout=k,
                theta=theta.tolist(),
                r_m=r.tolist(),
                distance_m=float(np.linalg.norm(r)),
                hit=False,
            )
        )
    journal.close()
    state = Journal.resume(journal.path).state
    restored, skipped = rebuild_learner(state)
    assert skipped == []
    np.testing.assert_array_equal(restored.ask(), learner.ask())


_WRITER = """
import sys
from pathlib import Path
from archery.protocol.journal_records import AbortedRecord, HeaderRecord, ProposedRecord
from archery.services.learner.journal import Journal
journal = Journal.create(Path(sys.argv[1]), HeaderRecord(session="k", algorithm="archer", seed=0,
    rollouts=10**6, options={}, config={}, learner_state={"pad": "x" * 4000}))
print("ready", flush=True)
k = 0
while True:
    k += 1
    journal.append(ProposedRecord(index=k, theta=[0.1, 0.0, 0.0]))
    journal.append(AbortedRecord(index=k, theta=[0.1, 0.0, 0.0], code="test", cause="x" * 3000,
                   retry_theta=[0.1, 0.0, 0.0]))
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
    proposed = [r.index for r in state.records if isinstance(r, ProposedRecord)]
    assert proposed == list(range(1, state.last_index + 1))
    if state.open is not None:  # the kill came between a proposed and its aborted record
        journal.append(
            AbortedRecord(
                index=state.last_index,
                theta=[0.1, 0.0, 0.0],
                code="test",
                cause="",
                retry_theta=[0.1, 0.0, 0.0],
            )
        )
    journal.append(EndRecord(reason="test", summary={}))
    journal.close()
    assert read_records(path)[1] == path.stat().st_size


# -- the records as Structs: old journals, typed errors, byte-stable lines ------------------------
OLD = Path(__file__).parent / "journals"  # journals as the learner wrote them before the Structs


@pytest.mark.parametrize(
    ("name", "summary", "kinds"),
    [
        (
            "old_format.jsonl",
            {"rollouts": 6, "aborted": 2, "hit_at": 4, "ended": "budget"},
            {"header", "proposed", "done", "aborted", "stopped", "resumed", "end"},
        ),
        (
            "old_format_from.jsonl",
            {"rollouts": 0, "aborted": 2, "hit_at": None, "ended": None},
            {"header", "proposed", "aborted", "stopped"},
        ),
    ],
)
def test_an_old_format_journal_decodes_unchanged(
    tmp_path: Path, name: str, summary: dict[str, Any], kinds: set[str]
) -> None:
    path = OLD / name
    data = path.read_bytes()
    records, size = read_records(path)
    assert size == len(data) and {r.kind for r in records} == kinds
    # every line encodes back to its very bytes (fields, order, float digits, no spaces)
    assert b"".join(encode_record(r) for r in records) == data
    # written before done records held the launched θ: it reads as absent, and stays so
    assert all(r.theta_launched is UNSET for r in records if isinstance(r, DoneRecord))
    state = JournalState.from_records(records, str(path))
    assert {k: state.summary()[k] for k in summary} == summary
    assert check_invariants(records, allow_open=state.ended is None) == []
    if state.ended is None:  # a stopped session resumes and goes on appending
        copy = tmp_path / name
        copy.write_bytes(data)
        with Journal.resume(copy, state.session) as journal:
            assert journal.state.retry_theta == state.retry_theta
            journal.append(ResumedRecord(after=journal.state.last_index))
        assert copy.read_bytes().startswith(data)


@pytest.mark.parametrize(
    ("number", "changes", "message"),
    [
        (3, {"index": "3"}, "Expected `int`, got `str` - at `$.index`"),
        (3, {"theta": [0.1, "x", 0.0]}, "Expected `float`, got `str` - at `$.theta[1]`"),
        (3, {"theta": []}, "Expected `array` of length >= 1 - at `$.theta`"),
        (3, {"hit": "yes"}, "Expected `bool`, got `str` - at `$.hit`"),
        (3, {"r_m": UNSET}, "Object missing required field `r_m`"),
        (5, {"code": UNSET}, "Object missing required field `code`"),
        (5, {"code": ""}, "Expected `str` of length >= 1 - at `$.code`"),
        (1, {"seed": 1.5}, "Expected `int`, got `float` - at `$.seed`"),
        (1, {"options": []}, "Expected `object`, got `array` - at `$.options`"),
    ],
)
def test_a_record_with_a_wrong_type_names_its_line_and_field(
    tmp_path: Path, number: int, changes: dict[str, Any], message: str
) -> None:
    lines = [json.loads(line) for line in (OLD / "old_format.jsonl").read_text().splitlines()]
    for key, value in changes.items():  # UNSET: the field is left out
        lines[number - 1].pop(key)
        if value is not UNSET:
            lines[number - 1][key] = value
    path = tmp_path / JOURNAL_NAME
    path.write_text("".join(json.dumps(line) + "\n" for line in lines))
    kind = lines[number - 1]["record"]
    with pytest.raises(JournalError) as caught:
        read_records(path)
    assert str(caught.value) == f"{path} line {number}: {kind} record: {message}"


def test_a_line_of_no_known_kind_is_not_a_record(tmp_path: Path) -> None:
    path = tmp_path / JOURNAL_NAME
    lines = (OLD / "old_format.jsonl").read_bytes().splitlines(keepends=True)
    for bad in (b'{"record":"paused","session":"old-format"}\n', b"[1, 2]\n", b'{"index":1}\n'):
        path.write_bytes(b"".join([*lines[:2], bad, *lines[2:]]))
        with pytest.raises(JournalError, match="line 3 is not a journal record"):
            read_records(path)


def test_a_header_of_another_version_says_so_even_when_its_fields_differ(tmp_path: Path) -> None:
    path = tmp_path / JOURNAL_NAME
    path.write_text(json.dumps({"record": "header", "version": 3, "session": "s"}) + "\n")
    with pytest.raises(
        JournalError, match="has journal version 3; this learner reads versions 1 and 2"
    ):
        read_records(path)


def _every_kind() -> list[JournalRecord]:
    """One record of each kind, with every field a line may have or lack."""
    theta = [0.17, 0.006, -0.026]
    header = msgspec.structs.replace(
        _header("s1"),
        controller_box={"low": [0.12, -0.02, -0.07], "high": [0.24, 0.06, 0.01]},
        from_={"session": "s0", "journal": "runs/s0/journal.jsonl", "algo": "archer"},
    )
    return [
        header,
        _proposed(1, theta),
        _done_record(
            1,
            theta,
            1,
            theta_measured=[0.1700000001, 0.006, -0.026],
            theta_launched=[0.1700000002, 0.006, -0.026],
            r_m=[6.201199994393392e-05, -1e-7],  # floats Python writes with an exponent
            ret=0.999,
            distance_m=1e-7,
            hit=True,
            shot=1,
            outcome="target",
            truth_r_m=[1e16, 0.0],
            truth_distance_m=1e16,
            detection={"status": "ok", "r_m": [0.01, 0.02], "type": "Detection"},
            timing={"ask_s": 6.2e-05, "rollout_s": 0.07},
        ),
        _proposed(2, theta),
        AbortedRecord(
            index=2, theta=theta, code="service_lost", cause="camera: gone", retry_theta=theta
        ),
        _proposed(3, theta),
        AbortedRecord(
            index=3,
            theta=theta,
            code="no_target",
            cause="the detector says no_target: θ unseen",  # UTF-8 as is
            retry_theta=theta,
            truth_r_m=None,
            detection={"status": "no_target", "reason": "dark"},
        ),
        StoppedRecord(reason="failed", cause="3 attempts in a row were aborted"),
        ResumedRecord(after=3),
        _proposed(4, theta),
        _done_record(4, theta, 2, hit=False),
        StoppedRecord(reason="stop requested"),
        EndRecord(reason="budget", summary={"rollouts": 2, "hit_at": 1, "ended": None}),
    ]


def test_each_record_kind_round_trips_byte_stable(tmp_path: Path) -> None:
    records = _every_kind()
    with Journal.create(tmp_path / "s1", records[0]) as journal:
        written = [journal.state.header] + [journal.append(r) for r in records[1:]]
    path = journal.path
    lines = path.read_bytes().splitlines(keepends=True)
    read, _ = read_records(path)
    assert {r.kind for r in read} == {
        "header", "proposed", "done", "aborted", "resumed", "stopped", "end"
    }  # fmt: skip
    assert read == written  # decoded as appended
    one = tmp_path / "one.jsonl"
    for record, line in zip(read, lines, strict=True):
        assert encode_record(record) == line  # decode → encode: the same bytes
        one.write_bytes(encode_record(record))
        assert read_records(one)[0] == [record]  # encode → decode: the same record
    assert "θ".encode() in lines[6] and b"\\u" not in lines[6]
    assert b'"truth_r_m"' not in lines[4] and b'"cause"' not in lines[11]  # absent stays absent


def test_only_a_regular_file_within_the_bound_is_read(tmp_path: Path) -> None:
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)  # opened without blocking, then refused
    with pytest.raises(JournalError, match="is not a regular file"):
        read_records(fifo)
    with pytest.raises(JournalError, match="is not a regular file"):
        read_records(Path("/dev/zero"))
    huge = tmp_path / "huge.jsonl"
    with open(huge, "wb") as f:
        f.truncate(MAX_JOURNAL_BYTES + 1)  # sparse: no block written
    with pytest.raises(JournalError, match=f"more than a journal may \\({MAX_JOURNAL_BYTES} "):
        read_records(huge)
    deep = tmp_path / "deep.jsonl"
    nested = b"[" * 100_000 + b"]" * 100_000
    deep.write_bytes(b'{"record": "header", "junk": ' + nested + b"}\n{}\n")
    with pytest.raises(JournalError, match="line 1 nests too deep"):
        read_records(deep)
    deep.write_bytes(nested + b"\n{}\n")
    with pytest.raises(JournalError, match="line 1 is not a journal record"):
        read_records(deep)


def test_a_journal_never_grows_past_the_bound(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    with Journal.create(tmp_path / "s1", _header()) as journal:
        size = journal.path.stat().st_size
        monkeypatch.setattr(journal_module, "MAX_JOURNAL_BYTES", size + 100)
        journal.append(_proposed(1, [0.17, 0.0, -0.02]))  # under 100 bytes
        with pytest.raises(JournalError, match=r"would pass \d+ bytes, the most a journal"):
            _done(journal, 1, [0.17, 0.0, -0.02], 1)
        assert read_records(journal.path)[0][-1].kind == "proposed"  # nothing written
