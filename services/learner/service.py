"""`archery learner`: runs learning sessions over the mesh, one rollout at a time, journaled.

Ports (ROBOT = the robot prefix):

* `ROBOT/learner/rpc:i`:
  - `start {algo?, rollouts?, seed?, until_hit?, scenario?: {theta0, bounds, hit_radius, reset},
    options?, from_journal?: SESSION}` starts a session (see `config.SessionConfig`; from
    another session's learned model with `from_journal`), or `start {resume: PATH, session?:
    ID}` continues the one journaled at PATH (a journal or its directory). Every path lies
    inside RUNS (a relative one is taken from there; `services.learner.runs_folder`). Replies
    at once with the session's status (its id, journal path); refused with code
    `service_missing` when the robot, camera, detector or controller is not alive, `busy`
    while a session runs (the message says how to follow it: `archery learn --attach ID`),
    `bad_request` or `bad_journal` for bad arguments; nothing journaled
    is touched then.
  - `stop` ends the running session after its current rollout (resumable); `status` → the
    running or last session's status (state idle, starting, waiting, running, reporting,
    finished, stopped or failed).
* `ROBOT/learner/rollout:o` (events): a `Rollout` per journal record of a rollout (proposed,
  done, aborted), in order.

With `--fleet P2,P3`, one learner process serves the same ports under each of those robot
prefixes too, and runs a session on each robot at once.

Sessions go to `RUNS/<session>/journal.jsonl`; when one ends, `report.png` (and `hit.png`, the
frame of the latest hit with the detection drawn) are written beside it.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import threading

from mesh.node import Node
from mesh.service import service_main
from protocol.robotspec import LEARNER
from services.learner.config import LearnerServiceConfig, add_arguments, make_config
from services.learner.handlers import LearnerHandlers

__all__ = ["main", "run"]

log = logging.getLogger("archery.learner")


def run(config: LearnerServiceConfig, stop: threading.Event) -> None:
    """Serve the learner until `stop` is set: for its robot and each robot of `--fleet`, a
    node of that robot with its own verbs and session thread (so one session per robot runs
    at once)."""
    with contextlib.ExitStack() as stack:
        served = []
        for robot in config.robots():
            node = stack.enter_context(Node(LEARNER, dataclasses.replace(config.net, robot=robot)))
            handlers = LearnerHandlers(config, node)
            stack.callback(handlers.close)
            node.serve(node.keys.learner_rpc(), handlers.verbs())
            served.append(node)
        for node in served:
            node.ready()
        log.info("learner ready for %s: runs in %s", ", ".join(config.robots()), config.runs)
        stop.wait()


def main(argv: list[str] | None = None) -> int:
    """`archery learner [flags]`: serve until SIGINT/SIGTERM (exit status 0)."""
    return service_main(
        argv,
        prog=LEARNER,
        description="learning sessions over the mesh (PoWER, ARCHER, baselines), journaled",
        add_arguments=add_arguments,
        make_config=make_config,
        run=run,
    )
