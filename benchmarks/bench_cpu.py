"""Benchmark of the CPU one rollout costs the whole mesh, as users run it, against an earlier
tree in the same run.

Run `python -m benchmarks.bench_cpu [--repeats 5] [--before 0d1273b] [--rollouts 42]`. Each
repeat runs, for each condition (nothing watching; `archery record` and `archery dashboard` with
a client polling the dashboard as its page does, `benchmarks.observers`), both trees back to back
(this one, "after", and `git archive BEFORE`, "before"; which goes first alternating, ABBA, so a
drift of the machine weighs least on a pair's ratio):

* `archery up` on a free loopback port (the robot at rtf 0, as `mesh.toml`), started as a user
  does, with the tree's code first on the path (`benchmarks.trees.env_for`);
* `archery learn --algo archer --no-until-hit --rollouts N --seed REPEAT`: an ARCHER session
  that goes on past its hit, so the work of every hit (its frame) is in;
* the kernel's CPU accounting (user + system, psutil) of the router, each of the five services
  (and the observers), read when the journal holds its 10th done rollout and again at its 40th:
  the start-up and the end-of-session report are left out. The journal is watched by reading
  it as it grows (every `POLL` s).

Prints, per tree and condition, the CPU ms per rollout summed over the router and the five
services (median [min, max] over the repeats), its ratio after / before within each repeat, the
wall time per rollout, the cores kept busy, the split per process, and the medians of the
journal's per-rollout timings (where a rollout's wall time goes). Writes
`runs/bench-cpu/bench.json`.

`--smoke` runs the same path at its smallest budget: this tree only (no `git archive`), one
repeat of both conditions (watched and not), sessions of 5 rollouts whose window runs from the
2nd to the 4th done rollout; the rendering backend is left to the product (`MUJOCO_GL` is
passed on only when set); everything it writes goes to a temporary folder, removed at the end.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import psutil

from archery.mesh.router import free_tcp_endpoint
from benchmarks.observers import Observers
from benchmarks.spread import median_spread
from benchmarks.trees import ROOT, env_for, header, tree_at

__all__ = ["ARCHERY", "main", "start_up", "stop"]

ARCHERY = (sys.executable, "-m", "archery.apps.cli")
MESH = ("router", "robot", "controller", "camera", "detector", "learner")
FIRST, LAST = 10, 40  # the window: from the 10th to the 40th journaled done rollout
SMOKE_WINDOW = (2, 4)  # the smoke run's window
POLL = 0.005  # s between reads of the growing journal
TIMINGS = ("posture_s", "release_s", "measure_s", "detector_grab_s", "hit_frame_s", "rollout_s")


def _cpu(procs: dict[str, psutil.Process]) -> dict[str, float]:
    """CPU seconds (user + system) each process has used so far."""
    out = {}
    for name, proc in procs.items():
        times = proc.cpu_times()
        out[name] = times.user + times.system
    return out


def _children(up: subprocess.Popen[str]) -> dict[str, psutil.Process]:
    """`archery up`'s children by service (the router's is `router`)."""
    out = {}
    for child in psutil.Process(up.pid).children():
        args = child.cmdline()
        cli = "archery.apps.cli" if "archery.apps.cli" in args else "apps.cli"  # a tree before it
        verb = args[args.index(cli) + 1]
        out[verb] = child
    missing = set(MESH) - set(out)
    if missing:
        raise RuntimeError(f"archery up runs no {', '.join(sorted(missing))}")
    return out


def start_up(env: dict[str, str], endpoint: str, out: Path, *more: str) -> subprocess.Popen[str]:
    """`archery up` on `endpoint` with the tree of `env` (and the arguments `more`), returned
    once all are alive."""
    up = subprocess.Popen(
        [
            *ARCHERY,
            "up",
            "--listen",
            endpoint,
            "--logs",
            str(out / "logs"),
            "--runs",
            "runs",
            *more,
        ],
        env=env,
        cwd=out,
        stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
    )
    assert up.stdout is not None
    for line in up.stdout:
        if "all alive" in line:
            return up
    up.wait()
    raise RuntimeError(f"archery up ended with status {up.returncode} before all were alive")


def stop(proc: subprocess.Popen[str]) -> None:
    """SIGINT a child and wait for it (SIGKILL after 60 s)."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(60)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def _done_lines(path: Path, offset: int, count: int) -> tuple[int, int, list[dict[str, Any]]]:
    """Read the complete lines of `path` from byte `offset`: the new offset, the done count
    and the done records among them."""
    with path.open("rb") as f:
        f.seek(offset)
        data = f.read()
    end = data.rfind(b"\n") + 1
    done = []
    for line in data[:end].splitlines():
        if b'"record":"done"' in line:
            done.append(json.loads(line))
    return offset + end, count + len(done), done


def _window(
    learn: subprocess.Popen[str],
    runs: Path,
    procs: dict[str, psutil.Process],
    window: tuple[int, int] = (FIRST, LAST),
) -> dict[str, Any]:
    """Wait for the session's journal to hold its `window[0]`-th and `window[1]`-th done
    rollouts (FIRST and LAST by default); the CPU seconds of each process and the wall seconds
    between them, and the window's done records."""
    first, last = window
    journal = None
    while journal is None:
        found = sorted(runs.glob("*/journal.jsonl"))
        if found:
            journal = found[0]
        elif learn.poll() is not None:
            raise RuntimeError(f"archery learn ended with status {learn.returncode}")
        time.sleep(POLL)
    offset, count, records = 0, 0, []
    marks: dict[int, tuple[float, dict[str, float]]] = {}
    while len(marks) < 2:
        offset, count, done = _done_lines(journal, offset, count)
        for mark in (first, last):
            if count >= mark and mark not in marks:
                marks[mark] = (time.monotonic(), _cpu(procs))
        if first in marks:
            records += done
        if len(marks) < 2:
            if learn.poll() is not None:
                raise RuntimeError(f"the session ended after {count} rollouts")
            time.sleep(POLL)
    (t0, cpu0), (t1, cpu1) = marks[first], marks[last]
    rollouts = last - first
    return {
        "journal": str(journal),
        "wall_s": (t1 - t0) / rollouts,
        "cpu_s": {name: (cpu1[name] - cpu0[name]) / rollouts for name in procs},
        "timing_s": {
            key: statistics.median(r["timing"][key] for r in records if key in r["timing"])
            for key in TIMINGS
            if any(key in r["timing"] for r in records)
        },
        "hits": sum(r["hit"] for r in records[1:]),
    }


def _one_run(
    env: dict[str, str],
    out: Path,
    seed: int,
    rollouts: int,
    watched: bool,
    window: tuple[int, int] = (FIRST, LAST),
) -> Any:
    """One mesh of the tree of `env`, one session, optionally watched; its window's figures
    (`window`: the first and last done rollout of the window)."""
    endpoint = free_tcp_endpoint()
    up = start_up(env, endpoint, out)
    try:
        procs = _children(up) | {"up": psutil.Process(up.pid)}
        with contextlib.ExitStack() as stack:
            if watched:
                observers = stack.enter_context(
                    Observers(
                        endpoint,
                        "icubSim",
                        out / "session.mcap",
                        recorder=True,
                        dashboard=True,
                        env=env,
                        cwd=out,
                    )
                )
                procs |= {n: psutil.Process(pid) for n, pid in observers.pids().items()}
            session = ("--algo", "archer", "--no-until-hit", "--rollouts", str(rollouts))
            learn = subprocess.Popen(
                [
                    *ARCHERY,
                    "learn",
                    "--connect",
                    endpoint,
                    "--quiet",
                    *session,
                    "--seed",
                    str(seed),
                ],
                env=env,
                cwd=out,
                stdin=subprocess.DEVNULL,
                stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL,
                text=True,
            )
            try:
                return _window(learn, out / "runs", procs, window)
            finally:
                stop(learn)
    finally:
        stop(up)


def _done(journal: str) -> list[dict[str, Any]]:
    with open(journal, "rb") as f:
        return [json.loads(line) for line in f if b'"record":"done"' in line]


def _same(after: dict[str, Any], before: dict[str, Any], last: int = LAST) -> dict[str, Any]:
    """How the two trees' sessions of one seed compare, rollout by rollout (the first `last`):
    θ proposed and the robot's true r (bit for bit), and the detector's r where the true r
    is the same (largest difference, m)."""
    pairs = list(zip(_done(after["journal"]), _done(before["journal"]), strict=False))[:last]
    truth = [a["truth_r_m"] == b["truth_r_m"] for a, b in pairs]
    return {
        "rollouts": len(pairs),
        "theta": sum(a["theta"] == b["theta"] for a, b in pairs),
        "truth": sum(truth),
        "first_truth_diff": next((i + 1 for i, t in enumerate(truth) if not t), None),
        "max_dr_m": max(
            (
                max(abs(x - y) for x, y in zip(a["r_m"], b["r_m"], strict=True))
                for (a, b), t in zip(pairs, truth, strict=True)
                if t
            ),
            default=float("nan"),
        ),
    }


def _total(run: dict[str, Any], names: tuple[str, ...] = MESH) -> float:
    return float(sum(run["cpu_s"][n] for n in names if n in run["cpu_s"]))


def _report(
    results: dict[str, dict[str, list[dict[str, Any]]]], trees: list[str], last: int = LAST
) -> None:
    """Print the tables; `last`: the window's last done rollout (the rollouts compared)."""
    conditions = list(results[trees[0]])
    print("\nCPU per rollout, router + five services (ms; median [min, max] over repeats):\n")
    print(
        "| tree | condition | CPU ms/rollout | ratio after/before | wall ms/rollout | cores busy |"
    )
    print("|---|---|---|---|---|---|")
    for cond in conditions:
        for tree in trees:
            runs = results[tree][cond]
            cpu = [1e3 * _total(r) for r in runs]
            wall = [1e3 * r["wall_s"] for r in runs]
            busy = [_total(r) / r["wall_s"] for r in runs]
            ratio = "–"
            if tree == "after" and "before" in results:
                before = results["before"][cond]
                ratios = [_total(a) / _total(b) for a, b in zip(runs, before, strict=True)]
                ratio = "×" + median_spread(ratios, ".3f")
            print(
                f"| {tree} | {cond} | {median_spread(cpu, '.1f')} | {ratio} "
                f"| {median_spread(wall, '.0f')} | {median_spread(busy)} |"
            )
    for cond in conditions:
        names = list(results[trees[0]][cond][0]["cpu_s"])
        print(f"\nCPU ms per rollout per process, {cond} (median over repeats):\n")
        print("| tree | " + " | ".join(names) + " |")
        print("|---|" + "---|" * len(names))
        for tree in trees:
            runs = results[tree][cond]
            cells = [f"{1e3 * statistics.median(r['cpu_s'][n] for r in runs):.1f}" for n in names]
            print(f"| {tree} | " + " | ".join(cells) + " |")
    print(
        "\nWhere a rollout's wall time goes (journal timings, median of the runs' medians, ms):\n"
    )
    print("| tree | condition | " + " | ".join(TIMINGS) + " | hits in window |")
    print("|---|---|" + "---|" * (len(TIMINGS) + 1))
    for cond in conditions:
        for tree in trees:
            runs = results[tree][cond]
            cells = []
            for key in TIMINGS:
                values = [r["timing_s"][key] for r in runs if key in r["timing_s"]]
                cells.append(f"{1e3 * statistics.median(values):.1f}" if values else "–")
            hits = statistics.median(r["hits"] for r in runs)
            print(f"| {tree} | {cond} | " + " | ".join(cells) + f" | {hits:g} |")
    if len(conditions) == 2:
        print(
            f"\nThe same seed on one tree, watched against not (the first {last} rollouts of "
            "each repeat's two sessions: the rtf-0 physics must not depend on the load):\n"
        )
        _same_table(
            [(tree, results[tree][conditions[1]], results[tree][conditions[0]]) for tree in trees],
            last,
        )
    if "before" not in results:
        return
    print(
        f"\nThe same seed on both trees (the first {last} rollouts of each repeat's sessions): "
        "θ proposed and the robot's true r bit for bit, the detector's r where the true r is "
        "the same:\n"
    )
    _same_table(
        [(cond, results["after"][cond], results["before"][cond]) for cond in conditions], last
    )


def _same_table(
    groups: list[tuple[str, list[dict[str, Any]], list[dict[str, Any]]]], last: int = LAST
) -> None:
    """Print, per group (a label and two runs per repeat), how the runs of a repeat compare
    (their first `last` rollouts)."""
    print("| runs | repeat | θ identical | true r identical | first that differs | max Δr |")
    print("|---|---|---|---|---|---|")
    for label, first, second in groups:
        for k, (a, b) in enumerate(zip(first, second, strict=True)):
            same = _same(a, b, last)
            n = same["rollouts"]
            print(
                f"| {label} | {k + 1} | {same['theta']}/{n} | {same['truth']}/{n} "
                f"| {same['first_truth_diff'] or '–'} | {1e3 * same['max_dr_m']:.4f} mm |"
            )


def _order(
    repeats: int, conditions: int, trees: list[tuple[str, dict[str, str]]]
) -> Iterator[tuple[int, int, str, dict[str, str]]]:
    """(repeat, condition, tree name, env) in the order of the runs: per repeat, each condition
    with the trees back to back (so a drift of the machine between a pair's runs is smallest),
    which tree goes first alternating from pair to pair (ABBA), the conditions' order alternating
    from repeat to repeat."""
    pair = 0
    for repeat in range(repeats):
        order = range(conditions) if repeat % 2 == 0 else reversed(range(conditions))
        for cond in order:
            for name, env in trees if pair % 2 == 0 else trees[::-1]:
                yield repeat, cond, name, env
            pair += 1


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark; exit status 0."""
    parser = argparse.ArgumentParser(prog="python -m benchmarks.bench_cpu", description=__doc__)
    parser.add_argument("--repeats", type=int, default=5, help="interleaved repeats (≥ 5)")
    parser.add_argument("--before", default="0d1273b", help="the earlier tree's commit")
    parser.add_argument("--no-before", action="store_true", help="this tree only")
    parser.add_argument("--no-observers", action="store_true", help="no watched condition")
    parser.add_argument("--rollouts", type=int, default=LAST + 2, help=f"session budget (> {LAST})")
    parser.add_argument("--out", default="runs/bench-cpu", help="output directory")
    parser.add_argument(
        "--smoke",
        action="store_true",
        help=f"smallest budget: this tree only, 1 repeat, {SMOKE_WINDOW[1] + 1}-rollout "
        "sessions, output in a temporary folder (overrides the flags above)",
    )
    args = parser.parse_args(argv)
    window = SMOKE_WINDOW if args.smoke else (FIRST, LAST)
    if args.smoke:
        args.repeats, args.no_before, args.rollouts = 1, True, window[1] + 1
    if args.rollouts <= window[1]:
        parser.error(f"--rollouts must be more than {window[1]}")
    base: dict[str, str] = {}  # smoke: the product picks its rendering backend
    if not args.smoke:
        base = {"MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    trees = [("after", env_for(ROOT, **base))]
    with tempfile.TemporaryDirectory(prefix="bench-cpu-") as tmp:
        if args.smoke:
            args.out = str(Path(tmp) / "out")
        out = Path(args.out).resolve()
        out.mkdir(parents=True, exist_ok=True)
        if not args.no_before:
            before = tree_at(args.before, Path(tmp))
            trees.insert(0, ("before", env_for(before, **base)))
        conditions = [("none", False)] + ([] if args.no_observers else [("watched", True)])
        results: dict[str, dict[str, list[dict[str, Any]]]] = {
            name: {cond: [] for cond, _ in conditions} for name, _ in trees
        }
        header()
        print(f"- Load before the run: {', '.join(f'{v:.2f}' for v in os.getloadavg())}")
        for repeat, cond_index, name, env in _order(args.repeats, len(conditions), trees):
            cond, watched = conditions[cond_index]
            run_dir = out / f"r{repeat}-{name}-{cond}-{time.time_ns()}"
            run_dir.mkdir(parents=True)
            run = _one_run(env, run_dir, repeat, args.rollouts, watched, window)
            results[name][cond].append(run)
            print(
                f"repeat {repeat + 1} {name} {cond}: {1e3 * _total(run):.1f} ms CPU, "
                f"{1e3 * run['wall_s']:.0f} ms wall per rollout",
                file=sys.stderr,
                flush=True,
            )
        print(f"- Load after the run: {', '.join(f'{v:.2f}' for v in os.getloadavg())}")
        names = [name for name, _ in trees]
        _report(results, names, window[1])
        (out / "bench.json").write_text(
            json.dumps({"config": vars(args), "results": results}, indent=2)
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
