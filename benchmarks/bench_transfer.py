"""Benchmark of transfer: rollouts to the 5 cm ring when a session starts from another's model.

Run `python -m benchmarks.bench_transfer [--sessions 40]`. On the ballistic world, archer-prior
and archer learn at 2.2 m (the learner's nominal model), then new sessions at 3 m and with a
stiffer bow (420 N/m) start either from scratch or from the 2.2 m session of the same index
(`ExperimentConfig.transfer`, what `archery experiment --from DIR` does). A last pair learns with
the stiff bow at 2.2 m, where archer-prior's model is wrong, and transfers to the stiff bow at
3 m. Prints the table; writes bench.json under --out.

`--smoke`: every pair, start and learner on 2 sessions of 10 rollouts (seconds; its figures are
noise), bench.json in a temporary directory, removed after.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

from archery.apps.experiment.config import ExperimentConfig, Transfer
from archery.apps.experiment.experiment import run_algorithm
from archery.sim.ballistic import Scenario

__all__ = ["PAIRS", "main"]

ALGORITHMS = ("archer-prior", "archer")
# (source label, source world, target label, target world)
PAIRS = (
    ("2.2 m", Scenario(), "target at 3 m", Scenario(distance=3.0)),
    ("2.2 m", Scenario(), "stiffer bow 420 N/m", Scenario(bow_stiffness=420.0)),
    (
        "bow 420 N/m at 2.2 m",
        Scenario(bow_stiffness=420.0),
        "bow 420 N/m at 3 m",
        Scenario(bow_stiffness=420.0, distance=3.0),
    ),
)


def _quartiles(values: np.ndarray) -> str:
    q1, median, q3 = np.percentile(values, [25, 50, 75])
    return f"{median:g} [{q1:g}, {q3:g}]"


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark, print the table, write bench.json under --out."""
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.bench_transfer", description=__doc__
    )
    parser.add_argument("--out", default="runs/bench-transfer", help="output directory")
    parser.add_argument("--sessions", type=int, default=40)
    parser.add_argument("--rollouts", type=int, default=60, help="budget of every session")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--smoke",
        action="store_true",
        help="2 sessions of 10 rollouts, output in a temporary directory: no figures",
    )
    args = parser.parse_args(argv)
    if args.smoke:
        args.sessions, args.rollouts = 2, 10
        with tempfile.TemporaryDirectory(prefix="bench-transfer-") as tmp:
            return _run(args, Path(tmp))
    return _run(args, Path(args.out))


def _run(args: argparse.Namespace, out: Path) -> int:
    """Every pair at the budgets of `args`; the table printed, bench.json under `out`."""
    table = [
        "| learned at | new world | algorithm | start | first shot ‖r‖ (cm): median "
        "| rollouts to hit: median [q1, q3] | sessions hit |",
        "|---|---|---|---|---|---|---|",
    ]
    results = []
    sources: dict[str, Transfer] = {}
    for source_label, source, target_label, target in PAIRS:
        if source_label not in sources:
            config = ExperimentConfig(
                ALGORITHMS, args.sessions, args.rollouts, args.seed, scenario=source
            )
            states = {name: run_algorithm(config, name).states for name in ALGORITHMS}
            sources[source_label] = Transfer(source_label, states)
        for name in ALGORITHMS:
            for start, transfer in (("scratch", None), ("transfer", sources[source_label])):
                config = ExperimentConfig(
                    (name,),
                    args.sessions,
                    args.rollouts,
                    args.seed + 1,  # other noise and learner seeds than the source sessions
                    scenario=target,
                    transfer=transfer,
                )
                run = run_algorithm(config, name)
                to_hit = run.rollouts_to_hit()
                first = 100 * float(np.median(run.distances[:, 0]))
                hits = int(np.sum(to_hit <= args.rollouts))
                table.append(
                    f"| {source_label} | {target_label} | {name} | {start} | {first:.1f} "
                    f"| {_quartiles(to_hit)} | {hits}/{args.sessions} |"
                )
                results.append(
                    {
                        "source": source_label,
                        "target": target_label,
                        "algorithm": name,
                        "start": start,
                        "rollouts_to_hit": to_hit.tolist(),
                        "first_r_cm": first,
                    }
                )
    print("\n".join(table))
    out.mkdir(parents=True, exist_ok=True)
    (out / "bench.json").write_text(json.dumps(results, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
