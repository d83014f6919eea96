"""A session beside a viewer's reads: wall time per rollout beside 16 far-future grabs of the
camera and beside a flood of the detector's `frame`, each against none.

Run `python -m benchmarks.bench_reads [--repeats 7] [--rollouts 80]`. A router and the five
services run as child processes (`benchmarks.learning_mesh`, the product's `archery up`
defaults: rtf 0). Each repeat runs three ARCHER sessions of `--rollouts` rollouts (`until_hit`
off), one per condition, in an order rotated from repeat to repeat:

* none: the session alone;
* grabs: a client of identity `viewer` keeps `GRABS` grabs of the camera asking for a sim time
  no session reaches (`after_sim_time` 1e9 s, a timeout of 120 s) from the session's start to
  its end, each re-sent the moment it ends (its caller waits `HOLD` s; a grab refused `busy` is
  re-sent after `BACKOFF` s);
* flood: from the session's start, a client of identity `viewer` makes `FLOOD` calls of the
  detector's `frame` back to back (each call waiting for its reply), then stops.

The calls name their caller as the product's do (`Verb.names_caller`): the camera holds at most
`mesh.rpc_server.MAX_WAITING_PER_CALLER` of the viewer's grabs and the detector serves it
`FRAME_RATE` frames a second; the rest are refused `busy`. Reported: wall ms per rollout, median
[min, max] over the repeats; the ratio of each condition to none within each repeat (goals:
grabs ≤ 1.05×, flood ≤ 1.10×); the calls sent, refused `busy` and served. A session that does
not finish all its rollouts fails the benchmark.

`--smoke`: one repeat of 3 rollouts per condition and a flood of 50 calls (seconds after the
mesh's start-up; no figures).
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from archery.mesh.node import Node
from archery.protocol.errors import RpcError
from archery.protocol.verbs import detector as dv
from archery.protocol.verbs.camera import GRAB, GrabArgs
from benchmarks.learning_mesh import learning_mesh, progress_bar
from benchmarks.machine import cpu_model
from benchmarks.spread import median_spread
from tests.rpc import rpc_call

__all__ = ["FLOOD", "GRABS", "main"]

GRABS = 16  # far-future grabs the viewer keeps sent
HOLD = 4.0  # s: how long the viewer waits for each (its grab asks 120 s)
BACKOFF = 1.0  # s before a grab refused `busy` is sent again
FLOOD = 1200  # `frame` calls at least, sent back to back
NEVER = 1e9  # s of sim time: a world state no session reaches
CONDITIONS = ("none", "grabs", "flood")


@dataclasses.dataclass
class Counts:
    """Calls a reader sent, and how they ended."""

    sent: int = 0
    busy: int = 0
    served: int = 0
    other: list[str] = dataclasses.field(default_factory=list)


class Reader:
    """`threads` threads of a `viewer` client, each calling `call` until `stop`, or until
    `most` calls were sent in all."""

    def __init__(self, call: Callable[[], Any], threads: int, most: float, backoff: float) -> None:
        self.counts = Counts()
        self.took = 0.0  # s from the first call to the last reply (the last thread's)
        self._started = time.perf_counter()
        self._call, self._most, self._backoff = call, most, backoff
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._threads = [threading.Thread(target=self._keep, daemon=True) for _ in range(threads)]
        for thread in self._threads:
            thread.start()

    def _keep(self) -> None:
        counts = self.counts
        while True:
            with self._lock:
                if self._stop.is_set() or counts.sent >= self._most:
                    self.took = max(self.took, time.perf_counter() - self._started)
                    return
                counts.sent += 1
            try:
                self._call()
                with self._lock:
                    counts.served += 1
            except RpcError as exc:
                with self._lock:
                    if exc.code == "busy":
                        counts.busy += 1
                    elif exc.code != "timeout":
                        counts.other.append(exc.code)
                if exc.code == "busy" and self._backoff:
                    self._stop.wait(self._backoff)

    def stop(self) -> Counts:
        """Stop sending; wait for each thread's last call to end."""
        self._stop.set()
        for thread in self._threads:
            thread.join()
        return self.counts


def _reader(viewer: Node, condition: str, flood: int) -> Reader:
    if condition == "grabs":
        key, args = viewer.keys.cam_rpc(), GrabArgs(after_sim_time=NEVER, timeout=120.0)
        return Reader(
            lambda: viewer.call_typed(key, GRAB, args, timeout=HOLD), GRABS, float("inf"), BACKOFF
        )
    key, frame = viewer.keys.detector_rpc(), dv.FrameArgs(overlay=True)
    return Reader(lambda: viewer.call_typed(key, dv.FRAME, frame, timeout=30.0), 1, flood, 0.0)


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
    parser = argparse.ArgumentParser(prog="python -m benchmarks.bench_reads", description=__doc__)
    parser.add_argument("--repeats", type=int, default=7, help="sessions per condition")
    parser.add_argument("--rollouts", type=int, default=80, help="rollouts per session")
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    parser.add_argument("--smoke", action="store_true", help="1 repeat of 3 rollouts: no figures")
    args = parser.parse_args(argv)
    args.flood = FLOOD
    if args.smoke:
        args.repeats, args.rollouts, args.flood = 1, 3, 50
    with tempfile.TemporaryDirectory(prefix="bench-reads-") as tmp:
        return _run(args, Path(tmp).resolve())


def _run(args: argparse.Namespace, out: Path) -> int:
    walls: dict[str, list[float]] = {c: [] for c in CONDITIONS}
    counts = {c: Counts() for c in CONDITIONS[1:]}
    flood_s: list[float] = []
    with (
        learning_mesh(out) as (node, rollouts),
        Node(None, dataclasses.replace(node.net, identity="viewer")) as viewer,
        progress_bar(disable=args.no_progress) as bar,
    ):
        # the detector keeps a frame to serve `frame` from the first session on
        _session(node, rollouts, 1, 99)
        task = bar.add_task("sessions", total=len(CONDITIONS) * args.repeats)
        for repeat in range(args.repeats):
            shift = repeat % len(CONDITIONS)
            for condition in CONDITIONS[shift:] + CONDITIONS[:shift]:
                seed = 100 + repeat
                if condition == "none":
                    wall = _session(node, rollouts, args.rollouts, seed)
                else:
                    reader = _reader(viewer, condition, args.flood)
                    try:
                        wall = _session(node, rollouts, args.rollouts, seed)
                    finally:
                        got = reader.stop()
                    if condition == "flood":
                        flood_s.append(reader.took)
                    total = counts[condition]
                    total.sent, total.busy = total.sent + got.sent, total.busy + got.busy
                    total.served += got.served
                    total.other += got.other
                walls[condition].append(1e3 * wall / args.rollouts)
                bar.advance(task)
    failed = any(c.other for c in counts.values())
    if args.smoke:
        print(f"smoke: ms per rollout {walls}; calls {counts}")
        return 1 if failed else 0
    print(f"machine: {cpu_model()}; {args.repeats} interleaved repeats of {args.rollouts} rollouts")
    print(f"ms per rollout, alone:                    {median_spread(walls['none'], '.1f')}")
    for condition, what, goal in (
        ("grabs", f"{GRABS} far-future grabs", 1.05),
        ("flood", f"a {args.flood}-call frame flood", 1.10),
    ):
        ratios = [c / n for c, n in zip(walls[condition], walls["none"], strict=True)]
        medians = statistics.median(walls[condition]) / statistics.median(walls["none"])
        got = counts[condition]
        print(f"ms per rollout, beside {what}: {median_spread(walls[condition], '.1f')}")
        print(
            f"  ratio / alone per repeat {median_spread(ratios, '.3f')} (goal ≤ {goal}), "
            f"medians {medians:.3f}×; calls sent {got.sent}, busy {got.busy}, "
            f"served {got.served}, other errors {len(got.other)}"
        )
    print(f"flood: s from its first call to its last reply {median_spread(flood_s, '.2f')}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
