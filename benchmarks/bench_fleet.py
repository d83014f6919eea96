"""Benchmark of a fleet of MuJoCo iCubs on this machine: rollouts/s with N robot stacks, CPU
seconds per rollout per process, and where a rollout's time goes.

Run `python -m benchmarks.bench_fleet [--robots 1,2,3] [--repeats 5] [--sessions 6] [--rollouts
10] [--pin]`. Each repeat runs every N in turn (interleaved, so a change in the machine's load
hits every N alike): a fresh router and N robot stacks (robot at rtf 0, controller, camera,
detector; `apps.up.launcher.Launcher`), then one `archery experiment --world mesh` in this
process (its learner: the work queue, one session thread per robot) of `--sessions` sessions per
algorithm × `--rollouts` rollouts, the same work for every N; then everything is stopped.

* rollouts/s: done rollouts between the first and the last done record of the run, over that
  time (the start-up of the stacks is left out); its ratio to N = 1 of the same repeat;
* cores busy: rollouts/s × CPU s per rollout, how much of the machine the fleet keeps busy
  (a single robot that keeps more than 2 / 1.6 = 1.25 of 2 cores busy leaves a second one less
  than 0.6 of its rate);
* `--pin`: robot stack i runs on core i mod the core count (the router and the learner on any),
  which measures what a further core per robot adds, as a further host would;
* CPU s per rollout per process: user + system CPU time (psutil) of each child over the run, and
  of this process (the learner), divided by the run's rollouts; per service, summed over the
  robots (what one rollout costs that service, wherever it ran);
* where a rollout's time goes: medians of the journal's per-rollout timings;
* the bound: the ratio N would reach keeping min(N, cores) cores busy at its measured CPU per
  rollout, min(N, cores) / (cores N = 1 keeps busy) × (N = 1's CPU per rollout / N's): the work
  a rollout needs and the parallelism one robot already has fix it, whatever the scheduling;
* the machine: `benchmarks.machine.core_scaling` in each repeat, what two CPU-bound processes
  get done together over one alone (2.0 on two idle cores of their own; the host's other
  guests and the cores' shared caches take from it).

The baseline is N = 1 (one robot, today's mesh). Prints Markdown tables; writes
`runs/bench-fleet/bench.json`.

`--smoke` runs the same path at its smallest budget: one repeat of N = 1 and N = 2 (so that a
fleet's prefixes and work queue run), two ARCHER sessions of 4 rollouts (its exploration phase
and one learned rollout) per N, `core_scaling` over 0.2 s; bench.json and the logs go to a
temporary folder, removed at the end.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import statistics
import sys
import tempfile
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import psutil

from archery.apps.experiment.config import ExperimentConfig
from archery.apps.experiment.experiment_mesh import (
    MeshSettings,
    mesh_experiment_config,
    run_mesh_experiment,
)
from archery.apps.up.launch_config import (
    SERVICES,
    MeshConfig,
    RobotSpec,
    RouterSpec,
    ServiceSpec,
    fleet_prefixes,
)
from archery.apps.up.launcher import Launcher
from archery.mesh.netflags import NetConfig
from archery.mesh.router import free_tcp_endpoint
from archery.protocol.journal_records import DoneRecord
from archery.services.learner.journal import read_records
from benchmarks.machine import core_scaling, cpu_model
from benchmarks.spread import median_spread

__all__ = ["main"]

STACK = tuple(s for s in SERVICES if s != "learner")
TIMINGS = ("rollout_s", "posture_s", "move_s", "nock_s", "release_s", "measure_s")


def _cpu(pid: int) -> float:
    try:
        times = psutil.Process(pid).cpu_times()
    except psutil.Error:
        return float("nan")
    return times.user + times.system


def _pin(pid: int, core: int) -> None:
    """Keep every thread of process `pid` (and the threads it starts later) on one core."""
    for task in Path(f"/proc/{pid}/task").iterdir():
        with contextlib.suppress(ProcessLookupError):  # a thread that ended meanwhile
            os.sched_setaffinity(int(task.name), {core})


def _one_run(n: int, config: ExperimentConfig, out: Path, pin: bool = False) -> dict[str, Any]:
    """N robot stacks and one experiment over them; its figures. `pin`: robot stack i runs on
    core i mod the core count (the router and the learner on any)."""
    prefixes = fleet_prefixes("bench", n)
    mesh = MeshConfig(
        RouterSpec(free_tcp_endpoint()),
        tuple(RobotSpec(p, STACK) for p in prefixes),
        {"robot": ServiceSpec(("--rtf", "0"))},
    )
    launcher = Launcher(logs=out / "logs", mesh=mesh)
    launcher.up(180)
    try:
        pids = {name: c.proc.pid for name, c in launcher.children.items() if c.proc is not None}
        if pin:
            cores = sorted(os.sched_getaffinity(0))
            for name, pid in pids.items():
                service, _, prefix = name.partition("@")  # a single robot's: no "@prefix"
                if service in STACK:
                    _pin(pid, cores[prefixes.index(prefix or prefixes[0]) % len(cores)])
        before = {name: _cpu(pid) for name, pid in pids.items()} | {"learner": _cpu(os.getpid())}
        settings = MeshSettings(NetConfig(connect=(launcher.endpoint,)), tuple(prefixes))
        run_mesh_experiment(config, out, settings, threading.Event(), progress=False)
        after = {name: _cpu(pid) for name, pid in pids.items()} | {"learner": _cpu(os.getpid())}
    finally:
        launcher.stop_all()
    done = [
        r
        for path in sorted((out / "sessions").glob("*/journal.jsonl"))
        for r in read_records(path)[0]
        if isinstance(r, DoneRecord)
    ]
    stamps = sorted(r.t for r in done)
    rate = (len(stamps) - 1) / (stamps[-1] - stamps[0])
    cpu: dict[str, list[float]] = {}
    for name in after:
        service = name.split("@")[0]
        cpu.setdefault(service, []).append((after[name] - before[name]) / len(done))
    timing = {
        key: float(np.median([r.timing[key] for r in done if key in (r.timing or {})]))
        for key in TIMINGS
    }
    return {
        "robots": n,
        "rollouts": len(done),
        "rollouts_per_s": rate,
        "cpu_s_per_rollout": {k: float(np.sum(v)) for k, v in cpu.items()},
        "cpu_s_per_rollout_all": float(sum(sum(v) for v in cpu.values())),
        "cores_busy": rate * float(sum(sum(v) for v in cpu.values())),
        "timing_median_s": timing,
    }


def _median_table(
    results: dict[int, list[dict[str, Any]]], field: str, columns: Sequence[str], unit: str
) -> None:
    """A Markdown table: per N, the median over repeats of each run's `field[column]` (ms)."""
    print("| N | " + " | ".join(columns) + " |")
    print("|---|" + "---|" * len(columns))
    for n, runs in results.items():
        cells = [f"{1e3 * statistics.median(r[field][c] for r in runs):.0f}{unit}" for c in columns]
        print(f"| {n} | " + " | ".join(cells) + " |")


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark; exit status 0."""
    os.environ.setdefault("MUJOCO_GL", "egl")
    parser = argparse.ArgumentParser(prog="python -m benchmarks.bench_fleet", description=__doc__)
    parser.add_argument("--robots", default="1,2,3", help="fleet sizes N, comma-separated")
    parser.add_argument("--repeats", type=int, default=5, help="interleaved repeats")
    parser.add_argument("--sessions", type=int, default=6, help="sessions per algorithm")
    parser.add_argument("--rollouts", type=int, default=10, help="rollouts per session")
    parser.add_argument("--algos", default="archer,power", help="algorithms, comma-separated")
    parser.add_argument("--out", default="runs/bench-fleet", help="output directory")
    parser.add_argument(
        "--pin",
        action="store_true",
        help="one core per robot stack (stack i on core i mod the cores): scaling per core",
    )
    parser.add_argument(
        "--smoke",
        action="store_true",
        help="smallest budget: 1 repeat of N = 1, 2, 2 archer sessions of 4 rollouts, output in "
        "a temporary folder (overrides the flags above but --pin)",
    )
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="bench-fleet-") as tmp:
        if args.smoke:
            args.robots, args.repeats, args.sessions, args.rollouts = "1,2", 1, 2, 4
            args.algos, args.out = "archer", tmp
        return _run(args)


def _run(args: argparse.Namespace) -> int:
    """Every repeat and fleet size; the tables and bench.json."""
    sizes = [int(x) for x in args.robots.split(",")]
    config = mesh_experiment_config(
        ExperimentConfig(
            algorithms=tuple(args.algos.split(",")),
            sessions=args.sessions,
            rollouts=args.rollouts,
            world="mesh",
        )
    )
    out = Path(args.out)
    results: dict[int, list[dict[str, Any]]] = {n: [] for n in sizes}
    scaling: list[float] = []
    started = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    cores = len(os.sched_getaffinity(0))
    for repeat in range(args.repeats):
        scaling.append(core_scaling(min(2, cores), 0.2 if args.smoke else 1.5))
        for n in sizes:
            run = _one_run(n, config, out / f"r{repeat}-n{n}-{time.time_ns()}", args.pin)
            results[n].append(run)
            print(
                f"repeat {repeat + 1}, N={n}: {run['rollouts_per_s']:.2f} rollouts/s, "
                f"CPU {run['cpu_s_per_rollout_all']:.3f} s/rollout",
                file=sys.stderr,
                flush=True,
            )
    base = [r["rollouts_per_s"] for r in results[sizes[0]]]
    print(
        f"\n{started}; {os.cpu_count()} cores, {cpu_model()}; {args.repeats} interleaved "
        f"repeats of {len(config.algorithms)} algorithms × {args.sessions} sessions × "
        f"{args.rollouts} rollouts per N"
        + ("; robot stack i pinned to core i mod the cores" if args.pin else "")
        + "\n"
    )
    print(
        f"| N robots | rollouts/s: median [min, max] | ratio to N={sizes[0]} "
        "| CPU s/rollout, all | cores busy | bound: ratio at min(N, cores) busy |"
    )
    print("|---|---|---|---|---|---|")
    for n in sizes:
        rates = [r["rollouts_per_s"] for r in results[n]]
        ratios = [r / b for r, b in zip(rates, base, strict=True)]
        total = [r["cpu_s_per_rollout_all"] for r in results[n]]
        busy = [r["cores_busy"] for r in results[n]]
        bound = [
            min(n, cores) / one["cores_busy"] * one["cpu_s_per_rollout_all"] / total_n
            for one, total_n in zip(results[sizes[0]], total, strict=True)
        ]
        print(
            f"| {n} | {median_spread(rates)} | {median_spread(ratios)} "
            f"| {median_spread(total, '.3f')} | {median_spread(busy)} | {median_spread(bound)} |"
        )
    print(
        f"\nThe machine, in the same repeats: two CPU-bound processes together do "
        f"{median_spread(scaling)}× the work of one (`core_scaling`; 2.0 on two idle cores)."
    )
    services = list(results[sizes[0]][0]["cpu_s_per_rollout"])
    print("\nCPU per rollout per service (median over repeats; the stack's summed over robots):\n")
    _median_table(results, "cpu_s_per_rollout", services, " ms")
    print("\nWhere a rollout's time goes (median over repeats of each run's median, ms):\n")
    _median_table(results, "timing_median_s", TIMINGS, "")
    out.mkdir(parents=True, exist_ok=True)
    (out / "bench.json").write_text(
        json.dumps(
            {"started": started, "config": vars(args), "results": results, "core_scaling": scaling},
            indent=2,
        )
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
