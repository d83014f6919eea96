"""What the benchmarks of learning sessions on the MuJoCo iCub share: a whole mesh on a free
loopback port with a client node following the learner's rollouts, and a progress bar."""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from archery.apps.progress import progress_bar
from archery.apps.up.launch_config import SERVICES
from archery.apps.up.launcher import Launcher
from archery.mesh.node import Node
from archery.mesh.router import free_tcp_endpoint
from archery.mesh.subscription import Subscription
from archery.protocol.messages import Rollout

__all__ = ["learning_mesh", "progress_bar"]


@contextmanager
def learning_mesh(out: Path) -> Iterator[tuple[Node, Subscription[Rollout]]]:
    """A router and the five services (logs under `out/logs`, the learner's sessions under
    `out`), all alive; yields a client node and its FIFO subscription to the learner's
    `Rollout` stream. Everything is stopped when the block ends."""
    os.environ.setdefault("MUJOCO_GL", "egl")
    launcher = Launcher(
        free_tcp_endpoint(), "bench", out / "logs", {"learner": ["--runs", str(out)]}
    )
    launcher.up(180)
    try:
        with Node(None, launcher.net) as node:
            rollouts = node.subscribe(node.keys.learner_rollouts(), Rollout, mode="fifo")
            node.wait_alive(SERVICES, timeout=30)
            yield node, rollouts
    finally:
        launcher.stop_all()
