"""SIGKILL drills: a service crashes mid-session.

* `kill-SERVICE` (robot, camera, detector, controller): `up`'s supervisor restarts it and the
  learner goes on with the same session by itself. Judged: the service runs as a new process,
  every other child is the process it was, the journal has no `resumed` record (the same
  session went on) and rollouts are done after the service's return.
* `kill-learner`: the supervisor restarts the learner and the session is resumed with the
  real client, `archery learn --resume JOURNAL`, which must follow it to its budget (exit 0).
* `kill-learner-xN`: the learner is SIGKILLed N times at random points (a seeded delay after a
  rollout, so in any step of the next ones: posture, shot, measurement, journal writes), and
  resumed each time (the learner's `start {resume}`, what `archery learn --resume` sends).
"""

from __future__ import annotations

import json
import random
import subprocess
import sys
import threading
import time

from archery.apps.drills.faults import (
    AFTER,
    finish,
    noticed,
    recovered,
    running_session,
    same_processes,
)
from archery.apps.drills.mesh import WAIT, DrillMesh
from archery.apps.drills.verdict import DrillResult
from archery.protocol.journal_records import ResumedRecord

__all__ = ["kill_learner", "kill_learner_repeatedly", "kill_service"]


def kill_service(mesh: DrillMesh, service: str, seed: int) -> DrillResult:
    """SIGKILL `service` (not the learner) mid-session; its supervised restart."""
    run = running_session(mesh, seed)
    before = mesh.pids()
    fault = time.time()
    mesh.launcher.kill(service)
    mesh.wait_new_process(service, before[service])
    assert mesh.tokens is not None
    back = mesh.tokens.wait(service, True, fault)
    mesh.wait_done(run, AFTER, after=back)
    detect, learner = noticed(mesh, run, service, fault)
    recover = recovered(mesh, run, back)
    problems = same_processes(before, mesh.pids(), [service])
    result = finish(
        f"kill-{service}",
        mesh,
        [run],
        problems,
        detect_s=detect,
        recover_s=recover,
        details={"down_s": back - fault, "learner_detect_s": learner},
    )
    if any(isinstance(r, ResumedRecord) for r in run.records()):
        result.passed = False
        result.notes.insert(0, "the session was resumed, not continued")
    result.notes.append(f"back {back - fault:.1f} s after the kill")
    if learner is not None:
        result.notes.append(f"learner waited for it after {learner:.2f} s")
    return result


def kill_learner(mesh: DrillMesh, seed: int, rollouts: int = 30) -> DrillResult:
    """SIGKILL the learner mid-session; restarted, the session resumed by `archery learn
    --resume`, which follows it to its budget."""
    started = time.time()
    run = mesh.start_session(seed, rollouts=rollouts)
    mesh.wait_done(run, 2, after=started)
    before = mesh.pids()
    fault = time.time()
    mesh.launcher.kill("learner")
    mesh.wait_new_process("learner", before["learner"])
    assert mesh.tokens is not None
    back = mesh.tokens.wait("learner", True, fault)
    launcher = mesh.launcher
    net = ["--connect", launcher.endpoint, "--robot", launcher.net.robot]
    argv = [sys.executable, "-m", "archery.apps.cli", "learn", *net, "--resume", str(run.journal)]
    problems = []
    try:
        client = subprocess.run(
            [*argv, "--quiet"], capture_output=True, text=True, timeout=WAIT, env=launcher.env
        )
        lines = client.stdout.strip().splitlines()
        line = json.loads(lines[-1]) if lines else {}
        if client.returncode != 0 or line.get("rollouts") != rollouts:
            problems.append(
                f"archery learn --resume: exit {client.returncode}, {line or client.stderr[-300:]}"
            )
    except subprocess.TimeoutExpired:
        problems.append(f"archery learn --resume did not end within {WAIT:g} s")
    gone = mesh.gone_at("learner", fault)
    problems += same_processes(before, mesh.pids(), ["learner"])
    return finish(
        "kill-learner",
        mesh,
        [run],
        problems,
        expect="finished",
        detect_s=None if gone is None else gone - fault,
        recover_s=recovered(mesh, run, back),
        notes=[f"resumed by archery learn --resume; back {back - fault:.1f} s after the kill"],
        details={"down_s": back - fault},
    )


def kill_learner_repeatedly(mesh: DrillMesh, times: int, seed: int) -> DrillResult:
    """SIGKILL the learner `times` times at seeded random points, resuming the session each
    time; its worst times to detect and recover."""
    rng = random.Random(seed)
    run = running_session(mesh, seed)
    assert mesh.tokens is not None
    detects: list[float] = []
    recovers: list[float] = []
    problems: list[str] = []
    pause = threading.Event()
    for _ in range(times):
        pause.wait(rng.uniform(0.0, 0.3))  # the random point: this far into the next rollouts
        pid = mesh.pids()["learner"]
        fault = time.time()
        mesh.launcher.kill("learner")
        mesh.wait_new_process("learner", pid)
        back = mesh.tokens.wait("learner", True, fault)
        mesh.resume(run)
        mesh.wait_done(run, 1, after=back)
        gone = mesh.gone_at("learner", fault)
        if gone is not None:
            detects.append(gone - fault)
        recover = recovered(mesh, run, back)
        if recover is not None:
            recovers.append(recover)
    mesh.wait_done(run, AFTER, after=time.time())
    resumed = sum(isinstance(r, ResumedRecord) for r in run.records())
    if resumed != times:
        problems.append(f"{resumed} resumed records for {times} kills")
    return finish(
        f"kill-learner-x{times}",
        mesh,
        [run],
        problems,
        detect_s=max(detects) if detects else None,
        recover_s=max(recovers) if len(recovers) == times else None,
        notes=[
            f"{times} kills (seed {seed}), worst times shown; mean recover "
            f"{sum(recovers) / max(1, len(recovers)):.2f} s"
        ],
        details={"detect_s_each": detects, "recover_s_each": recovers},
    )
