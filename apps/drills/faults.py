"""Shared steps of the drills that fault a running session: start it, find when the fault was
noticed and when the session went on, stop it and judge it."""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any

from archery.apps.drills.mesh import DrillMesh, SessionRun
from archery.apps.drills.verdict import DrillResult, Evidence, judge
from archery.protocol.journal_records import AbortedRecord

__all__ = ["finish", "noticed", "recovered", "running_session", "same_processes"]

BEFORE = 2  # done rollouts before the fault
AFTER = 3  # done rollouts after the service's return


def running_session(mesh: DrillMesh, seed: int) -> SessionRun:
    """A session started on `mesh`, with `BEFORE` rollouts done."""
    started = time.time()
    run = mesh.start_session(seed)
    mesh.wait_done(run, BEFORE, after=started)
    return run


def noticed(
    mesh: DrillMesh, run: SessionRun, service: str, fault: float
) -> tuple[float | None, float | None]:
    """(time to detect, the learner's own time to detect) of a fault at `fault` (wall s).

    Detected: the first of the service's liveliness token going (the learner's rig watches the
    same tokens and dates the loss by them), the supervisor reporting its exit, the learner's
    status waiting for it, or a `service_lost` abort in the journal. The learner's own: the
    last two only.
    """
    assert mesh.status is not None
    learner = [
        mesh.status.first_waiting(service, fault),
        next(
            (
                r.t
                for r in run.records()
                if isinstance(r, AbortedRecord)
                and r.code == "service_lost"
                and r.t > fault
                and service in r.cause
            ),
            None,
        ),
    ]
    gone = mesh.gone_at(service, fault)
    own = [t for t in learner if t is not None]
    every = own + ([] if gone is None else [gone])
    return (
        min(every) - fault if every else None,
        min(own) - fault if own else None,
    )


def recovered(mesh: DrillMesh, run: SessionRun, back: float) -> float | None:
    """Seconds from `back` (wall s) to the session's next done rollout (None: none yet)."""
    done = mesh.done_after(run, back)
    return done[0].t - back if done else None


def same_processes(
    before: dict[str, int], after: dict[str, int], changed: Sequence[str] = ()
) -> list[str]:
    """Problems: a child other than `changed` runs as another process, or one in `changed`
    does not."""
    problems = [
        f"{name} was restarted (pid {pid} → {after.get(name)})"
        for name, pid in before.items()
        if name not in changed and after.get(name) != pid
    ]
    problems += [f"{name} was not restarted" for name in changed if after.get(name) == before[name]]
    return problems


def finish(
    name: str,
    mesh: DrillMesh,
    runs: Sequence[SessionRun],
    problems: list[str],
    *,
    expect: str = "stopped",
    detect_s: float | None = None,
    recover_s: float | None = None,
    notes: Sequence[str] = (),
    details: dict[str, Any] | None = None,
) -> DrillResult:
    """Stop the last session (unless it ended already), check the mesh and judge the drill."""
    final: dict[str, Any] | None = None
    if runs:
        final = mesh.stop_session(runs[-1]) if expect == "stopped" else mesh.wait_final(runs[-1])
        if final["state"] != expect:
            problems.append(f"session {final['state']}, not {expect}: {final.get('cause', '')}")
    problems += mesh.problems()
    sessions = [Evidence(run.records(), run.published_done()) for run in runs]
    if recover_s is None:
        problems.append("no rollout was done after the fault was over")
    figures = dict(details or {})
    if final is not None:
        figures |= {"rollouts": final.get("rollouts"), "aborted": final.get("aborted")}
    return judge(
        name,
        sessions,
        problems,
        detect_s=detect_s,
        recover_s=recover_s,
        notes=notes,
        details=figures,
    )
