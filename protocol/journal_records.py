"""The records of a learning session's journal: one tagged msgspec Struct per kind.

A journal (`services.learner.journal`) is JSON lines, one record a line; the record's kind is
its `record` field (the tag), so a line reads `{"record":"proposed","session":…,"t":…,…}`. The
same Structs are what the learner builds, what the journal encodes and decodes, and (proposed,
done and aborted) what `protocol.messages.Rollout` carries on `learner/rollout:o`. A session
writes a header, then per attempt proposed and done or aborted, checkpoints, and resumed,
stopped or end; each record's class says what it holds. Field order is the order of the lines
on disk; a field a line may lack is `UNSET` when absent, so a record encodes back to its line.
Which records may follow which (index order, one open attempt, the same θ) is the journal's
business: these types say only what each record holds.
"""

from __future__ import annotations

from typing import Annotated, Any

import msgspec
from msgspec import UNSET, Meta, UnsetType

__all__ = [
    "CHECKPOINT_EVERY",
    "JOURNAL_VERSION",
    "READ_VERSIONS",
    "RECORD_KINDS",
    "RECORD_TYPES",
    "AbortedRecord",
    "CheckpointRecord",
    "DoneRecord",
    "EndRecord",
    "HeaderRecord",
    "JournalRecord",
    "ProposedRecord",
    "ResumedRecord",
    "RolloutRecord",
    "SessionRecord",
    "StoppedRecord",
]

JOURNAL_VERSION = 2  # what this code writes
READ_VERSIONS = (1, 2)  # what it reads and resumes (1: a learner state in every done record)
CHECKPOINT_EVERY = 100  # done rollouts between two checkpoints of a session

Index = Annotated[int, Meta(ge=1, description="attempt or rollout number, 1-based")]
Theta = Annotated[list[float], Meta(min_length=1, description="m")]
Vector = Annotated[list[float], Meta(description="m")]


class JournalRecord(msgspec.Struct, frozen=True, kw_only=True, tag_field="record"):
    """Base of every journal record; `record` (the tag) names its kind."""

    @property
    def kind(self) -> str:
        """The record's kind: header, proposed, done, aborted, checkpoint, resumed, stopped or
        end."""
        return str(type(self).__struct_config__.tag)


class HeaderRecord(JournalRecord, frozen=True, kw_only=True, tag="header"):
    """The first line of a journal, written once: what the session is, and its learner before
    any proposal.

    `version` and `created` (UTC, ISO 8601) are filled in by the journal that writes it.
    `rollouts` is the budget of done rollouts, `options` the learner's options, `config` the
    rest of the session settings, `controller_box` the controller's θ box and `learner_state`
    the learner before its first proposal. `from` is there when the session started from
    another session's learned model; `rig` holds what replaying a shot needs: the robot's world
    parameters, its shot count before the session and the controller's trajectory time (s).
    """

    version: int = JOURNAL_VERSION
    created: str = ""
    session: str
    algorithm: str
    seed: int
    rollouts: Annotated[int, Meta(description="budget of done rollouts")]
    options: dict[str, Any]
    config: dict[str, Any]
    controller_box: dict[str, Any] | UnsetType = UNSET  # {"low", "high"} (m)
    learner_state: dict[str, Any]
    from_: dict[str, str] | UnsetType = msgspec.field(default=UNSET, name="from")
    rig: dict[str, Any] | UnsetType = UNSET  # {"world", "shot", "traj_time"}: to replay a shot


class SessionRecord(JournalRecord, frozen=True, kw_only=True):
    """Base of every record after the header: its `session` id and wall time `t` (s since the
    epoch), both stamped by the journal when it appends the record."""

    session: str = ""
    t: float = 0.0


class ProposedRecord(SessionRecord, frozen=True, kw_only=True, tag="proposed"):
    """Attempt `index` is about to run θ (m)."""

    index: Index
    theta: Theta


class DoneRecord(SessionRecord, frozen=True, kw_only=True, tag="done"):
    """Attempt `index` was measured and the learner told: done rollout number `rollout`
    (1-based, done rollouts only).

    Attributes:
        theta: θ proposed and run (m); theta_measured: θ the controller reached (m);
            theta_launched: θ the arrow was launched with (m, the robot's release reply;
            absent from journals written before it was recorded, or when the rig did not
            tell it).
        r_m: the measured r (m) on the target plane; ret: the return R = exp(−‖r‖/s).
        distance_m: ‖r‖ (m); hit: ‖r‖ below the session's hit radius.
        shot, outcome: the robot's shot number and what it says of the shot.
        truth_r_m, truth_distance_m: the robot's ground-truth r and ‖r‖ (m), for plots only.
        detection: the detector's reply (plain data); timing: the rollout's steps (s).
        learner_state: version 1 journals only: the learner right after it was told (left out
            of a published record); version 2 writes checkpoints instead.
    """

    index: Index
    rollout: Index
    theta: Theta
    theta_measured: Vector | None = None
    theta_launched: Vector | UnsetType = UNSET
    r_m: Theta
    ret: float | None = None
    distance_m: Annotated[float, Meta(ge=0, description="m")]
    hit: bool
    shot: int | None = None
    outcome: str | None = None
    truth_r_m: Vector | None = None
    truth_distance_m: Annotated[float, Meta(ge=0, description="m")] | None = None
    detection: dict[str, Any] | None = None
    timing: dict[str, float] | None = None
    learner_state: dict[str, Any] | UnsetType = UNSET


class AbortedRecord(SessionRecord, frozen=True, kw_only=True, tag="aborted"):
    """Attempt `index` ended without a measurement (the learner was not told): why (`code`, a
    machine-readable word such as no_arrow or service_lost, and `cause`), and the θ (m) the
    next attempt runs. A detector's refusal keeps the ground truth (m) and its reply."""

    index: Index
    theta: Theta
    code: Annotated[str, Meta(min_length=1)]
    cause: str
    retry_theta: Theta
    truth_r_m: Vector | UnsetType | None = UNSET
    detection: dict[str, Any] | UnsetType = UNSET

    def note(self) -> str:
        """ "[code] cause", as progress lines show an aborted attempt."""
        return f"[{self.code}] {self.cause}"


class CheckpointRecord(SessionRecord, frozen=True, kw_only=True, tag="checkpoint"):
    """The learner's state after `rollout` done rollouts (`Learner.checkpoint_state`: its
    history, the θ and r of the done records before it, left out and rebuilt from them; its
    `told` counts them). Written every `CHECKPOINT_EVERY` done rollouts and when the session
    stops or ends, so no record grows with the session (version 1 journals kept the whole
    state in each done record instead)."""

    rollout: Annotated[int, Meta(ge=0)]
    learner_state: dict[str, Any]


class ResumedRecord(SessionRecord, frozen=True, kw_only=True, tag="resumed"):
    """The session was continued from its journal after attempt `after` (0: before any);
    `skipped` names checkpoints that could not be restored (the state was rebuilt from an
    earlier one)."""

    after: Annotated[int, Meta(ge=0)]
    skipped: str | UnsetType = UNSET


class StoppedRecord(SessionRecord, frozen=True, kw_only=True, tag="stopped"):
    """The session paused, resumable: `reason` (stop requested, failed) and, when it failed,
    the `cause`. A session that is over ends with an `EndRecord` instead."""

    reason: str
    cause: str | UnsetType = UNSET


class EndRecord(SessionRecord, frozen=True, kw_only=True, tag="end"):
    """The session is over: `reason` (hit, budget) and its summary (counts, distances in m:
    `services.learner.journal.JournalState.summary`)."""

    reason: str
    summary: dict[str, Any]


RECORD_TYPES: tuple[type[JournalRecord], ...] = (
    HeaderRecord,
    ProposedRecord,
    DoneRecord,
    AbortedRecord,
    CheckpointRecord,
    ResumedRecord,
    StoppedRecord,
    EndRecord,
)
RECORD_KINDS: tuple[str, ...] = tuple(str(t.__struct_config__.tag) for t in RECORD_TYPES)

RolloutRecord = ProposedRecord | DoneRecord | AbortedRecord
"""The records of one attempt, the ones `Rollout` messages carry."""
