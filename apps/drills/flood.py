"""Flood drill (`flood-N`): N messages are published as fast as the network takes them on the
robot's `ROBOT/left_arm/command:i` mid-session: valid JointCommands (the arm's latest measured
position: hold where you are) and invalid ones (another part, a wrong length, names that do
not match, values far beyond the joint limits, bytes that are no message), in a seeded order.

Judged: no child crashed or was restarted, the robot stays alive, and the same session goes on
(rollouts done after the flood; aborted attempts are allowed, lost or duplicated rollouts are
not). No fault is detected; time to recover: from the end of the flood to the next done
rollout.
"""

from __future__ import annotations

import random
import time

import msgspec
import zenoh

from archery.apps.drills.faults import AFTER, finish, recovered, running_session, same_processes
from archery.apps.drills.mesh import DrillMesh
from archery.apps.drills.verdict import DrillResult
from archery.protocol.codec import encode
from archery.protocol.journal_records import AbortedRecord, DoneRecord, ResumedRecord
from archery.protocol.messages import JointCommand, JointState
from archery.protocol.verbs.robot import COUNTERS

__all__ = ["PART", "flood", "flood_drill"]

PART = "left_arm"


def flood(mesh: DrillMesh, count: int, seed: int) -> dict[str, int]:
    """Publish `count` commands on the left arm's command port; how many of each kind."""
    node = mesh.node
    assert node is not None
    keys = node.keys
    state = node.subscribe(keys.state(PART), JointState)
    arm = mesh.until(state.latest, f"a state of {PART}")
    key = keys.command(PART)
    # Blocking: every message reaches the router, however fast they come.
    publisher = node.session.declare_publisher(
        key, congestion_control=zenoh.CongestionControl.BLOCK
    )
    rng = random.Random(seed)
    kinds = {"valid": 0, "wrong_part": 0, "wrong_length": 0, "names": 0, "limits": 0, "junk": 0}
    for _ in range(count):
        kind = rng.choice(list(kinds))
        kinds[kind] += 1
        position = list((state.latest() or arm).position)
        if kind == "valid":
            message = JointCommand(part=PART, position=position)
        elif kind == "wrong_part":
            message = JointCommand(part="right_leg", position=position)
        elif kind == "wrong_length":
            message = JointCommand(part=PART, position=position[:-1])
        elif kind == "names":  # not even constructible: encoded by hand
            fields = msgspec.to_builtins(JointCommand(part=PART, position=position))
            publisher.put(msgspec.msgpack.encode(fields | {"names": ["nope"]}))
            continue
        elif kind == "limits":
            message = JointCommand(part=PART, position=[100.0] * len(position))
        else:
            publisher.put(rng.randbytes(rng.randint(1, 64)))
            continue
        publisher.put(encode(message))
    publisher.undeclare()
    return kinds


def counted(mesh: DrillMesh) -> dict[str, int]:
    """The robot's command counters of the left arm: accepted, rejected, undecodable."""
    assert mesh.node is not None
    reply = mesh.node.call_typed(mesh.node.keys.part_rpc(PART), COUNTERS, timeout=10)
    return {
        "accepted": reply.accepted,
        "rejected": reply.rejected,
        "undecodable": reply.undecodable,
    }


def flood_drill(mesh: DrillMesh, count: int, seed: int) -> DrillResult:
    """Flood the left arm's command port with `count` messages mid-session."""
    run = running_session(mesh, seed)
    before = mesh.pids()
    first = counted(mesh)
    start = time.time()
    kinds = flood(mesh, count, seed)
    end = time.time()
    mesh.wait_done(run, AFTER, after=end)
    problems = same_processes(before, mesh.pids())
    last = counted(mesh)
    seen = {k: last[k] - first[k] for k in last}
    if not any(seen.values()):
        problems.append("the robot counted none of the commands")
    if any(isinstance(r, ResumedRecord) for r in run.records()):
        problems.append("the session was resumed, not continued")
    during = [r for r in run.records() if isinstance(r, DoneRecord) and start < r.t <= end]
    aborted = [r for r in run.records() if isinstance(r, AbortedRecord) and r.t > start]
    rate = count / max(end - start, 1e-9)
    return finish(
        f"flood-{count}",
        mesh,
        [run],
        problems,
        recover_s=recovered(mesh, run, end),
        notes=[
            f"{count} messages in {end - start:.1f} s ({rate:,.0f}/s); {len(during)} rollouts "
            f"done during it, {len(aborted)} attempts aborted since; the robot counted "
            + ", ".join(f"{n} {k}" for k, n in seen.items())
        ],
        details={
            "kinds": kinds,
            "flood_s": end - start,
            "done_during": len(during),
            "robot_counted": seen,
        },
    )
