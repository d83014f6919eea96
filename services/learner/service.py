"""`archery learner`: runs learning sessions over the mesh, one rollout at a time, journaled.

It serves `ROBOT/learner/rpc:i` (`start`, `stop`, `status`: `services.learner.handlers`) and
publishes each journal record of a rollout on `ROBOT/learner/rollout:o`; docs/learning.md
tells the verbs. With `--fleet P2,P3`, one learner process serves the same
ports under each of those robot prefixes too, and runs a session on each robot at once.
Sessions go to `RUNS/<session>/journal.jsonl`; when one ends, `report.png` (and `hit.png`, the
frame of the latest hit with the detection drawn) are written beside it.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import threading

from archery.mesh.node import Node
from archery.mesh.service import service_main
from archery.mesh.signals import wait_for_stop
from archery.protocol.robotspec import LEARNER
from archery.services.learner.config import LearnerServiceConfig, add_arguments, make_config
from archery.services.learner.handlers import LearnerHandlers

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
        wait_for_stop(stop)


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
