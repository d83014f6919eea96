"""Benchmark of the simulation experiment: every learner on the paper's range and harder ones.

Run `python -m benchmarks.bench_experiment [--sessions 40] [--rollouts 60] [--seed 0] [--out DIR]
[--smoke]`. For each scenario, every algorithm runs `--sessions` sessions of `--rollouts`
rollouts in the ballistic world; it prints the table (rollouts to hit, hit rate, final distance,
wall time in s) and the goals, writes each scenario's figures and bench.json under `--out`, and
times `archery experiment` with the defaults as a fresh process.

`--smoke` runs the same path at its smallest budget: every scenario and algorithm, one session
of 8 rollouts (CMA-ES's exploration phase and one learned rollout), the timed command likewise;
its figures and bench.json go to a temporary folder, removed at the end.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from archery.apps.experiment.censored import format_count, format_counts, format_mean
from archery.apps.experiment.config import AlgorithmRun, ExperimentConfig
from archery.apps.experiment.experiment import run_algorithm, summarise, write_outputs
from archery.services.learner.algorithms.registry import ALGORITHMS
from archery.sim.ballistic import Scenario

__all__ = ["PAPER_ROLLOUTS", "SCENARIOS", "main"]

# The paper's Fig. 5: rollouts to reach the centre in the simulation experiment.
PAPER_ROLLOUTS = {"archer": 5, "power": 19}
SCENARIOS: dict[str, Scenario] = {
    "paper (2.2 m)": Scenario(),
    "drag 0.05/m + wind 1,3,0 m/s": Scenario(drag=0.05, wind=(1.0, 3.0, 0.0)),
    "noise σ=2 cm": Scenario(noise=0.02),
    "target at 5 m": Scenario(distance=5.0),
}
ALGORITHM_ORDER = (
    "archer",
    "archer-plain",
    "archer-iso",
    "archer-plain-iso",
    "archer-ridge",
    "power",
    "power-metre",
    "cma",
    "hill",
    "random",
)
FIGURE_ALGORITHMS = ("archer", "archer-plain", "power", "cma", "hill", "random")
DEFAULT_COMMAND_ALGORITHMS = ("archer", "power", "cma", "hill", "random")


def _slug(name: str) -> str:
    return "".join(c if c.isalnum() else "-" for c in name).strip("-").replace("--", "-")


def _paper(scenario: str, algorithm: str) -> str:
    if scenario != "paper (2.2 m)":
        return "–"
    family = algorithm.split("-")[0]
    return str(PAPER_ROLLOUTS[family]) if family in PAPER_ROLLOUTS else "–"


def _row(scenario: str, name: str, stats: dict, sessions: int) -> str:
    h = stats["rollouts_to_hit"]
    final = stats["final_distance"]
    return (
        f"| {scenario} | {name} | {format_counts(h)} | {format_mean(h)} "
        f"| {stats['hits']}/{sessions} ({100 * stats['hit_rate']:.0f} %) "
        f"| {100 * final['mean']:.1f} ± {100 * final['std']:.1f} "
        f"| {stats['wall_time_s']:.2f} | {_paper(scenario, name)} |"
    )


def _time_default_command(out: Path, sessions: int, rollouts: int, seed: int) -> float:
    """Wall time (s) of `archery experiment` with the default algorithms, as a fresh process."""
    command = [
        sys.executable,
        "-m",
        "archery.apps.cli",
        "experiment",
        "--sessions",
        str(sessions),
        "--rollouts",
        str(rollouts),
        "--seed",
        str(seed),
        "--out",
        str(out),
        "--force",  # the benchmark's own folder: a run before this one is replaced
        "--no-progress",
    ]
    start = time.perf_counter()
    subprocess.run(command, check=True, stdout=subprocess.DEVNULL)
    return time.perf_counter() - start


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark, print the table, write figures and bench.json under --out."""
    parser = argparse.ArgumentParser(prog="python -m benchmarks.bench_experiment")
    parser.add_argument("--out", default="runs/bench-experiment", help="output directory")
    parser.add_argument("--sessions", type=int, default=40, help="sessions per algorithm")
    parser.add_argument("--rollouts", type=int, default=60, help="rollouts per session")
    parser.add_argument("--seed", type=int, default=0, help="the experiment's seed")
    parser.add_argument(
        "--smoke",
        action="store_true",
        help="smallest budget: 1 session of 8 rollouts, output in a temporary folder "
        "(overrides --sessions, --rollouts, --out)",
    )
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="bench-experiment-") as tmp:
        if args.smoke:
            args.sessions, args.rollouts, args.out = 1, 8, tmp
        return _run(args)


def _run(args: argparse.Namespace) -> int:
    """Every scenario and algorithm, the timed command; the table, goals and bench.json."""
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    lines = [
        "| scenario | algorithm | rollouts to hit: median [q1, q3] | mean | hit rate "
        "| final ‖r‖ (cm) | time (s) | paper |",
        "|---|---|---|---|---|---|---|---|",
    ]
    results: dict[str, dict] = {}
    for scenario_name, scenario in SCENARIOS.items():
        config = ExperimentConfig(
            algorithms=ALGORITHM_ORDER,
            sessions=args.sessions,
            rollouts=args.rollouts,
            seed=args.seed,
            scenario=scenario,
        )
        runs: dict[str, AlgorithmRun] = {}
        for name in ALGORITHM_ORDER:
            runs[name] = run_algorithm(config, name)
        summary = summarise(config, runs)
        results[scenario_name] = summary
        for name in ALGORITHM_ORDER:
            lines.append(_row(scenario_name, name, summary["algorithms"][name], args.sessions))
        shown = dataclasses.replace(config, algorithms=FIGURE_ALGORITHMS)
        write_outputs(
            out / _slug(scenario_name), shown, {name: runs[name] for name in FIGURE_ALGORITHMS}
        )
        print(f"done: {scenario_name}", file=sys.stderr, flush=True)

    command_time = _time_default_command(
        out / "default-command", args.sessions, args.rollouts, args.seed
    )
    paper = results["paper (2.2 m)"]["algorithms"]
    goals = []
    for name in ("archer", "archer-plain", "archer-iso", "archer-plain-iso"):
        a = paper[name]
        met = a["rollouts_to_hit"]["median"] <= 4 and a["hits"] == args.sessions
        goals.append(
            f"ARCHER goal (median <= 4, {args.sessions}/{args.sessions} hit) with {name}: "
            f"{'met' if met else 'NOT met'} (median {a['rollouts_to_hit']['median']:g}, "
            f"{a['hits']}/{args.sessions}; paper: {PAPER_ROLLOUTS['archer']})"
        )
    for name in ("power", "power-metre"):
        h = paper[name]["rollouts_to_hit"]
        met = abs(h["median"] - PAPER_ROLLOUTS["power"]) <= 3 and not h["median_censored"]
        goals.append(
            f"PoWER goal (median within {PAPER_ROLLOUTS['power']} ± 3) with {name}: "
            f"{'met' if met else 'NOT met'} (median {format_count(h, 'median')}, "
            f"{paper[name]['hits']}/{args.sessions} hit)"
        )
    default_time = sum(paper[name]["wall_time_s"] for name in DEFAULT_COMMAND_ALGORITHMS)
    timing = (
        f"wall time of `archery experiment` with the defaults ({args.sessions} sessions × "
        f"{args.rollouts} rollouts × {len(DEFAULT_COMMAND_ALGORITHMS)} algorithms): "
        f"{command_time:.2f} s as a fresh process (imports, learning, files, figures); "
        f"learning and simulation alone {default_time:.2f} s"
    )
    print("\n".join(lines))
    print()
    print("\n".join(goals))
    print(timing)
    hit_rates = {
        s: {n: r["algorithms"][n]["hit_rate"] for n in ALGORITHM_ORDER} for s, r in results.items()
    }
    (out / "bench.json").write_text(
        json.dumps(
            {
                "results": results,
                "goals": goals,
                "command_wall_time_s": command_time,
                "hit_rates": hit_rates,
                "labels": {n: ALGORITHMS[n].label for n in ALGORITHM_ORDER},
                "numpy": np.__version__,
            },
            indent=2,
        )
        + "\n"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
