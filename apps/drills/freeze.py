"""SIGSTOP drills (`freeze-SERVICE`): a service is frozen beyond the Zenoh lease (10 s) for
`FREEZE` s mid-session, then continued with SIGCONT.

The router drops the frozen process's session once its lease expires, so its liveliness token
goes and the learner waits for it; after SIGCONT the process reconnects by itself. Judged: the
token went while frozen, came back after SIGCONT, the session went on by itself (no `resumed`
record) and no child was restarted. The service's return is its token coming back.
"""

from __future__ import annotations

import os
import signal
import threading
import time

from archery.apps.drills import faults
from archery.apps.drills.mesh import DrillMesh
from archery.apps.drills.verdict import DrillResult
from archery.protocol.journal_records import ResumedRecord

__all__ = ["FREEZE", "LEASE", "freeze_service"]

LEASE = 10.0  # s: Zenoh's default lease
FREEZE = 12.0  # s: how long a service stays frozen


def freeze_service(mesh: DrillMesh, service: str, seed: int, hold: float = FREEZE) -> DrillResult:
    """SIGSTOP `service` for `hold` s mid-session, then SIGCONT."""
    run = faults.running_session(mesh, seed)
    before = mesh.pids()
    pid = before[service]
    fault = time.time()
    os.kill(pid, signal.SIGSTOP)
    try:
        threading.Event().wait(hold)  # the outage itself, deliberately this long
    finally:
        os.kill(pid, signal.SIGCONT)
    cont = time.time()
    assert mesh.tokens is not None
    problems: list[str] = []
    went = mesh.tokens.first(service, False, fault)
    if went is None or went > cont:
        problems.append(f"{service}'s token did not go while it was frozen")
    back = mesh.tokens.wait(service, True, max(cont, went or fault))
    mesh.wait_done(run, faults.AFTER, after=back)
    detect, learner = faults.noticed(mesh, run, service, fault)
    problems += faults.same_processes(before, mesh.pids())
    if any(isinstance(r, ResumedRecord) for r in run.records()):
        problems.append("the session was resumed, not continued")
    notes = [f"frozen {cont - fault:.1f} s; token back {back - cont:.1f} s after SIGCONT"]
    if learner is not None:
        notes.append(f"learner waited for it after {learner:.2f} s")
    return faults.finish(
        f"freeze-{service}",
        mesh,
        [run],
        problems,
        detect_s=detect,
        recover_s=faults.recovered(mesh, run, back),
        notes=notes,
        details={"learner_detect_s": learner, "token_back_after_cont_s": back - cont},
    )
