"""A drill's result and its verdict, from the journals of its sessions: pure, no processes.

A drill passes when every session's journal keeps its invariants
(`services.learner.journal.check_invariants`), no rollout was lost or duplicated, and the
drill's own checks (`problems`: the session went on, the right processes were restarted, …)
found nothing wrong.

* Rollouts lost: attempts proposed but never ended (done or aborted), done rollout numbers
  skipped, and rollouts published as done (`learner/rollout:o`) that the journal has not.
* Rollouts duplicated: done records whose attempt index or rollout number an earlier done
  record of the same session had already.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

from archery.protocol.journal_records import (
    AbortedRecord,
    DoneRecord,
    JournalRecord,
    ProposedRecord,
)
from archery.services.learner.journal import check_invariants

__all__ = ["DrillResult", "Evidence", "count_lost_duplicated", "judge"]


@dataclass
class Evidence:
    """One session of a drill: its journal's records and the done attempts it published."""

    records: list[JournalRecord]
    published_done: list[int] = field(default_factory=list)


@dataclass
class DrillResult:
    """One drill's row of the table.

    Attributes:
        name: the drill.
        passed: its verdict.
        detect_s: fault → loss noticed (s), None when nothing was lost or it was not seen.
        recover_s: service back → next done rollout (s), None when there was none.
        lost: rollouts lost (all its sessions).
        duplicated: rollouts duplicated (all its sessions).
        notes: what else is worth knowing, failures first.
        details: extra figures for `--json` (per-kill times, the learner's own detection, …).
    """

    name: str
    passed: bool
    detect_s: float | None = None
    recover_s: float | None = None
    lost: int = 0
    duplicated: int = 0
    notes: list[str] = field(default_factory=list)
    details: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """Plain values (`--json`)."""
        out = asdict(self)
        for key in ("detect_s", "recover_s"):
            if out[key] is not None:
                out[key] = round(out[key], 3)
        return out


def count_lost_duplicated(evidence: Evidence) -> tuple[int, int]:
    """(rollouts lost, rollouts duplicated) of one session."""
    proposed: list[int] = []
    ended: set[int] = set()
    done_indices: set[int] = set()
    numbers: set[int] = set()
    duplicated = 0
    for record in evidence.records:
        if isinstance(record, ProposedRecord):
            proposed.append(record.index)
        elif isinstance(record, DoneRecord | AbortedRecord):
            ended.add(record.index)
        if isinstance(record, DoneRecord):
            if record.index in done_indices or record.rollout in numbers:
                duplicated += 1
            done_indices.add(record.index)
            numbers.add(record.rollout)
    never_ended = len([i for i in dict.fromkeys(proposed) if i not in ended])
    skipped = (max(numbers) - len(numbers)) if numbers else 0
    unjournaled = len(set(evidence.published_done) - done_indices)
    return never_ended + skipped + unjournaled, duplicated


def judge(
    name: str,
    sessions: Sequence[Evidence],
    problems: Sequence[str] = (),
    *,
    detect_s: float | None = None,
    recover_s: float | None = None,
    notes: Sequence[str] = (),
    details: dict[str, Any] | None = None,
) -> DrillResult:
    """The verdict of a drill from its sessions' journals and its own `problems`."""
    lost = duplicated = 0
    breaches: list[str] = []
    for evidence in sessions:
        session_lost, session_duplicated = count_lost_duplicated(evidence)
        lost += session_lost
        duplicated += session_duplicated
        breaches += [f"journal: {v}" for v in check_invariants(evidence.records)]
    if not sessions:
        breaches.append("no session was journaled")
    failures = list(problems) + breaches
    if lost:
        failures.append(f"{lost} rollout(s) lost")
    if duplicated:
        failures.append(f"{duplicated} rollout(s) duplicated")
    return DrillResult(
        name,
        not failures,
        detect_s,
        recover_s,
        lost,
        duplicated,
        [*failures, *notes],
        dict(details or {}),
    )
