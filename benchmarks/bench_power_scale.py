"""Benchmark of PoWER's return scale s in R = exp(−‖r‖/s) on the paper's ballistic scenario.

Run `python -m benchmarks.bench_power_scale [--out DIR]`. For every master seed (5 by default,
interleaved: each seed runs every scale before the next seed starts) and every scale, PoWER
runs the paper's experiment (40 sessions × 60 rollouts, 2.2 m, no drag, no noise); the table
gives, per scale, the median rollouts to hit [quartiles] and the hit rate of seed 0 (what
`archery experiment` shows), the median of the five seeds' medians with their range, and its
ratio to the paper's 19 and to s = 1 m (‖r‖ in metres, the baseline). The goal: the default
scale (`services.learner.algorithms.power.DEFAULT_RETURN_SCALE`) is within 19 ± 3.

`--smoke`: every scale on 1 seed of 2 sessions × 20 rollouts (seconds; its figures are noise),
bench.json in a temporary directory, removed after.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from archery.apps.experiment.censored import count_stats, format_counts
from archery.apps.experiment.config import ExperimentConfig
from archery.apps.experiment.experiment import run_algorithm
from archery.services.learner.algorithms.power import DEFAULT_RETURN_SCALE
from benchmarks.machine import cpu_model

__all__ = ["PAPER_POWER", "SCALES", "main"]

PAPER_POWER = 19  # the paper's Fig. 5: PoWER's rollouts to the 5 cm ring
TOLERANCE = 3  # rollouts either side of it
SCALES = (1.0, 0.5, 0.2, 0.1, 0.05, 0.03, 0.02, 0.01, 0.005)  # m
BASELINE = 1.0  # m: ‖r‖ in metres, Eq. 1 read literally


def _scale_text(scale: float) -> str:
    return f"{scale:g} m" if scale >= 1 else f"{100 * scale:g} cm"


def sweep(
    scales: tuple[float, ...], seeds: int, sessions: int, rollouts: int
) -> dict[float, list[dict]]:
    """Per scale, the rollouts-to-hit statistics of each master seed 0 … seeds − 1."""
    results: dict[float, list[dict]] = {scale: [] for scale in scales}
    for seed in range(seeds):  # interleaved: every scale once per seed
        for scale in scales:
            config = ExperimentConfig(
                algorithms=("power",),
                sessions=sessions,
                rollouts=rollouts,
                seed=seed,
                power_scale=scale,
            )
            run = run_algorithm(config, "power")
            stats = count_stats(run.rollouts_to_hit(), rollouts)
            stats["hit_rate"] = 1 - stats["censored_sessions"] / sessions
            results[scale].append(stats)
        print(f"done: seed {seed}", file=sys.stderr, flush=True)
    return results


def main(argv: list[str] | None = None) -> int:
    """Run the sweep, print the table and the goal, write bench.json under --out."""
    parser = argparse.ArgumentParser(prog="python -m benchmarks.bench_power_scale")
    parser.add_argument("--out", default="runs/bench-power-scale", help="output directory")
    parser.add_argument("--seeds", type=int, default=5, help="master seeds (repeats, >= 5)")
    parser.add_argument("--sessions", type=int, default=40)
    parser.add_argument("--rollouts", type=int, default=60)
    parser.add_argument(
        "--smoke",
        action="store_true",
        help="every scale, 1 seed of 2 sessions × 20 rollouts, output in a temporary directory",
    )
    args = parser.parse_args(argv)
    if args.smoke:
        args.seeds, args.sessions, args.rollouts = 1, 2, 20
        with tempfile.TemporaryDirectory(prefix="bench-power-scale-") as tmp:
            return _run(args, Path(tmp))
    return _run(args, Path(args.out))


def _run(args: argparse.Namespace, out: Path) -> int:
    """The sweep of `args`; the table and goal printed, bench.json under `out`."""
    out.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    results = sweep(SCALES, args.seeds, args.sessions, args.rollouts)
    wall = time.perf_counter() - start

    def medians(scale: float) -> np.ndarray:
        return np.array([s["median"] for s in results[scale]])

    baseline = float(np.median(medians(BASELINE)))
    lines = [
        f"| s | seed 0: rollouts to hit, median [q1, q3] | seed 0: hit rate "
        f"| median over {args.seeds} seeds [min, max] | ÷ paper ({PAPER_POWER}) "
        f"| ÷ s = 1 m | within {PAPER_POWER} ± {TOLERANCE} |",
        "|---|---|---|---|---|---|---|",
    ]
    summary = {}
    for scale in SCALES:
        first = results[scale][0]
        m = medians(scale)
        overall = float(np.median(m))
        censored = any(s["median_censored"] for s in results[scale])
        within = abs(overall - PAPER_POWER) <= TOLERANCE and not censored
        spread = f"[{m.min():g}, {m.max():g}]"
        if censored:
            spread += f" ({args.rollouts + 1}: a median > {args.rollouts} among them)"
        default = " (default)" if scale == DEFAULT_RETURN_SCALE else ""
        lines.append(
            f"| {_scale_text(scale)}{default} | {format_counts(first)} "
            f"| {round(first['hit_rate'] * args.sessions)}/{args.sessions} "
            f"| {overall:g} {spread} | {overall / PAPER_POWER:.2f} | {overall / baseline:.2f} "
            f"| {'yes' if within else 'no'} |"
        )
        summary[str(scale)] = {
            "per_seed": results[scale],
            "median_of_medians": overall,
            "within": within,
        }
    closest = min(SCALES, key=lambda s: abs(summary[str(s)]["median_of_medians"] - PAPER_POWER))
    default_median = summary[str(DEFAULT_RETURN_SCALE)]["median_of_medians"]
    met = summary[str(DEFAULT_RETURN_SCALE)]["within"]
    goal = (
        f"goal: the default s = {_scale_text(DEFAULT_RETURN_SCALE)} within {PAPER_POWER} ± "
        f"{TOLERANCE}: {'met' if met else 'NOT met'} (median over seeds {default_median:g}); "
        f"the scale closest to {PAPER_POWER}: {_scale_text(closest)}"
    )
    print("\n".join(lines))
    print()
    print(goal)
    print(
        f"{len(SCALES)} scales × {args.seeds} seeds × {args.sessions} sessions × "
        f"{args.rollouts} rollouts in {wall:.1f} s; {cpu_model()}, Python "
        f"{platform.python_version()}"
    )
    (out / "bench.json").write_text(
        json.dumps(
            {"scales": summary, "goal": goal, "closest": closest, "wall_time_s": wall}, indent=2
        )
        + "\n"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
