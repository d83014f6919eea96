"""Benchmark of an idle mesh's CPU cost: what the services burn when nobody asks for anything.

Run `python -m benchmarks.bench_idle [--seconds 10] [--repeats 1] [--settle 5]`. It starts the
mesh as `archery up` does (`Launcher`, router and the five services), waits until every service
is alive, lets it settle (the detector's start-up calibration, the learner's idle state), then
measures each process's CPU time (user + system, `psutil`) over `--seconds` s of wall time,
`--repeats` times. It prints per process and in total the CPU used as a percentage of one core
(median over the repeats, and the spread); the goal is ≤ 5 % in total (issue 27).

`--smoke` runs the same path at its smallest budget: the whole mesh up, no settling, one
measurement of 0.5 s; it prints the table and the goal's verdict but exits 0 whatever the
verdict (half a second measures nothing), nonzero only when the mesh or the measurement fails.
Its logs go to a temporary folder that is removed at the end.
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

import psutil

from benchmarks.bench_record import mesh_launcher

__all__ = ["main", "measure"]

GOAL = 5.0  # % of one core for the whole idle mesh


def _cpu(proc: psutil.Process) -> float:
    times = proc.cpu_times()
    return times.user + times.system


def measure(procs: dict[str, psutil.Process], seconds: float) -> dict[str, float]:
    """Each process's CPU use over `seconds` s of wall time, in % of one core."""
    before = {name: _cpu(p) for name, p in procs.items()}
    start = time.monotonic()
    time.sleep(seconds)
    wall = time.monotonic() - start
    return {name: 100.0 * (_cpu(p) - before[name]) / wall for name, p in procs.items()}


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.bench_idle", description=__doc__)
    parser.add_argument("--seconds", type=float, default=10.0, help="per measurement")
    parser.add_argument("--repeats", type=int, default=5, help="measurements")
    parser.add_argument("--settle", type=float, default=5.0, help="s after all are alive")
    parser.add_argument(
        "--smoke",
        action="store_true",
        help="smallest budget (no settling, one 0.5 s measurement; overrides the flags above); "
        "the goal is not judged",
    )
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark; exit status 0 (1 when the idle mesh is over the goal, outside a smoke
    run)."""
    args = _parser().parse_args(argv)
    if args.smoke:
        args.seconds, args.repeats, args.settle = 0.5, 1, 0.0
    os.environ.setdefault("MUJOCO_GL", "egl")
    tmp = Path(tempfile.mkdtemp(prefix="bench-idle-"))
    try:
        return _run(args, tmp)
    finally:
        if args.smoke:
            shutil.rmtree(tmp, ignore_errors=True)


def _run(args: argparse.Namespace, tmp: Path) -> int:
    """Measure the mesh whose logs go under `tmp`; print the table; the exit status."""
    launcher = mesh_launcher(tmp, "benchidle", tmp / "model.json")
    runs: list[dict[str, float]] = []
    with launcher:
        took = launcher.up(180)
        print(f"mesh alive in {took:.1f} s; settling {args.settle:g} s", flush=True)
        procs = {
            name: psutil.Process(child.proc.pid)
            for name, child in launcher.children.items()
            if child.proc is not None
        }
        time.sleep(args.settle)
        for i in range(args.repeats):
            run = measure(procs, args.seconds)
            runs.append(run)
            print(f"repeat {i}: total {sum(run.values()):.1f} % of one core", flush=True)
    print("\n--- bench_idle")
    print(f"idle CPU, % of one core ({args.seconds:g} s × {args.repeats}; median, spread):")
    for name in runs[0]:
        values = [run[name] for run in runs]
        print(
            f"  {name:<11} {statistics.median(values):6.2f} %"
            f"  ({min(values):.2f}–{max(values):.2f})"
        )
    totals = [sum(run.values()) for run in runs]
    total = statistics.median(totals)
    print(
        f"  {'total':<11} {total:6.2f} %  ({min(totals):.2f}–{max(totals):.2f}); "
        f"goal ≤ {GOAL:g} %: {'met' if total <= GOAL else 'NOT met'}"
        + (" (not judged in a smoke run)" if args.smoke else "")
    )
    return 0 if total <= GOAL or args.smoke else 1


if __name__ == "__main__":
    sys.exit(main())
