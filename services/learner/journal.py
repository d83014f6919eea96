"""The crash-proof journal of a learning session: JSON lines, appended and fsynced one by one.

A journal is one file, `runs/<session>/journal.jsonl`. Every line is one JSON object with a
`record` kind and the `session` id:

* `header` (first line, once): journal `version`, `algorithm`, `seed`, `rollouts` (budget of
  done rollouts), `options` (the learner's), `config` (the rest of the session settings) and
  `learner_state`, the learner before its first proposal.
* `proposed` {index, theta}: rollout `index` (1, 2, …, attempts included) is about to run θ (m).
* `done` {index, rollout, theta, r_m, distance_m, hit, learner_state, …}: rollout `index`
  finished, the learner was told (θ, r) and `learner_state` is its state right after; `rollout`
  counts done rollouts (1-based).
* `aborted` {index, theta, code, cause, retry_theta}: rollout `index` ended without a
  measurement (the learner was not told); the next attempt runs `retry_theta`.
* `resumed`, `stopped` (paused, resumable) and `end` {reason, summary} (the session is over).

Each record is written with one `write`, then `flush` and `os.fsync`, so a record is either
durable or (after a crash mid-write) a torn last line without its newline, which `read` ignores
and `Journal.resume` cuts off before appending. `JournalState` replays the records and checks
them: one header, one rollout at a time, each index proposed once and finished at most once.
`check_invariants` lists every breach of a whole journal at once (for fault drills and tests).
Pure: no Zenoh.
"""

from __future__ import annotations

import json
import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from protocol.errors import ArcheryError

__all__ = [
    "JOURNAL_NAME",
    "JOURNAL_VERSION",
    "RECORD_KINDS",
    "Journal",
    "JournalError",
    "JournalState",
    "check_invariants",
    "read_records",
]

JOURNAL_VERSION = 1
JOURNAL_NAME = "journal.jsonl"
RECORD_KINDS = ("header", "proposed", "done", "aborted", "resumed", "stopped", "end")


class JournalError(ArcheryError, ValueError):
    """A journal that cannot be read, resumed or written; the message names the file and line."""

    code = "bad_journal"


def _encode(record: dict[str, Any]) -> bytes:
    """One record as a JSON line (UTF-8, no NaN allowed)."""
    try:
        text = json.dumps(record, allow_nan=False, separators=(",", ":"), ensure_ascii=False)
    except ValueError as exc:
        raise JournalError(
            f"record {record.get('record')!r} holds NaN or infinity: {exc}"
        ) from None
    return (text + "\n").encode()


def read_records(path: Path) -> tuple[list[dict[str, Any]], int]:
    """The records of a journal file and the byte length of its intact part.

    A last line without its newline, or one that is not valid JSON, is a torn write and is left
    out (its bytes lie beyond the returned length). Any other bad line is an error.

    Raises:
        JournalError: the file is missing or unreadable, or a line other than the last is not a
            JSON object.
    """
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise JournalError(f"cannot read journal {path}: {exc.strerror or exc}") from None
    records: list[dict[str, Any]] = []
    good = 0
    lines = data.split(b"\n")
    # After the last newline comes "" (an intact file) or the bytes of a torn write.
    complete, tail = lines[:-1], lines[-1]
    for number, line in enumerate(complete, start=1):
        final = number == len(complete) and not tail
        try:
            record = json.loads(line)
        except (UnicodeDecodeError, json.JSONDecodeError) as exc:
            if final:
                break  # a torn write that reached its newline (e.g. zero-filled blocks)
            raise JournalError(
                f"{path} line {number} is not JSON ({exc}); only the last line may be torn, so "
                f"the file is damaged"
            ) from None
        if not isinstance(record, dict) or record.get("record") not in RECORD_KINDS:
            raise JournalError(
                f"{path} line {number} is not a journal record (a JSON object whose 'record' "
                f"is one of {', '.join(RECORD_KINDS)})"
            )
        records.append(record)
        good += len(line) + 1
    return records, good


def check_invariants(records: list[dict[str, Any]], *, allow_open: bool = False) -> list[str]:
    """Every breach of a journal's rollout invariants (empty when it keeps them all): attempt
    indices proposed 1, 2, … once each; each proposed attempt ended by exactly one `done` or
    `aborted` record, after it (the last may stay open with `allow_open`, e.g. while running or
    after a crash); done rollout numbers 1, 2, … in order.

    Args:
        records: the journal's records in order (`read_records`), header first.
        allow_open: accept a last proposed attempt that has not ended yet.
    """
    violations: list[str] = []
    # as the records hold them: None where a record lacks its number
    proposed: list[int | None] = []
    ended: dict[int | None, str] = {}
    rollouts: list[int | None] = []
    for number, record in enumerate(records, start=1):
        kind, index = record.get("record"), record.get("index")
        if kind == "proposed":
            if index in proposed:
                violations.append(f"record {number}: attempt {index} proposed again")
            proposed.append(index)
        elif kind in ("done", "aborted"):
            if index not in proposed:
                violations.append(f"record {number}: {kind} for attempt {index}, never proposed")
            elif index in ended:
                violations.append(
                    f"record {number}: attempt {index} {kind} after it was {ended[index]} already"
                )
            ended.setdefault(index, kind)
            if kind == "done":
                rollouts.append(record.get("rollout"))
    if proposed != list(range(1, len(proposed) + 1)):
        violations.append(f"attempt indices not contiguous from 1: {proposed}")
    if rollouts != list(range(1, len(rollouts) + 1)):
        violations.append(f"done rollout numbers not contiguous from 1: {rollouts}")
    open_ = [i for i in proposed if i not in ended]
    if allow_open and open_ == proposed[-1:]:
        open_ = []
    if open_:
        violations.append(f"attempts proposed but never ended: {open_}")
    return violations


def _index(record: dict[str, Any], where: str) -> int:
    index = record.get("index")
    if isinstance(index, bool) or not isinstance(index, int) or index < 1:
        raise JournalError(f"{where}: index must be an integer >= 1, got {index!r}")
    return index


def _theta(record: dict[str, Any], key: str, where: str) -> list[float]:
    value = record.get(key)
    if (
        not isinstance(value, list)
        or not value
        or not all(isinstance(x, int | float) and not isinstance(x, bool) for x in value)
        or not all(math.isfinite(x) for x in value)
    ):
        raise JournalError(f"{where}: {key} must be a list of finite numbers (m), got {value!r}")
    return [float(x) for x in value]


@dataclass
class JournalState:
    """What a journal says so far, checked record by record (`apply`).

    Attributes:
        header: the header record.
        done: the done records, in order.
        aborted: the aborted records, in order.
        last_index: index of the latest proposed rollout (0 before any).
        open: the proposed record still waiting for its done/aborted record, if any.
        retry_theta: θ (m) the next attempt must run, set by an abort and cleared by a done.
        aborts_in_row: aborted records since the last done or resumed record, by code.
        ended: the end record, once the session is over.
        records: every record applied, in order.
    """

    header: dict[str, Any]
    done: list[dict[str, Any]] = field(default_factory=list)
    aborted: list[dict[str, Any]] = field(default_factory=list)
    last_index: int = 0
    open: dict[str, Any] | None = None
    retry_theta: list[float] | None = None
    aborts_in_row: dict[str, int] = field(default_factory=dict)
    ended: dict[str, Any] | None = None
    records: list[dict[str, Any]] = field(default_factory=list)

    @property
    def session(self) -> str:
        """The session id."""
        return str(self.header["session"])

    @property
    def learner_state(self) -> dict[str, Any]:
        """The learner's state after the last done rollout (the header's before any)."""
        source = self.done[-1] if self.done else self.header
        return dict(source["learner_state"])

    @classmethod
    def from_records(cls, records: list[dict[str, Any]], where: str = "journal") -> JournalState:
        """Replay records (the first must be the header).

        Raises:
            JournalError: a record breaks the journal's rules; the message names it.
        """
        if not records:
            raise JournalError(f"{where} is empty: no header record")
        state = cls(header=cls._check_header(records[0], where))
        state.records.append(records[0])
        for number, record in enumerate(records[1:], start=2):
            state.apply(record, f"{where} record {number}")
        return state

    @staticmethod
    def _check_header(header: dict[str, Any], where: str) -> dict[str, Any]:
        if header.get("record") != "header":
            raise JournalError(f"{where} does not start with a header record")
        version = header.get("version")
        if version != JOURNAL_VERSION:
            raise JournalError(
                f"{where} has journal version {version!r}; this learner reads version "
                f"{JOURNAL_VERSION} only (finish it with the version that wrote it)"
            )
        for key, kind in (
            ("session", str),
            ("algorithm", str),
            ("seed", int),
            ("rollouts", int),
            ("options", dict),
            ("config", dict),
            ("learner_state", dict),
        ):
            if not isinstance(header.get(key), kind):
                raise JournalError(f"{where} header lacks {key!r} ({kind.__name__})")
        return header

    def apply(self, record: dict[str, Any], where: str = "record") -> None:
        """Check `record` against what came before and take it in (every check runs before
        anything changes).

        Raises:
            JournalError: it breaks a rule (wrong session, index out of order, a rollout
                finished twice, anything after the end …); the state is unchanged.
        """
        kind = record.get("record")
        if kind not in RECORD_KINDS or kind == "header":
            raise JournalError(
                f"{where}: kind {kind!r} is not one of {', '.join(RECORD_KINDS[1:])}"
            )
        if record.get("session") != self.session:
            raise JournalError(
                f"{where} belongs to session {record.get('session')!r}, not {self.session!r}"
            )
        if self.ended is not None:
            raise JournalError(f"{where}: {kind} after the session's end record")
        if kind == "proposed":
            index = _index(record, where)
            _theta(record, "theta", where)
            if self.open is not None:
                raise JournalError(
                    f"{where}: rollout {index} proposed while rollout {self.open['index']} is "
                    f"still open"
                )
            if index != self.last_index + 1:
                raise JournalError(
                    f"{where}: rollout {index} proposed after rollout {self.last_index}; "
                    f"expected {self.last_index + 1}"
                )
            self.open = record
            self.last_index = index
        elif kind in ("done", "aborted"):
            index = _index(record, where)
            theta = _theta(record, "theta", where)
            if self.open is None or self.open["index"] != index:
                opened = None if self.open is None else self.open["index"]
                raise JournalError(
                    f"{where}: {kind} for rollout {index}, but the open rollout is {opened}"
                )
            if theta != self.open["theta"]:
                raise JournalError(
                    f"{where}: rollout {index} {kind} with θ {theta}, proposed {self.open['theta']}"
                )
            if kind == "done":
                _theta(record, "r_m", where)
                if not isinstance(record.get("learner_state"), dict):
                    raise JournalError(f"{where}: done record without a learner_state")
                if record.get("rollout") != len(self.done) + 1:
                    raise JournalError(
                        f"{where}: done rollout number {record.get('rollout')!r}, expected "
                        f"{len(self.done) + 1}"
                    )
                self.done.append(record)
                self.retry_theta = None
                self.aborts_in_row = {}
            else:
                code = record.get("code")
                if not isinstance(code, str) or not code:
                    raise JournalError(f"{where}: aborted record without a code")
                self.retry_theta = _theta(record, "retry_theta", where)
                self.aborted.append(record)
                self.aborts_in_row[code] = self.aborts_in_row.get(code, 0) + 1
            self.open = None
        elif kind == "resumed":
            self.aborts_in_row = {}  # a deliberate restart gets a fresh count of aborts
        elif kind == "end":
            if self.open is not None:
                raise JournalError(f"{where}: end while rollout {self.open['index']} is open")
            self.ended = record
        self.records.append(record)

    def hit_at(self) -> int | None:
        """The done-rollout number (1-based) of the first hit, or None."""
        return next((int(d["rollout"]) for d in self.done if d.get("hit")), None)

    def summary(self) -> dict[str, Any]:
        """Counts and results so far, as plain values."""
        last = self.done[-1] if self.done else None
        return {
            "session": self.session,
            "algorithm": self.header["algorithm"],
            "seed": self.header["seed"],
            "budget": self.header["rollouts"],
            "rollouts": len(self.done),
            "aborted": len(self.aborted),
            "hit_at": self.hit_at(),
            "final_distance_m": None if last is None else last.get("distance_m"),
            "best_distance_m": min((d["distance_m"] for d in self.done), default=None),
            "ended": None if self.ended is None else self.ended.get("reason"),
        }


class Journal:
    """Appends records to one session's journal file, durably (write, flush, fsync per record).

    Build one with `create` (a new session) or `resume` (an existing file); `state` is kept in
    step with the file, and a record that would break the journal's rules is refused before
    anything is written.
    """

    def __init__(self, path: Path, state: JournalState) -> None:
        self.path = path
        self.state = state
        self._file = open(path, "ab")  # noqa: SIM115 (kept open for the session)

    @classmethod
    def create(cls, directory: Path, header: dict[str, Any]) -> Journal:
        """Start `directory/journal.jsonl` with `header` (its `record`, `version` and `created`
        are filled in).

        Raises:
            JournalError: the journal exists already, or the header is incomplete.
        """
        header = {
            "record": "header",
            "version": JOURNAL_VERSION,
            "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            **header,
        }
        state = JournalState.from_records([header], str(directory / JOURNAL_NAME))
        directory.mkdir(parents=True, exist_ok=True)
        path = directory / JOURNAL_NAME
        try:
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
        except FileExistsError:
            raise JournalError(
                f"journal {path} exists already; resume it or choose another session id"
            ) from None
        try:
            os.write(fd, _encode(header))
            os.fsync(fd)
        finally:
            os.close(fd)
        _fsync_dir(directory)
        return cls(path, state)

    @classmethod
    def resume(cls, path: Path, session: str | None = None) -> Journal:
        """Open an existing journal to continue its session.

        A torn last line is cut off (it never was a complete record); nothing else is changed.

        Raises:
            JournalError: unreadable or broken journal, another session than `session`, another
                version, or a session that has ended.
        """
        records, good = read_records(path)
        state = JournalState.from_records(records, str(path))
        if session is not None and state.session != session:
            raise JournalError(
                f"journal {path} belongs to session {state.session!r}, not {session!r}"
            )
        if state.ended is not None:
            raise JournalError(
                f"session {state.session!r} in {path} has ended ({state.ended.get('reason')}); "
                f"start a new session instead"
            )
        if path.stat().st_size > good:
            with open(path, "r+b") as f:
                f.truncate(good)
                f.flush()
                os.fsync(f.fileno())
        return cls(path, state)

    def append(self, kind: str, **fields: Any) -> dict[str, Any]:
        """Check, write and fsync one record of `kind`; returns it.

        Raises:
            JournalError: the record breaks the journal's rules (nothing is written).
        """
        record = {"record": kind, "session": self.state.session, "t": time.time(), **fields}
        line = _encode(record)
        if self._file.closed:
            raise JournalError(f"journal {self.path} is closed; resume it to append")
        self.state.apply(record, f"new {kind} record")  # checks before it changes anything
        try:
            self._file.write(line)
            self._file.flush()
            os.fsync(self._file.fileno())
        except OSError as exc:
            self._file.close()  # the file may now hold a torn record: resume re-reads it
            raise JournalError(
                f"cannot write to journal {self.path}: {exc.strerror or exc}"
            ) from None
        return record

    def close(self) -> None:
        """Close the file (idempotent)."""
        if not self._file.closed:
            self._file.close()

    def __enter__(self) -> Journal:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _fsync_dir(directory: Path) -> None:
    """Make a new directory entry durable (best effort where directories cannot be opened)."""
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)
