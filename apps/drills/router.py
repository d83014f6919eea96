"""Router drills (`router-Ns`): the router of a supervised mesh is SIGKILLed mid-session and
`up`'s supervisor restarts it on the same endpoint after N s (its restart back-off: the outage).

The services, the learner and the drill's own node are Zenoh clients: they reconnect to the new
router by themselves and declare their liveliness tokens again. Judged: no service was
restarted, all five are alive on the new router and the same session goes on by itself (no
`resumed` record). Detected: the supervisor reporting the router's exit. The router's return:
it listens again.
"""

from __future__ import annotations

import dataclasses
import time

from archery.apps.drills.faults import AFTER, finish, recovered, running_session, same_processes
from archery.apps.drills.mesh import WAIT, DrillMesh
from archery.apps.drills.verdict import DrillResult
from archery.apps.up.restart_policy import RestartPolicy
from archery.mesh.router import wait_for_endpoint
from archery.protocol.journal_records import ResumedRecord

__all__ = ["router_outage"]


def router_outage(mesh: DrillMesh, outage: float, seed: int) -> DrillResult:
    """Kill the router mid-session; restarted `outage` s later by the supervisor."""
    launcher = mesh.launcher
    original = launcher.mesh
    policy = RestartPolicy(budget=100, backoff=outage, backoff_max=outage)
    launcher.mesh = dataclasses.replace(
        original, router=dataclasses.replace(original.router, restart=policy)
    )
    try:
        run = running_session(mesh, seed)
        before = mesh.pids()
        fault = time.time()
        launcher.kill("router")
        mesh.wait_new_process("router", before["router"], timeout=outage + WAIT)
        wait_for_endpoint(launcher.endpoint, WAIT)
        back = time.time()
        alive = mesh.wait_alive()
        mesh.wait_done(run, AFTER, after=back)
    finally:
        launcher.mesh = original
    noticed = mesh.supervisor_noticed("router", fault)
    problems = same_processes(before, mesh.pids(), ["router"])
    if any(isinstance(r, ResumedRecord) for r in run.records()):
        problems.append("the session was resumed, not continued")
    assert mesh.status is not None
    waited = next((t for t, s, _ in mesh.status.seen if t > back and s == "waiting"), None)
    notes = [
        f"router down {back - fault:.1f} s; all five alive {alive - back:.1f} s after it "
        f"listened again"
    ]
    if waited is not None:
        notes.append("the learner waited for its services")
    return finish(
        f"router-{outage:g}s",
        mesh,
        [run],
        problems,
        detect_s=None if noticed is None else noticed - fault,
        recover_s=recovered(mesh, run, back),
        notes=notes,
        details={"outage_s": back - fault, "alive_again_s": alive - back},
    )
