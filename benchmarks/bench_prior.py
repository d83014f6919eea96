"""Benchmark of archer-prior: rollouts to the 5 cm ring with the ballistic model as a prior.

Run `python -m benchmarks.bench_prior [--sessions 40] [--robot-sessions 40] [--before COMMIT]`.
Four parts (`--parts`, default all):

* the ballistic world, the paper's range and ranges whose physics differ from the learner's
  nominal model (2.2 m, 300 N/m bow, no drag): archer-prior, archer and power in the same run;
* a changing world: the wind turns at rollout 30; rollouts to hit again for every algorithm
  (archer-recent is ARCHER choosing the N best among the 4 most recent rollouts);
* ranges: archer-prior on targets from 1.5 to 5 m with drag and a side wind, one row per
  distance, this tree beside the earlier commit `--before` (`benchmarks.prior_ranges`);
* the MuJoCo iCub over the mesh (a router and the five services as child processes, as in
  `benchmarks.bench_loop`): one session per seed until the first hit, with archer-prior on its
  nominal model and on deliberately wrong ones (a 3 m target, a 40 % stiffer bow), archer and
  power. The robot's bow is the same spring model as the analytic one, but its hands, arrow and
  release are MuJoCo's.

Writes summary.json, curves.csv and the figures of each ballistic part, and bench.json, under
--out; prints the tables.

`--smoke` runs every part at its smallest budget, its figures noise: the scenarios and the
wind change on 1 session of 31 rollouts (the change at rollout 30, one rollout after it; the
plots of the first scenario alone), the ranges on 1 session of 2 rollouts per distance against
the `--before` tree (still extracted and run: the comparison path), and one robot session of 2
rollouts per robot learner on the whole mesh; everything it writes goes to a temporary
directory, removed after.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from archery.apps.experiment.config import AlgorithmRun, ExperimentConfig, WindChange
from archery.apps.experiment.experiment import run_algorithm, write_outputs
from archery.services.learner.algorithms.registry import ALGORITHMS
from archery.sim.ballistic import Scenario
from benchmarks.learning_mesh import learning_mesh, progress_bar
from benchmarks.prior_ranges import AIRS, range_rows, range_table
from benchmarks.trees import ROOT, header, tree_at
from tests.rpc import rpc_call

__all__ = ["CHANGE", "ROBOT_VARIANTS", "SCENARIOS", "main"]

SCENARIOS: dict[str, Scenario] = {
    "paper (2.2 m)": Scenario(),
    "drag 0.1/m + wind 0,6,0 m/s": Scenario(drag=0.1, wind=(0.0, 6.0, 0.0)),
    "drag 0.05/m + headwind 4,0,0 m/s": Scenario(drag=0.05, wind=(4.0, 0.0, 0.0)),
    "target at 3 m": Scenario(distance=3.0),
    "stiffer bow 420 N/m": Scenario(bow_stiffness=420.0),
    "noise σ=2 cm": Scenario(noise=0.02),
    "target at 5 m": Scenario(distance=5.0),
}
ALGORITHM_ORDER = ("archer-prior", "archer", "power")
CHANGE_SCENARIO = Scenario(drag=0.05, wind=(0.0, 3.0, 0.0))
CHANGE = WindChange(30, (0.0, -6.0, 0.0))
CHANGE_ALGORITHMS = ("archer-prior", "archer", "archer-recent", "power")
# (label, algorithm, learner options) of the robot sessions.
ROBOT_VARIANTS: tuple[tuple[str, str, dict[str, Any]], ...] = (
    ("archer-prior (nominal model)", "archer-prior", {}),
    ("archer-prior (model: target at 3 m)", "archer-prior", {"model_distance": 3.0}),
    ("archer-prior (model: bow 420 N/m)", "archer-prior", {"model_stiffness": 420.0}),
    ("archer", "archer", {}),
    ("power", "power", {}),
)
ROBOT_BUDGET = {"archer-prior": 30, "archer": 30, "power": 60}
SMOKE_ROBOT_BUDGET = 2  # rollouts of a robot session in the smoke run


def _slug(name: str) -> str:
    return "".join(c if c.isalnum() else "-" for c in name).strip("-").replace("--", "-")


def _quartiles(values: np.ndarray) -> str:
    q1, median, q3 = np.percentile(values, [25, 50, 75])
    return f"{median:g} [{q1:g}, {q3:g}]"


def _run_ballistic(
    args: argparse.Namespace, out: Path
) -> tuple[list[str], list[str], dict[str, Any]]:
    configs = [
        (
            name,
            ExperimentConfig(
                algorithms=ALGORITHM_ORDER,
                sessions=args.sessions,
                rollouts=args.rollouts,
                seed=args.seed,
                scenario=scenario,
            ),
        )
        for name, scenario in SCENARIOS.items()
    ]
    change = ExperimentConfig(
        algorithms=CHANGE_ALGORITHMS,
        sessions=args.sessions,
        rollouts=args.rollouts,
        seed=args.seed,
        scenario=CHANGE_SCENARIO,
        wind_change=CHANGE,
    )
    configs.append(("wind change", change))
    total = sum(len(c.algorithms) * c.rollouts for _, c in configs)
    table = [
        "| scenario | first shot ‖r‖ (cm) | algorithm | rollouts to hit: median [q1, q3] "
        "| sessions hit | final ‖r‖ (cm) | time (s) |",
        "|---|---|---|---|---|---|---|",
    ]
    change_table = [
        f"| algorithm | rollouts to hit: median [q1, q3] | to hit again after the change at "
        f"rollout {CHANGE.at}: median [q1, q3] | sessions hitting again | final ‖r‖ (cm) |",
        "|---|---|---|---|---|",
    ]
    results: dict[str, Any] = {}
    with progress_bar(disable=args.no_progress) as bar:
        task = bar.add_task("ballistic", total=total)
        for index, (scenario_name, config) in enumerate(configs):
            runs: dict[str, AlgorithmRun] = {}
            for name in config.algorithms:
                bar.update(task, description=f"{scenario_name[:24]:>24}: {name:>13}")
                runs[name] = run_algorithm(config, name, lambda: bar.advance(task))
            figures = not args.smoke or index == 0  # the smoke run plots the first alone
            summary = write_outputs(out / _slug(scenario_name), config, runs, figures=figures)
            results[scenario_name] = summary
            for name, run in runs.items():
                a = summary["algorithms"][name]
                to_hit = run.rollouts_to_hit()
                final = 100 * run.distances[:, -1]
                if config.wind_change is None:
                    first = 100 * float(np.median(runs["archer-prior"].distances[:, 0]))
                    table.append(
                        f"| {scenario_name} | {first:.1f} | {name} | {_quartiles(to_hit)} "
                        f"| {a['hits']}/{config.sessions} | {final.mean():.1f} ± {final.std():.1f} "
                        f"| {run.wall_time:.2f} |"
                    )
                else:
                    rehit = run.rollouts_to_rehit(CHANGE.at)
                    change_table.append(
                        f"| {name} | {_quartiles(to_hit)} | {_quartiles(rehit)} "
                        f"| {a['rehits']}/{config.sessions} | {final.mean():.1f} ± "
                        f"{final.std():.1f} |"
                    )
    return table, change_table, results


def _robot_session(
    node: Any, rollouts: Any, algo: str, options: dict[str, Any], seed: int, budget: int
) -> dict[str, Any]:
    from archery.apps.learn.follow import follow
    from archery.protocol.journal_records import DoneRecord
    from archery.services.learner.journal import read_records

    request = {"algo": algo, "seed": seed, "rollouts": budget, "options": options}
    start = time.perf_counter()
    session = rpc_call(node, node.keys.learner_rpc(), "start", request, timeout=60)["session"]
    final = follow(node, session, rollouts, lambda m: None, poll=0.2)
    final["wall_s"] = time.perf_counter() - start
    done = [r for r in read_records(Path(final["journal"]))[0] if isinstance(r, DoneRecord)]
    final["first_r_cm"] = 100 * float(np.linalg.norm(done[0].r_m)) if done else None
    return final


def _budget(args: argparse.Namespace, algo: str) -> int:
    """A robot session's rollout budget: `ROBOT_BUDGET`'s, or the smoke run's."""
    return SMOKE_ROBOT_BUDGET if args.smoke else ROBOT_BUDGET[algo]


def _run_robot(args: argparse.Namespace, out: Path) -> tuple[list[str], dict[str, Any]]:
    finals: dict[str, list[dict[str, Any]]] = {}
    with learning_mesh(out) as (node, rollouts), progress_bar(disable=args.no_progress) as bar:
        task = bar.add_task("robot", total=len(ROBOT_VARIANTS) * args.robot_sessions)
        for label, algo, options in ROBOT_VARIANTS:
            bar.update(task, description=f"robot: {label}")
            for seed in range(args.robot_sessions):
                final = _robot_session(node, rollouts, algo, options, seed, _budget(args, algo))
                finals.setdefault(label, []).append(final)
                bar.advance(task)
    table = [
        "| robot learner | first shot ‖r‖ (cm): median [max] | rollouts to the 5 cm ring: "
        "median [q1, q3] | sessions hit | aborted attempts |",
        "|---|---|---|---|---|",
    ]
    summary: dict[str, Any] = {}
    for label, algo, _ in ROBOT_VARIANTS:
        runs = finals[label]
        budget = _budget(args, algo)
        to_hit = np.array([f["hit_at"] if f["hit_at"] is not None else budget + 1 for f in runs])
        first = np.array([f["first_r_cm"] for f in runs if f["first_r_cm"] is not None])
        hits = sum(f["hit_at"] is not None for f in runs)
        aborted = sum(f["aborted"] for f in runs)
        table.append(
            f"| {label} | {np.median(first):.1f} [{first.max():.1f}] | {_quartiles(to_hit)} "
            f"| {hits}/{len(runs)} | {aborted} |"
        )
        summary[label] = {
            "rollouts_to_hit": to_hit.tolist(),
            "first_r_cm": first.tolist(),
            "hits": hits,
            "aborted": aborted,
            "sessions": [f["session"] for f in runs],
        }
    return table, summary


def _run_ranges(args: argparse.Namespace) -> tuple[list[str], list[str], dict[str, Any]]:
    """The range tables of every air, this tree beside `args.before`."""
    tables: list[str] = []
    goals: list[str] = []
    results: dict[str, Any] = {}
    common = {
        "sessions": args.range_sessions,
        "rollouts": args.range_rollouts,
        "seed": args.seed,
    }
    with tempfile.TemporaryDirectory() as tmp:
        before = tree_at(args.before, Path(tmp))
        for label, drag, wind in AIRS:
            rows = {
                name: range_rows(tree, drag=drag, wind=wind, **common)
                for name, tree in ((args.before, before), ("this tree", ROOT))
            }
            table, met = range_table(
                label,
                (args.before, rows[args.before]),
                rows["this tree"],
                sessions=args.range_sessions,
                budget=args.range_rollouts,
            )
            tables += [*table, ""]
            goals += met
            results[label] = rows
    return tables, goals, results


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark, print the tables, write the figures and bench.json under --out."""
    parser = argparse.ArgumentParser(prog="python -m benchmarks.bench_prior", description=__doc__)
    parser.add_argument("--out", default="runs/bench-prior", help="output directory")
    parser.add_argument("--sessions", type=int, default=40, help="ballistic sessions")
    parser.add_argument("--rollouts", type=int, default=60, help="ballistic rollout budget")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--robot-sessions", type=int, default=40, help="robot sessions per learner (0: none)"
    )
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bars")
    parser.add_argument(
        "--before", default="0d1273b", help="the earlier commit of the range tables' baseline"
    )
    parser.add_argument("--range-sessions", type=int, default=40, help="sessions per range")
    parser.add_argument("--range-rollouts", type=int, default=20, help="budget per range session")
    parser.add_argument(
        "--parts",
        default="scenarios,ranges,robot",
        help="comma-separated parts to run: scenarios (with the wind change), ranges, robot",
    )
    parser.add_argument(
        "--smoke",
        action="store_true",
        help="every part at its smallest budget, output in a temporary directory: no figures",
    )
    args = parser.parse_args(argv)
    parts = set(args.parts.split(","))
    unknown = parts - {"scenarios", "ranges", "robot"}
    if unknown:
        parser.error(f"--parts: unknown part(s) {', '.join(sorted(unknown))}")
    if args.smoke:
        args.sessions, args.rollouts = 1, CHANGE.at + 1
        args.range_sessions, args.range_rollouts = 1, 2
        args.robot_sessions = 1
        with tempfile.TemporaryDirectory(prefix="bench-prior-") as tmp:
            return _run(args, parts, Path(tmp))
    return _run(args, parts, Path(args.out))


def _run(args: argparse.Namespace, parts: set[str], out: Path) -> int:
    """The `parts` of the benchmark at the budgets of `args`; the tables printed, the figures
    and bench.json under `out`."""
    out.mkdir(parents=True, exist_ok=True)
    header()
    results: dict[str, Any] = {}
    goals: list[str] = []
    if "scenarios" in parts:
        results, goals = _scenarios_part(args, out)
    ranges: dict[str, Any] = {}
    if "ranges" in parts:
        range_tables, range_goals, ranges = _run_ranges(args)
        print()
        print("\n".join(range_tables))
        print("\n".join(range_goals))
        goals += range_goals
    robot: dict[str, Any] = {}
    if "robot" in parts and args.robot_sessions > 0:
        robot_table, robot = _run_robot(args, out / "robot")
        print()
        print("\n".join(robot_table))
    (out / "bench.json").write_text(
        json.dumps(
            {
                "ballistic": results,
                "ranges": ranges,
                "goals": goals,
                "robot": robot,
                "labels": {n: ALGORITHMS[n].label for n in (*ALGORITHM_ORDER, "archer-recent")},
            },
            indent=2,
        )
        + "\n"
    )
    return 0


def _scenarios_part(args: argparse.Namespace, out: Path) -> tuple[dict[str, Any], list[str]]:
    """Run and print the scenario tables and the wind change; (results, goal lines)."""
    table, change_table, results = _run_ballistic(args, out)
    print("\n".join(table))
    print()
    print(
        f"wind {', '.join(f'{w:g}' for w in CHANGE_SCENARIO.wind)} m/s (drag "
        f"{CHANGE_SCENARIO.drag:g}/m), turning to {', '.join(f'{w:g}' for w in CHANGE.wind)} m/s "
        f"at rollout {CHANGE.at}:"
    )
    print("\n".join(change_table))
    goals = []
    for scenario_name in SCENARIOS:
        a = results[scenario_name]["algorithms"]["archer-prior"]
        median = a["rollouts_to_hit"]["median"]
        met = median <= 2 and a["hits"] == args.sessions
        goals.append(
            f"archer-prior goal (median <= 2, {args.sessions}/{args.sessions} hit) on "
            f"{scenario_name}: {'met' if met else 'NOT met'} (median {median:g}, "
            f"{a['hits']}/{args.sessions})"
        )
    print()
    print("\n".join(goals))
    return results, goals


if __name__ == "__main__":
    sys.exit(main())
