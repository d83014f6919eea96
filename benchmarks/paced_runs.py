"""What the benchmarks of an observer beside a learning session share (`bench_foxglove`,
`bench_ros2`): their flags, one run per real-time factor (1, then 0; `--smoke`: 0 only, one
repeat of 2 rollouts) in a temporary folder, and the report printed after every run."""

from __future__ import annotations

import argparse
import os
import shutil
import tempfile
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from archery.apps.up.launch_config import SERVICES
from archery.apps.up.launcher import Launcher
from archery.mesh.node import Node
from archery.mesh.subscription import Subscription
from archery.protocol.messages import Rollout
from benchmarks.bench_record import _per_rollout, mesh_launcher
from benchmarks.trees import header

__all__ = ["PacedMesh", "paced_mesh", "run_paced"]

#: one rtf's sessions: (rtf, repeats, rollouts per session, folder) -> its result
OneRtf = Callable[[float, int, int, Path], dict[str, Any]]


class PacedMesh:
    """A whole mesh at one rtf: its launcher, a client node, its FIFO subscription to the
    learner's rollouts and the pids of the router and the services."""

    def __init__(self, launcher: Launcher, node: Node, feed: Subscription[Rollout]) -> None:
        self.launcher, self.node, self.feed = launcher, node, feed
        self.pids = {n: c.proc.pid for n, c in launcher.children.items() if c.proc is not None}


@contextmanager
def paced_mesh(tmp: Path, robot: str, rtf: float) -> Iterator[PacedMesh]:
    """A whole mesh of `robot` at real-time factor `rtf` (files under `tmp`), all alive and
    warmed up (one untimed 2-rollout session: the detector calibrates); stopped at the end."""
    launcher = mesh_launcher(tmp / f"rtf{rtf:g}", robot, tmp / f"model-{rtf:g}.json", rtf)
    launcher.up(180)
    try:
        with Node(None, launcher.net) as node:
            feed = node.subscribe(node.keys.learner_rollouts(), Rollout, mode="fifo")
            node.wait_alive(SERVICES, timeout=30)
            _per_rollout(node, feed, 1000, 2)
            yield PacedMesh(launcher, node, feed)
    finally:
        launcher.stop_all()


def run_paced(
    name: str,
    doc: str | None,
    argv: Sequence[str] | None,
    one_rtf: OneRtf,
    report: Callable[[dict[str, Any], int], None],
) -> int:
    """Parse `python -m benchmarks.NAME`'s flags from `argv`, run `one_rtf` at rtf 1 and 0
    (`--smoke`: 0 only, 1 repeat of 2 rollouts), print `report` of each; exit status 0."""
    os.environ.setdefault("MUJOCO_GL", "egl")
    parser = argparse.ArgumentParser(prog=f"python -m benchmarks.{name}", description=doc)
    parser.add_argument("--repeats", type=int, default=5, help="pairs of sessions per rtf (≥ 5)")
    parser.add_argument("--rollouts-rtf1", type=int, default=8, help="rollouts per session, rtf 1")
    parser.add_argument("--rollouts-rtf0", type=int, default=30, help="rollouts per session, rtf 0")
    parser.add_argument("--smoke", action="store_true", help="1 repeat of 2 rollouts at rtf 0")
    args = parser.parse_args(argv)
    tmp = Path(tempfile.mkdtemp(prefix=f"{name}-"))
    try:
        header()
        print(f"- Load before the run: {', '.join(f'{x:.2f}' for x in os.getloadavg())}")
        plan = [(0.0, 1, 2)] if args.smoke else [
            (1.0, args.repeats, args.rollouts_rtf1), (0.0, args.repeats, args.rollouts_rtf0),
        ]  # fmt: skip
        results = [(one_rtf(rtf, n, k, tmp), k) for rtf, n, k in plan]
        print(f"\n--- {name}")
        for result, rollouts in results:
            report(result, rollouts)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return 0
