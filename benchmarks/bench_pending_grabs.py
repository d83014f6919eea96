"""A session beside grabs that never come true: wall time per rollout with `PENDING` pending
grabs of the camera against none.

Run `python -m benchmarks.bench_pending_grabs [--repeats 5] [--rollouts 40]`. A router and the
five services run as child processes (`benchmarks.learning_mesh`, the product's defaults: rtf
0). Each repeat runs two ARCHER sessions of `--rollouts` rollouts (`until_hit` off), in
alternating order: one alone, one while a client (the tools' default identity) keeps
`PENDING` grabs of the camera waiting for a world state that never comes (`after_sim_time`
1e9 s), each asking `HOLD` s and re-sent the moment it ends, so that `PENDING` are in hand
throughout. Between the two, the benchmark waits until the pending grabs have run out. Reported:
wall ms per rollout, median [min, max] over the repeats, and their ratio (goal ≤ 1.05×), with
the grabs refused `busy` (none expected: `PENDING` is `mesh.rpc_server.MAX_WAITING_PER_CALLER`,
the most one identity has waiting; `benchmarks.bench_reads` tries more).

`--smoke`: one repeat of 3 rollouts each (seconds after the mesh's start-up; no figures).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

from archery.mesh.node import Node
from archery.mesh.rpc_server import MAX_WAITING_PER_CALLER
from archery.protocol.errors import RpcError
from archery.protocol.verbs.camera import GRAB, GrabArgs
from benchmarks.learning_mesh import learning_mesh, progress_bar
from benchmarks.machine import cpu_model
from benchmarks.spread import median_spread
from tests.rpc import rpc_call

__all__ = ["HOLD", "PENDING", "main"]

PENDING = MAX_WAITING_PER_CALLER  # grabs in hand while a session runs
HOLD = 4.0  # s: how long each pending grab asks to wait (and its caller waits)
NEVER = 1e9  # s of sim time: a world state no session reaches


class Pending:
    """`PENDING` threads, each keeping one far-future grab waiting until `stop`."""

    def __init__(self, node: Node) -> None:
        self._node = node
        self._stop = threading.Event()
        self.sent = 0
        self.busy = 0
        self.other: list[str] = []
        self._lock = threading.Lock()
        self._threads = [threading.Thread(target=self._keep, daemon=True) for _ in range(PENDING)]
        for thread in self._threads:
            thread.start()

    def _keep(self) -> None:
        key, grab = self._node.keys.cam_rpc(), GRAB
        args = GrabArgs(after_sim_time=NEVER, timeout=HOLD)
        while not self._stop.is_set():
            with self._lock:
                self.sent += 1
            try:
                self._node.call_typed(key, grab, args, timeout=HOLD)
            except RpcError as exc:
                with self._lock:
                    if exc.code == "busy":
                        self.busy += 1
                    elif exc.code != "timeout":
                        self.other.append(exc.code)
                if exc.code == "busy":
                    self._stop.wait(0.1)

    def stop(self) -> None:
        """Stop re-sending and wait until each thread's last grab has run out (≤ `HOLD` s)."""
        self._stop.set()
        for thread in self._threads:
            thread.join()


def _session(node: Node, rollouts: Any, count: int, seed: int) -> float:
    """One ARCHER session of `count` rollouts; its wall time (s)."""
    from archery.apps.learn.follow import follow

    learner = node.keys.learner_rpc()
    request = {"algo": "archer", "seed": seed, "rollouts": count, "until_hit": False}
    start = time.perf_counter()
    started = rpc_call(node, learner, "start", request, timeout=60)
    final = follow(node, started["session"], rollouts, lambda _: None, poll=0.2)
    wall = time.perf_counter() - start
    done = final.get("rollouts")
    if done != count or final.get("state") != "finished":
        raise RuntimeError(f"the session ended {final.get('state')} after {done} rollouts")
    return wall


def main(argv: list[str] | None = None) -> int:
    """Run the interleaved sessions and print the table."""
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.bench_pending_grabs", description=__doc__
    )
    parser.add_argument("--repeats", type=int, default=5, help="sessions per condition")
    parser.add_argument("--rollouts", type=int, default=40, help="rollouts per session")
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    parser.add_argument("--smoke", action="store_true", help="1 repeat of 3 rollouts: no figures")
    args = parser.parse_args(argv)
    if args.smoke:
        args.repeats, args.rollouts = 1, 3
    with tempfile.TemporaryDirectory(prefix="bench-pending-grabs-") as tmp:
        return _run(args, Path(tmp).resolve())


def _run(args: argparse.Namespace, out: Path) -> int:
    walls: dict[str, list[float]] = {"none": [], "pending": []}
    busy = sent = 0
    other: list[str] = []
    with (
        learning_mesh(out) as (node, rollouts),
        progress_bar(disable=args.no_progress) as bar,
    ):
        task = bar.add_task("sessions", total=2 * args.repeats)
        for repeat in range(args.repeats):
            order = ("none", "pending") if repeat % 2 == 0 else ("pending", "none")
            for condition in order:
                seed = 100 + repeat
                if condition == "none":
                    wall = _session(node, rollouts, args.rollouts, seed)
                else:
                    with Node(None, node.net) as viewer:
                        pending = Pending(viewer)
                        try:
                            wall = _session(node, rollouts, args.rollouts, seed)
                        finally:
                            pending.stop()
                    busy, sent = busy + pending.busy, sent + pending.sent
                    other += pending.other
                walls[condition].append(1e3 * wall / args.rollouts)
                bar.advance(task)
    if args.smoke:
        print(f"smoke: ms per rollout {walls}, pending grabs sent {sent}, busy {busy}")
        return 0 if not other else 1
    ratios = [p / n for p, n in zip(walls["pending"], walls["none"], strict=True)]
    print(f"machine: {cpu_model()}; {args.repeats} interleaved repeats of {args.rollouts} rollouts")
    print(f"ms per rollout, no pending grab:     {median_spread(walls['none'], '.1f')}")
    print(f"ms per rollout, {PENDING} pending grabs:    {median_spread(walls['pending'], '.1f')}")
    print(f"ratio pending / none (per repeat):  {median_spread(ratios, '.3f')} (goal ≤ 1.05)")
    print(
        f"pending grabs sent {sent}, refused busy {busy}, other errors {len(other)}; "
        f"medians {statistics.median(walls['pending']) / statistics.median(walls['none']):.3f}×"
    )
    return 0 if not other else 1


if __name__ == "__main__":
    sys.exit(main())
