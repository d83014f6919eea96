"""Benchmark of the closed loop over the mesh: wall time per rollout and rollouts to the ring.

Run `python -m benchmarks.bench_loop [--seeds N] [--algos archer,power]`. It starts a router
and the five services as child processes (`apps.up.launcher.Launcher`, robot at rtf 0), then
runs one session per (algorithm, seed) through the learner's RPC, ending at the first rollout
inside the 5 cm ring (measured by the detector) or at the budget. From the journals:

* wall time per rollout: between consecutive done records of a session (everything: ask, two
  journal writes, posture, nock, release, measure, tell), the first rollout of each session
  left out (it includes the robot's reset and the move from home);
* its breakdown from each done record's timing: IK + transport of the posture call, the motion
  (the controller's move), nock, the flight (release call), the measure call with the
  detector's own timings (grab: waiting for the camera's render of the landed scene, and
  detection) and what remains of it (transport), the learner's ask and tell and the journal
  write; the camera's mean render time from its `status`;
* rollouts to the ring per algorithm: median, quartiles, sessions that hit, and how far the
  detector's r is from the robot's ground truth.

Writes `runs/bench-loop/bench.json`; prints the tables. `--smoke`: one ARCHER session of 2
rollouts on the same whole mesh (tens of seconds, most of it the mesh's start-up; its figures
are noise), the journals and bench.json in a temporary directory, removed after.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from archery.apps.learn.follow import follow
from archery.apps.up.launch_config import SERVICES
from archery.apps.up.launcher import Launcher
from archery.mesh.node import Node
from archery.mesh.router import free_tcp_endpoint
from archery.protocol.journal_records import DoneRecord
from archery.protocol.messages import Rollout
from archery.services.learner.journal import read_records
from tests.rpc import rpc_call

__all__ = ["main"]

BUDGET = {"archer": 30, "power": 60}
SMOKE_BUDGET = 2  # rollouts of the smoke run's one session: one rollout-to-rollout time


def _session(node: Node, rollouts: Any, algo: str, seed: int, budget: int) -> dict[str, Any]:
    request = {"algo": algo, "seed": seed, "rollouts": budget}
    start = time.perf_counter()
    session = rpc_call(node, node.keys.learner_rpc(), "start", request, timeout=60)["session"]
    final = follow(node, session, rollouts, lambda m: None, poll=0.2)
    final["wall_s"] = time.perf_counter() - start
    return final


def _stats(values: list[float], scale: float = 1e3) -> dict[str, float]:
    v = np.asarray(values, dtype=float) * scale
    if v.size == 0:
        return {"median": float("nan"), "p90": float("nan"), "n": 0}
    return {"median": float(np.median(v)), "p90": float(np.percentile(v, 90)), "n": int(v.size)}


def _breakdown(done: list[DoneRecord]) -> dict[str, list[float]]:
    parts: dict[str, list[float]] = {}

    def add(name: str, value: float | None) -> None:
        if value is not None:
            parts.setdefault(name, []).append(float(value))

    for record in done:
        t = record.timing or {}
        detector = {k[len("detector_") :]: v for k, v in t.items() if k.startswith("detector_")}
        add("IK + transport (posture call − move)", t.get("ik_and_transport_s"))
        add("motion (controller's move)", t.get("move_s"))
        add("nock call", t.get("nock_s"))
        add("flight (release call)", t.get("release_s"))
        add("measure call", t.get("measure_s"))
        for name, value in detector.items():
            add(f"  detector: {name}", value)
        inside = sum(v for k, v in detector.items() if k in ("total_s",)) or sum(detector.values())
        add("  transport + wait (measure − detector)", t.get("measure_s", 0.0) - inside)
        add("learner ask + tell", t.get("ask_s", 0.0) + t.get("learner_s", 0.0))
        add("journal: proposed record", t.get("journal_proposed_s"))
        add("hit frame (hits only)", t.get("hit_frame_s"))
        add("rollout (ask → before the done record)", t.get("rollout_s"))
    return parts


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark; exit status 0."""
    os.environ.setdefault("MUJOCO_GL", "egl")
    parser = argparse.ArgumentParser(prog="python -m benchmarks.bench_loop", description=__doc__)
    parser.add_argument("--seeds", type=int, default=10, help="sessions per algorithm")
    parser.add_argument("--algos", default="archer,power", help="comma-separated algorithms")
    parser.add_argument("--out", default="runs/bench-loop", help="output directory")
    parser.add_argument(
        "--smoke",
        action="store_true",
        help="one archer session of 2 rollouts, output in a temporary directory: no figures",
    )
    args = parser.parse_args(argv)
    if args.smoke:
        with tempfile.TemporaryDirectory(prefix="bench-loop-") as tmp:
            return _run(args.algos.split(",")[:1], 1, Path(tmp), budget=SMOKE_BUDGET)
    return _run(args.algos.split(","), args.seeds, Path(args.out))


def _run(algos: list[str], seeds: int, out: Path, budget: int | None = None) -> int:
    """Sessions of every algorithm in `algos` for seeds 0 … seeds − 1 (each to its `BUDGET`,
    or to `budget` rollouts); the tables printed, bench.json under `out`."""
    launcher = Launcher(
        free_tcp_endpoint(), "bench", out / "logs", {"learner": ["--runs", str(out)]}
    )
    t0 = time.perf_counter()
    launcher.up(180)
    startup = time.perf_counter() - t0
    sessions: dict[str, list[dict[str, Any]]] = {}
    try:
        with Node(None, launcher.net) as node:
            rollouts = node.subscribe(node.keys.learner_rollouts(), Rollout, mode="fifo")
            node.wait_alive(SERVICES, timeout=30)
            for algo in algos:
                for seed in range(seeds):
                    final = _session(node, rollouts, algo, seed, budget or BUDGET.get(algo, 60))
                    sessions.setdefault(algo, []).append(final)
                    print(
                        f"{algo} seed {seed}: {final['state']} {final.get('ended')}, hit at "
                        f"{final['hit_at']}, {final['rollouts']} rollouts, {final['aborted']} "
                        f"aborted, {final['wall_s']:.1f} s",
                        flush=True,
                    )
            camera = rpc_call(node, node.keys.cam_rpc(), "status", timeout=10)
    finally:
        codes = launcher.stop_all()
    per_rollout: list[float] = []
    done_all: list[DoneRecord] = []
    truth_error: list[float] = []
    for finals in sessions.values():
        for final in finals:
            records = read_records(Path(final["journal"]))[0]
            done = [r for r in records if isinstance(r, DoneRecord)]
            done_all += done[1:]
            per_rollout += [b.t - a.t for a, b in itertools.pairwise(done)]
            truth_error += [
                float(np.linalg.norm(np.subtract(d.r_m, d.truth_r_m)))
                for d in done
                if d.truth_r_m is not None
            ]
    print(f"\nstart-up until all five services are alive: {startup:.1f} s; stop codes {codes}")
    print(
        f"machine: {os.cpu_count()} cores, {platform.processor() or platform.machine()}, "
        f"Python {platform.python_version()}"
    )
    print("\n| figure | median (ms) | p90 (ms) | n |\n|---|---|---|---|")
    print(
        "| **wall time per rollout** (done → done) | {median:.0f} | {p90:.0f} | {n} |".format(
            **_stats(per_rollout)
        )
    )
    breakdown = _breakdown(done_all)
    for name, values in breakdown.items():
        s = _stats(values)
        print(f"| {name} | {s['median']:.1f} | {s['p90']:.1f} | {s['n']} |")
    print(
        f"| camera: mean render of a {camera['width']}x{camera['height']} frame (all "
        f"{camera['renders']} renders, also between rollouts) | {camera['render_ms']:.1f} | – | "
        f"{camera['renders']} |"
    )
    e = _stats(truth_error, 1e2)
    print(f"\n‖r_detector − r_true‖: median {e['median']:.2f} cm, p90 {e['p90']:.2f} cm")
    print(
        "\n| algorithm | rollouts to the 5 cm ring: median [q1, q3] | sessions hit | "
        "aborted attempts | wall per session (s) |\n|---|---|---|---|---|"
    )
    summary: dict[str, Any] = {}
    for algo, finals in sessions.items():
        limit = budget or BUDGET.get(algo, 60)
        to_hit = [f["hit_at"] if f["hit_at"] is not None else limit + 1 for f in finals]
        q1, med, q3 = np.percentile(to_hit, [25, 50, 75])
        hits = sum(f["hit_at"] is not None for f in finals)
        aborted = sum(f["aborted"] for f in finals)
        wall = statistics.median(f["wall_s"] for f in finals)
        print(
            f"| {algo} | {med:g} [{q1:g}, {q3:g}] | {hits}/{len(finals)} | {aborted} | {wall:.1f} |"
        )
        summary[algo] = {"rollouts_to_hit": to_hit, "hits": hits, "aborted": aborted}
    out.mkdir(parents=True, exist_ok=True)
    (out / "bench.json").write_text(
        json.dumps(
            {
                "startup_s": startup,
                "camera": {k: camera[k] for k in ("renders", "render_ms", "frames")},
                "per_rollout_ms": _stats(per_rollout),
                "breakdown_ms": {k: _stats(v) for k, v in breakdown.items()},
                "truth_error_cm": e,
                "algorithms": summary,
                "sessions": {a: [f["session"] for f in fs] for a, fs in sessions.items()},
            },
            indent=2,
        )
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
