"""Benchmark of Fig. 6 on the MuJoCo iCubs: the wall time of `archery experiment --world mesh`
on a fleet started by `archery up --robots N`, this tree against an earlier one in the same run.

Run `python -m benchmarks.bench_fig6 [--before 0d1273b] [--repeats 1] [--robots 3] [--sessions
40] [--rollouts 60] [--algo archer,power,cma,hill,random]`. Each repeat runs, for each tree
(this one and `git archive BEFORE`, alternating which goes first), as users do:

* `archery up --robots N --restart never` on a free loopback port, with the tree's code first
  on the path (`benchmarks.trees.env_for`), until it reports all alive;
* `archery experiment --world mesh --sessions S --rollouts R --algo A --out DIR` (seed 0, every
  session its whole budget), timed from its start to its exit;
* the router's and the stacks' CPU time (psutil) over the experiment.

Prints per tree the wall time (median [min, max] over repeats), the ratio this / earlier per
repeat, rollouts/s, CPU s per rollout, and the rollouts to hit per algorithm (the same seed on
both trees: the learners' figures should agree). Writes `runs/bench-fig6/bench.json`; each run's
figures are in its `--out` folder (`fig6.png`, `summary.json`).

`--smoke` runs the same path at its smallest budget: one repeat, one robot, one ARCHER session
of 4 rollouts (its exploration phase and one learned rollout), the earlier tree being
`git archive HEAD` (this tree's last commit, so that the comparison runs without the history of
a shallow clone); everything it writes goes to a temporary folder, removed at the end.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import psutil

from archery.mesh.router import free_tcp_endpoint
from benchmarks.bench_cpu import ARCHERY, start_up, stop
from benchmarks.spread import median_spread
from benchmarks.trees import ROOT, env_for, header, interleaved, tree_at

__all__ = ["main"]


def _cpu(up: subprocess.Popen[str]) -> float:
    """CPU seconds (user + system) `archery up` and its children have used so far."""
    total = 0.0
    for proc in [psutil.Process(up.pid), *psutil.Process(up.pid).children(recursive=True)]:
        try:
            times = proc.cpu_times()
        except psutil.Error:
            continue
        total += times.user + times.system
    return total


def _one_run(env: dict[str, str], out: Path, args: argparse.Namespace) -> dict[str, Any]:
    """One fleet, one experiment: its wall time, CPU and summary."""
    endpoint = free_tcp_endpoint()
    up = start_up(env, endpoint, out, "--robots", str(args.robots), "--restart", "never")
    try:
        cpu0, t0 = _cpu(up), time.monotonic()
        experiment = subprocess.run(
            [
                *ARCHERY,
                "experiment",
                "--world",
                "mesh",
                "--connect",
                endpoint,
                "--sessions",
                str(args.sessions),
                "--rollouts",
                str(args.rollouts),
                "--algo",
                args.algo,
                "--out",
                str(out / "experiment"),
                "--no-progress",
            ],
            env=env,
            cwd=out,
            stdin=subprocess.DEVNULL,
            capture_output=True,
            text=True,
        )
        wall = time.monotonic() - t0
        cpu = _cpu(up) - cpu0
    finally:
        stop(up)
    if experiment.returncode != 0:
        raise RuntimeError(f"archery experiment exited {experiment.returncode}: "
                           f"{experiment.stderr[-2000:]}")  # fmt: skip
    summary = json.loads((out / "experiment" / "summary.json").read_text())
    rollouts = args.sessions * args.rollouts * len(args.algo.split(","))
    to_hit = {name: a["rollouts_to_hit"]["median"] for name, a in summary["algorithms"].items()}
    return {"wall_s": wall, "cpu_s": cpu, "rollouts": rollouts, "to_hit": to_hit}


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark; exit status 0."""
    parser = argparse.ArgumentParser(prog="python -m benchmarks.bench_fig6", description=__doc__)
    parser.add_argument("--before", default="0d1273b", help="the earlier tree's commit")
    parser.add_argument("--repeats", type=int, default=1, help="interleaved repeats")
    parser.add_argument("--robots", type=int, default=3, help="robot stacks (default 3)")
    parser.add_argument("--sessions", type=int, default=40, help="sessions per algorithm")
    parser.add_argument("--rollouts", type=int, default=60, help="rollouts per session")
    parser.add_argument("--algo", default="archer,power,cma,hill,random", help="algorithms")
    parser.add_argument("--out", default="runs/bench-fig6", help="output directory")
    parser.add_argument(
        "--smoke",
        action="store_true",
        help="smallest budget: 1 repeat, 1 robot, 1 archer session of 4 rollouts, before = HEAD, "
        "output in a temporary folder (overrides the flags above)",
    )
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="bench-fig6-") as tmp:
        if args.smoke:
            args.before, args.repeats, args.robots = "HEAD", 1, 1
            args.sessions, args.rollouts, args.algo = 1, 4, "archer"
            args.out = str(Path(tmp) / "out")
        return _run(args, Path(tmp))


def _run(args: argparse.Namespace, tmp: Path) -> int:
    """Both trees' runs (the earlier one extracted under `tmp`) and the report."""
    out = Path(args.out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    results: dict[str, list[dict[str, Any]]] = {"after": [], "before": []}
    before = tmp / "before"
    before.mkdir()
    trees = [("after", ROOT), ("before", tree_at(args.before, before))]
    for repeat, name, tree in interleaved(args.repeats, trees):
        run_dir = out / f"{name}-{repeat}"
        run_dir.mkdir(parents=True, exist_ok=True)
        run = _one_run(env_for(tree), run_dir, args)
        results[name].append(run)
        print(
            f"repeat {repeat + 1}, {name}: {run['wall_s']:.1f} s, "
            f"{run['rollouts'] / run['wall_s']:.2f} rollouts/s, "
            f"CPU {run['cpu_s'] / run['rollouts'] * 1000:.1f} ms/rollout, "
            f"to hit {run['to_hit']}",
            file=sys.stderr,
            flush=True,
        )
    header()
    print(
        f"- `archery up --robots {args.robots}` and `archery experiment --world mesh` "
        f"({args.sessions} sessions × {args.rollouts} rollouts × {args.algo}), "
        f"{args.repeats} interleaved repeats; before: `{args.before}`\n"
    )
    print("| tree | wall s | rollouts/s | CPU ms/rollout | rollouts to hit (median) |")
    print("|---|---|---|---|---|")
    for name, runs in results.items():
        wall = median_spread([r["wall_s"] for r in runs])
        rate = median_spread([r["rollouts"] / r["wall_s"] for r in runs])
        cpu = median_spread([1000 * r["cpu_s"] / r["rollouts"] for r in runs])
        print(f"| {name} | {wall} | {rate} | {cpu} | {runs[-1]['to_hit']} |")
    pairs = zip(results["after"], results["before"], strict=True)
    ratios = [a["wall_s"] / b["wall_s"] for a, b in pairs]
    print(f"\nwall time after / before, per repeat: {median_spread(ratios, '.3f')}")
    (out / "bench.json").write_text(json.dumps(results, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
