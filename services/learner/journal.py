"""The crash-proof journal of a learning session: JSON lines, appended and fsynced one by one.

A journal is one file, `runs/<session>/journal.jsonl`; every line is one record of
`protocol.journal_records`, decoded with msgspec and encoded as it always was
(`encode_record`). Each record is written unbuffered, then fsynced (`Journal.append`), so it
is either durable or a torn last line without its newline, which `read_records` ignores and
`Journal.resume` cuts off before appending. `JournalState` replays the records and checks what
the types cannot: one header, one rollout at a time, each index proposed once and finished at
most once, in order. `check_invariants` lists every breach of a whole journal at once (for
fault drills and tests). Pure: no Zenoh.
"""

from __future__ import annotations

import contextlib
import errno
import io
import json
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Union

import msgspec
import numpy as np
from msgspec import UnsetType

from archery.mesh.regular_file import FileRefused, open_regular, read_regular
from archery.protocol.errors import ArcheryError
from archery.protocol.journal_records import (
    JOURNAL_VERSION,
    READ_VERSIONS,
    RECORD_KINDS,
    RECORD_TYPES,
    AbortedRecord,
    CheckpointRecord,
    DoneRecord,
    EndRecord,
    HeaderRecord,
    JournalRecord,
    ProposedRecord,
    ResumedRecord,
    SessionRecord,
)
from archery.protocol.text import SHOWN_LIMIT, cut, shown
from archery.protocol.verbs.learner import MAX_ROLLOUTS

__all__ = [
    "JOURNAL_NAME",
    "MAX_JOURNAL_BYTES",
    "ROLLOUT_BYTES",
    "Checkpoint",
    "Journal",
    "JournalError",
    "JournalState",
    "check_invariants",
    "encode_record",
    "read_records",
]

JOURNAL_NAME = "journal.jsonl"

# What one done rollout adds to a journal (bytes): its proposed and done records (about 1.7 kB
# with the detector's reply and the steps' timing, whatever the session's length: no record
# holds the history) and its share of the checkpoints (a learner's state without its history,
# about 1 kB, every `CHECKPOINT_EVERY` rollouts; CMA-ES's grows by 2 bytes per rollout).
ROLLOUT_BYTES = 4096
# The largest journal the learner reads or writes (bytes): `MAX_ROLLOUTS` rollouts of
# `ROLLOUT_BYTES` with a margin of 6 for aborted attempts (about 1 kB each, both records), so a
# session within its budget never reaches it (`Journal.room_for` says so before a session
# starts). Reading a journal takes a few times its size in memory, so a bigger file (a huge or
# sparse one) is refused before it is read, and a record that would pass the bound is refused
# instead of writing a journal that could not be read back.
MAX_JOURNAL_BYTES = 6 * MAX_ROLLOUTS * ROLLOUT_BYTES
_decoder: msgspec.json.Decoder[Any] = msgspec.json.Decoder(Union[RECORD_TYPES])  # noqa: UP007


class JournalError(ArcheryError, ValueError):
    """A journal that cannot be read, resumed or written; the message names the file and line."""

    code = "bad_journal"


def _plain(value: Any) -> Any:
    """A numpy scalar as the Python number it holds (what `json` wrote of it)."""
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"a journal record cannot hold {type(value).__name__} {value!r}")


def encode_record(record: JournalRecord) -> bytes:
    """One record as its journal line: compact JSON (UTF-8, fields in the Struct's order, no
    NaN), newline included, so a record decoded from a line encodes back to it.

    Raises:
        JournalError: the record holds NaN or infinity, or a value JSON cannot hold.
    """
    try:
        text = json.dumps(
            msgspec.to_builtins(record, enc_hook=_plain),
            allow_nan=False,
            separators=(",", ":"),
            ensure_ascii=False,
        )
    except ValueError as exc:
        raise JournalError(f"record {record.kind!r} holds NaN or infinity: {exc}") from None
    except TypeError as exc:
        raise JournalError(f"record {record.kind!r}: {exc}") from None
    return (text + "\n").encode()


def _version_error(where: str, version: Any) -> JournalError:
    readable = " and ".join(str(v) for v in READ_VERSIONS)
    return JournalError(
        f"{where} has journal version {shown(version)}; this learner reads versions {readable} "
        f"only (finish it with the version that wrote it)"
    )


def _decode(line: bytes, where: str) -> JournalRecord:
    """The record of one JSON line, checked against its kind's Struct.

    Raises:
        JournalError: the line is JSON but not a record (not an object, no known `record`
            kind, nested too deep), or a field is missing or of the wrong type; the message
            says which.
        msgspec.DecodeError: the line is not JSON at all (the caller decides: torn or damaged).
    """
    try:
        record: JournalRecord = _decoder.decode(line)
    except RecursionError:
        raise JournalError(f"{where} nests too deep to be a journal record") from None
    except msgspec.ValidationError as exc:
        try:
            loose = msgspec.json.decode(line)
        except RecursionError:
            loose = None
        kind = loose.get("record") if isinstance(loose, dict) else None
        if kind not in RECORD_KINDS:
            raise JournalError(
                f"{where} is not a journal record (a JSON object whose 'record' is one of "
                f"{', '.join(RECORD_KINDS)})"
            ) from None
        if kind == "header" and loose.get("version") not in READ_VERSIONS:
            raise _version_error(where, loose.get("version")) from None
        raise JournalError(f"{where}: {kind} record: {cut(str(exc), 2 * SHOWN_LIMIT)}") from None
    return record


def read_records(path: Path) -> tuple[list[JournalRecord], int]:
    """The records of a journal file and the byte length of its intact part.

    A last line without its newline, or one that is not valid JSON, is a torn write and is left
    out (its bytes lie beyond the returned length). Any other bad line is an error.

    The file is opened without blocking (a FIFO does not wedge the reader) and must be a
    regular file of at most `MAX_JOURNAL_BYTES`, checked on the open file before reading.

    Raises:
        JournalError: the file is missing or unreadable, not a regular file, bigger than
            `MAX_JOURNAL_BYTES`, or a line other than the last is not JSON, or a line is no
            journal record or a record with a missing or mistyped field (the message names the
            line and the field).
    """
    data = _read_bounded(path)
    records: list[JournalRecord] = []
    good = 0
    lines = data.split(b"\n")
    # After the last newline comes "" (an intact file) or the bytes of a torn write.
    complete, tail = lines[:-1], lines[-1]
    for number, line in enumerate(complete, start=1):
        final = number == len(complete) and not tail
        try:
            record = _decode(line, f"{path} line {number}")
        except msgspec.DecodeError as exc:
            if final:
                break  # a torn write that reached its newline (e.g. zero-filled blocks)
            raise JournalError(
                f"{path} line {number} is not JSON ({exc}); only the last line may be torn, so "
                f"the file is damaged"
            ) from None
        records.append(record)
        good += len(line) + 1
    return records, good


def _journal_error(path: Path, refused: FileRefused) -> JournalError:
    """`refused` (`mesh.regular_file`) worded for the journal at `path`."""
    if refused.problem == "cannot_open":
        return JournalError(f"cannot read journal {path}: {refused.detail}")
    if refused.problem == "not_regular":
        return JournalError(f"journal {path} is not a regular file ({refused.detail})")
    if refused.problem == "too_large":
        return JournalError(
            f"journal {path} holds {refused.size} bytes, more than a journal may "
            f"({MAX_JOURNAL_BYTES} bytes)"
        )
    return JournalError(f"journal {path} holds more than {MAX_JOURNAL_BYTES} bytes")


def _open_regular(path: Path, flags: int) -> int:
    """A descriptor of the regular file `path`, opened with `flags` and O_NONBLOCK (so that a
    FIFO or a device cannot block the open) and checked on the open file.

    Raises:
        JournalError: it cannot be opened, is not a regular file or is bigger than
            `MAX_JOURNAL_BYTES`.
    """
    try:
        return open_regular(path, flags, MAX_JOURNAL_BYTES)
    except FileRefused as refused:
        raise _journal_error(path, refused) from None


def _read_bounded(path: Path) -> bytes:
    """The bytes of the regular file `path`, at most `MAX_JOURNAL_BYTES` (`_open_regular`)."""
    try:
        return read_regular(path, MAX_JOURNAL_BYTES)
    except FileRefused as refused:
        raise _journal_error(path, refused) from None


def check_invariants(records: Sequence[JournalRecord], *, allow_open: bool = False) -> list[str]:
    """Every breach of a journal's rollout invariants (empty when it keeps them all): attempt
    indices proposed 1, 2, … once each; each proposed attempt ended by exactly one `done` or
    `aborted` record, after it (the last may stay open with `allow_open`, e.g. while running or
    after a crash); done rollout numbers 1, 2, … in order.

    Args:
        records: the journal's records in order (`read_records`), header first.
        allow_open: accept a last proposed attempt that has not ended yet.
    """
    violations: list[str] = []
    proposed: list[int] = []
    ended: dict[int, str] = {}
    rollouts: list[int] = []
    for number, record in enumerate(records, start=1):
        if isinstance(record, ProposedRecord):
            if record.index in proposed:
                violations.append(f"record {number}: attempt {record.index} proposed again")
            proposed.append(record.index)
        elif isinstance(record, DoneRecord | AbortedRecord):
            kind, index = record.kind, record.index
            if index not in proposed:
                violations.append(f"record {number}: {kind} for attempt {index}, never proposed")
            elif index in ended:
                violations.append(
                    f"record {number}: attempt {index} {kind} after it was {ended[index]} already"
                )
            ended.setdefault(index, kind)
            if isinstance(record, DoneRecord):
                rollouts.append(record.rollout)
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


@dataclass(frozen=True)
class Checkpoint:
    """A learner state a journal holds: after `rollout` done rollouts, whole (the header's, a
    version 1 done record's) or without its history (a checkpoint record's); `where` names it."""

    rollout: int
    state: dict[str, Any]
    where: str


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
        checkpoints: the learner states the journal holds, oldest first (the header's first).
        n_done, n_aborted: how many done and aborted records it holds.

    A session's own journal (`Journal`) calls `forget_history` once the learner is built:
    from then on `done`, `aborted`, `records` and `checkpoints` keep only their last item, so
    that a running session's memory does not grow with its length (the file holds them all).
    """

    header: HeaderRecord
    done: list[DoneRecord] = field(default_factory=list)
    aborted: list[AbortedRecord] = field(default_factory=list)
    last_index: int = 0
    open: ProposedRecord | None = None
    retry_theta: list[float] | None = None
    aborts_in_row: dict[str, int] = field(default_factory=dict)
    ended: EndRecord | None = None
    records: list[JournalRecord] = field(default_factory=list)
    checkpoints: list[Checkpoint] = field(default_factory=list)
    n_done: int = 0
    n_aborted: int = 0
    _first_hit: int | None = None
    _best: DoneRecord | None = None
    _keep: bool = True

    @property
    def session(self) -> str:
        """The session id."""
        return self.header.session

    @property
    def checkpointed(self) -> int:
        """Done rollouts the latest checkpoint follows (0: only the header's state)."""
        return self.checkpoints[-1].rollout if self.checkpoints else 0

    @classmethod
    def from_records(cls, records: Sequence[JournalRecord], where: str = "journal") -> JournalState:
        """Replay records (the first must be the header).

        Raises:
            JournalError: a record breaks the journal's rules; the message names it.
        """
        if not records:
            raise JournalError(f"{where} is empty: no header record")
        header = cls._check_header(records[0], where)
        state = cls(header=header)
        state.records.append(header)
        state.checkpoints.append(Checkpoint(0, header.learner_state, f"{where} header"))
        for number, record in enumerate(records[1:], start=2):
            state.apply(record, f"{where} record {number}")
        return state

    @staticmethod
    def _check_header(header: JournalRecord, where: str) -> HeaderRecord:
        if not isinstance(header, HeaderRecord):
            raise JournalError(f"{where} does not start with a header record")
        if header.version not in READ_VERSIONS:
            raise _version_error(where, header.version)
        return header

    def apply(self, record: JournalRecord, where: str = "record") -> None:
        """Check `record` against what came before (`check`) and take it in.

        Raises:
            JournalError: it breaks a rule; the state is unchanged.
        """
        self.check(record, where)
        if isinstance(record, ProposedRecord):
            self.open = record
            self.last_index = record.index
        elif isinstance(record, DoneRecord):
            self.done.append(record)
            self.n_done += 1
            self.retry_theta = None
            self.aborts_in_row = {}
            self.open = None
            if record.hit and self._first_hit is None:
                self._first_hit = record.rollout
            if self._best is None or record.distance_m < self._best.distance_m:
                self._best = record
            if not isinstance(record.learner_state, UnsetType):  # version 1: every done record
                self.checkpoints.append(Checkpoint(record.rollout, record.learner_state, where))
        elif isinstance(record, CheckpointRecord):
            self.checkpoints.append(Checkpoint(record.rollout, record.learner_state, where))
        elif isinstance(record, AbortedRecord):
            self.retry_theta = list(record.retry_theta)
            self.aborted.append(record)
            self.n_aborted += 1
            self.aborts_in_row[record.code] = self.aborts_in_row.get(record.code, 0) + 1
            self.open = None
        elif isinstance(record, ResumedRecord):
            self.aborts_in_row = {}  # a deliberate restart gets a fresh count of aborts
        elif isinstance(record, EndRecord):
            self.ended = record
        self.records.append(record)
        if not self._keep:
            self._trim()

    def forget_history(self) -> None:
        """Keep only the last done, aborted and checkpoint records and the last record from now
        on (the counts, the best rollout and the first hit stay whole)."""
        self._keep = False
        self._trim()

    def _trim(self) -> None:
        for items in (self.done, self.aborted, self.records, self.checkpoints):
            del items[:-1]

    def check(self, record: JournalRecord, where: str = "record") -> None:
        """Whether `record` may come next; changes nothing. Its fields' types are msgspec's to
        check (`read_records`, `Journal.append`); these are the rules between records.

        Raises:
            JournalError: it breaks a rule (wrong session, index out of order, a rollout
                finished twice, anything after the end …); the message names it.
        """
        if not isinstance(record, SessionRecord):
            raise JournalError(
                f"{where}: kind {record.kind!r} is not one of {', '.join(RECORD_KINDS[1:])}"
            )
        kind = record.kind
        if record.session != self.session:
            raise JournalError(
                f"{where} belongs to session {record.session!r}, not {self.session!r}"
            )
        if self.ended is not None:
            raise JournalError(f"{where}: {kind} after the session's end record")
        if isinstance(record, ProposedRecord):
            index = record.index
            if self.open is not None:
                raise JournalError(
                    f"{where}: rollout {index} proposed while rollout {self.open.index} is "
                    f"still open"
                )
            if index != self.last_index + 1:
                raise JournalError(
                    f"{where}: rollout {index} proposed after rollout {self.last_index}; "
                    f"expected {self.last_index + 1}"
                )
        elif isinstance(record, DoneRecord | AbortedRecord):
            index, theta = record.index, record.theta
            if self.open is None or self.open.index != index:
                opened = None if self.open is None else self.open.index
                raise JournalError(
                    f"{where}: {kind} for rollout {index}, but the open rollout is {opened}"
                )
            if theta != self.open.theta:
                raise JournalError(
                    f"{where}: rollout {index} {kind} with θ {theta}, proposed {self.open.theta}"
                )
            if isinstance(record, DoneRecord) and record.rollout != self.n_done + 1:
                raise JournalError(
                    f"{where}: done rollout number {record.rollout!r}, expected {self.n_done + 1}"
                )
        elif isinstance(record, CheckpointRecord):
            if self.open is not None:
                raise JournalError(f"{where}: checkpoint while rollout {self.open.index} is open")
            if record.rollout != self.n_done:
                raise JournalError(
                    f"{where}: checkpoint after rollout {record.rollout}, but {self.n_done} "
                    f"are done"
                )
        elif isinstance(record, EndRecord) and self.open is not None:
            raise JournalError(f"{where}: end while rollout {self.open.index} is open")

    @property
    def best(self) -> DoneRecord | None:
        """The done rollout with the smallest ‖r‖ (the first of equals), or None."""
        return self._best

    def hit_at(self) -> int | None:
        """The done-rollout number (1-based) of the first hit, or None."""
        return self._first_hit

    def summary(self) -> dict[str, Any]:
        """Counts and results so far, as plain values (distances in m)."""
        last = self.done[-1] if self.done else None
        return {
            "session": self.session,
            "algorithm": self.header.algorithm,
            "seed": self.header.seed,
            "budget": self.header.rollouts,
            "rollouts": self.n_done,
            "aborted": self.n_aborted,
            "hit_at": self.hit_at(),
            "final_distance_m": None if last is None else last.distance_m,
            "best_distance_m": None if self._best is None else self._best.distance_m,
            "ended": None if self.ended is None else self.ended.reason,
        }


class Journal:
    """Appends records to one session's journal file, durably (each written whole, then fsynced).

    Build one with `create` (a new session) or `resume` (an existing file); `state` is kept in
    step with the file, and a record that would break the journal's rules is refused before
    anything is written.
    """

    def __init__(self, path: Path, state: JournalState) -> None:
        self.path = path
        self.state = state
        fd = _open_regular(path, os.O_WRONLY | os.O_APPEND)
        # Unbuffered: a failed write leaves nothing behind to be flushed (and fail) again.
        self._file = os.fdopen(fd, "ab", buffering=0)  # kept open for the session
        self._size = os.fstat(fd).st_size  # bytes, kept within MAX_JOURNAL_BYTES

    @classmethod
    def create(cls, directory: Path, header: HeaderRecord) -> Journal:
        """Start `directory/journal.jsonl` with `header` (its `version` and `created` are filled
        in).

        Raises:
            JournalError: the journal exists already, or a field of the header is missing or
                of the wrong type.
        """
        path = directory / JOURNAL_NAME
        header = msgspec.structs.replace(
            header,
            version=JOURNAL_VERSION,
            created=time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        )
        line = encode_record(header)
        state = JournalState.from_records([_decode(line, f"{path} header")], str(path))
        directory.mkdir(parents=True, exist_ok=True)
        try:
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
        except FileExistsError:
            raise JournalError(
                f"journal {path} exists already; resume it or choose another session id"
            ) from None
        try:
            os.write(fd, line)
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
                f"journal {path} belongs to session {shown(state.session)}, not {shown(session)}"
            )
        if state.ended is not None:
            raise JournalError(
                f"session {state.session!r} in {path} has ended ({state.ended.reason}); "
                f"start a new session instead"
            )
        journal = cls(path, state)
        if journal._size > good:
            os.ftruncate(journal._file.fileno(), good)
            os.fsync(journal._file.fileno())
            journal._size = good
        return journal

    def append(self, record: JournalRecord) -> JournalRecord:
        """Check, write and fsync one record; returns it as written (stamped with this
        journal's `session` and the wall time `t`, s since the epoch). `state` takes the record
        in only once it is durable, so it never counts a record the file lacks.

        Raises:
            JournalError: a field is missing or of the wrong type, the record breaks the
                journal's rules, or it would make the journal bigger than `MAX_JOURNAL_BYTES`
                (nothing is written); or the write or fsync failed (e.g. a full disk; the
                message gives the system's reason): the journal is closed then, its file
                possibly ending in a torn record that `resume` cuts off.
        """
        where = f"new {record.kind} record"
        if isinstance(record, SessionRecord):
            record = msgspec.structs.replace(record, session=self.state.session, t=time.time())
        line = encode_record(record)
        record = _decode(line, where)  # what is written is what a reader will decode
        if self._file.closed:
            raise JournalError(f"journal {self.path} is closed; resume it to append")
        self.state.check(record, where)  # nothing is written when it breaks a rule
        if self._size + len(line) > MAX_JOURNAL_BYTES:
            raise JournalError(
                f"journal {self.path} would pass {MAX_JOURNAL_BYTES} bytes, the most a journal "
                f"may hold ({MAX_ROLLOUTS} rollouts with room for aborted attempts); start a "
                f"new session"
            )
        try:
            _write_all(self._file, line)
            os.fsync(self._file.fileno())
            self._size += len(line)
        except OSError as exc:
            self.close()
            raise JournalError(
                f"cannot write to journal {self.path}: {exc.strerror or exc}"
            ) from None
        self.state.apply(record, where)
        return record

    @property
    def size(self) -> int:
        """The journal's bytes so far."""
        return self._size

    def room_for(self, rollouts: int) -> None:
        """Check, before a session (re)starts, that `rollouts` more done rollouts fit in the
        journal at `ROLLOUT_BYTES` each.

        Raises:
            JournalError: they would not; nothing is written.
        """
        need = self._size + rollouts * ROLLOUT_BYTES
        if need > MAX_JOURNAL_BYTES:
            raise JournalError(
                f"journal {self.path} holds {self._size} bytes; {rollouts} more rollouts would "
                f"take it to about {need}, past the {MAX_JOURNAL_BYTES} a journal may hold; "
                f"start a new session"
            )

    def close(self) -> None:
        """Close the file (idempotent; never raises: every record written was fsynced)."""
        if not self._file.closed:
            with contextlib.suppress(OSError):
                self._file.close()

    def __enter__(self) -> Journal:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _write_all(file: io.RawIOBase, data: bytes) -> None:
    """Write every byte of `data` to an unbuffered file (a write may take only part of it).

    Raises:
        OSError: the system refused a write (e.g. ENOSPC); the bytes before it stay written.
    """
    view = memoryview(data)
    while view:
        written = file.write(view)
        if not written:
            raise OSError(errno.EIO, f"a write took none of {len(view)} bytes")
        view = view[written:]


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
