"""Benchmark of the task as a Gymnasium environment (`apps.gym`).

Run `python -m benchmarks.bench_gym [--repeats 5] [--steps 3000] [--sessions 40]
[--robot-shots 12] [--only steps|learners|robot] [--smoke]`. Three figures, each over
`--repeats` interleaved repeats (the order of the two conditions alternating), median [min,
max]:

1. Steps per second of `archery/Aim-v0` in one process (`gymnasium.make`, with Gymnasium's
   order and passive checks, and the bare `AimEnv`) against calling the ballistic model
   directly (`BallisticWorld.step`) on the same θ: the overhead ratio per repeat.
2. Rollouts to the 5 cm ring through the environment, median [q1, q3] of `--sessions`
   sessions, for ARCHER, PoWER, pycma's CMA-ES and NGOpt (`archery compare`'s run), beside
   `archery experiment`'s figures for ARCHER and PoWER (the same seeds); and the wall time of
   the compare run of ARCHER and PoWER against the experiment's lockstep run of the same.
3. `archery/AimRobot-v0`'s wall time per step against `archery learn`'s per rollout (the
   learner service's session, journaled), ARCHER on a whole mesh (robot at rtf 0) started here,
   `--robot-shots` shots each (no stop at a hit), the first left out of both (it includes the
   move from home); goal ≤ 1.1×.

`--smoke`: every part at its smallest budget (one repeat; the figures are noise).
"""

from __future__ import annotations

import argparse
import itertools
import os
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from archery.apps.compare.compare import compare
from archery.apps.experiment.censored import count_stats, format_counts
from archery.apps.experiment.config import ExperimentConfig
from archery.apps.experiment.experiment import run_algorithm
from archery.apps.gym.agent import run_learner
from archery.apps.gym.aim import AimEnv
from archery.apps.gym.registration import AIM_ID, AIM_ROBOT_ID
from archery.apps.learn.follow import follow
from archery.protocol.journal_records import DoneRecord
from archery.services.learner.journal import read_records
from archery.sim.ballistic import BallisticWorld
from benchmarks.learning_mesh import learning_mesh
from benchmarks.machine import cpu_model
from benchmarks.spread import median_spread
from tests.rpc import rpc_call

__all__ = ["main"]

METHODS = ("archer", "power", "pycma", "ngopt")
PARTS = ("steps", "learners", "robot")


def _order(k: int, pair: tuple[str, str]) -> tuple[str, str]:
    return pair if k % 2 == 0 else (pair[1], pair[0])


def _step_rates(repeats: int, steps: int) -> None:
    rng = np.random.default_rng(0)
    low, high = np.array([0.15, -0.05, -0.05]), np.array([0.25, 0.05, 0.05])
    thetas = rng.uniform(low, high, size=(steps, 3))
    world = BallisticWorld()
    made = gym.make(AIM_ID, until_hit=False, budget=steps)
    bare = AimEnv(until_hit=False, budget=steps)

    def direct() -> float:
        world.reset(0)
        start = time.perf_counter()
        for theta in thetas:
            world.step(theta)
        return steps / (time.perf_counter() - start)

    def through(env: gym.Env[Any, Any]) -> float:
        env.reset(seed=0)
        start = time.perf_counter()
        for theta in thetas:
            env.step(theta)
        return steps / (time.perf_counter() - start)

    rates: dict[str, list[float]] = {"direct": [], "make": [], "bare": []}
    ratios: dict[str, list[float]] = {"make": [], "bare": []}
    for k in range(repeats):
        for name in _order(k, ("direct", "env")):
            if name == "direct":
                rates["direct"].append(direct())
            else:
                rates["make"].append(through(made))
                rates["bare"].append(through(bare))
        ratios["make"].append(rates["direct"][-1] / rates["make"][-1])
        ratios["bare"].append(rates["direct"][-1] / rates["bare"][-1])
    print(f"\n### Steps per second ({steps} shots a repeat, {repeats} interleaved repeats)\n")
    print("| path | steps/s | time per step against the model |\n|---|---|---|")
    print(f"| `BallisticWorld.step` (the model) | {median_spread(rates['direct'], '.0f')} | 1 |")
    print(
        f"| `AimEnv.step` (the bare environment) | {median_spread(rates['bare'], '.0f')} | "
        f"**{median_spread(ratios['bare'], '.3f')}×** |"
    )
    print(
        f'| `gymnasium.make("{AIM_ID}")` (with its checks) | '
        f"{median_spread(rates['make'], '.0f')} | **{median_spread(ratios['make'], '.3f')}×** |"
    )


def _learners(repeats: int, sessions: int, rollouts: int) -> None:
    config = ExperimentConfig(algorithms=("archer", "power"), sessions=sessions, rollouts=rollouts)
    runs: dict[str, Any] = {}
    walls: dict[str, list[float]] = {"compare": [], "experiment": []}
    for k in range(repeats):
        for name in _order(k, ("compare", "experiment")):
            start = time.perf_counter()
            if name == "compare":
                env = gym.make(AIM_ID, until_hit=False, budget=rollouts)
                compare(env, ("archer", "power"), sessions, rollouts, 0)
            else:
                for algo in config.algorithms:
                    runs[algo] = run_algorithm(config, algo)
            walls[name].append(time.perf_counter() - start)
    env = gym.make(AIM_ID, until_hit=False, budget=rollouts)
    through = compare(env, METHODS, sessions, rollouts, 0)
    print(f"\n### Rollouts to the 5 cm ring, {sessions} sessions × {rollouts} rollouts, seed 0\n")
    print("| learner | through `archery/Aim-v0` | `archery experiment` | hits |\n|---|---|---|---|")
    for name, run in through.items():
        stats = count_stats(run.rollouts_to_hit(), rollouts)
        beside = "–"
        if name in runs:
            beside = format_counts(count_stats(runs[name].rollouts_to_hit(), rollouts))
        hits = sessions - stats["censored_sessions"]
        print(f"| {name} | {format_counts(stats)} | {beside} | {hits}/{sessions} |")
    ratio = [c / e for c, e in zip(walls["compare"], walls["experiment"], strict=True)]
    print(
        f"\nWall time of ARCHER and PoWER, {sessions} sessions each: through the environment "
        f"{median_spread(walls['compare'], '.2f', ' s')}, the experiment's lockstep run "
        f"{median_spread(walls['experiment'], '.2f', ' s')}: **{median_spread(ratio, '.2f')}×** "
        f"({repeats} interleaved repeats)"
    )


def _robot(repeats: int, shots: int) -> None:
    per_step: list[float] = []
    per_rollout: list[float] = []
    ratios: list[float] = []
    with (
        tempfile.TemporaryDirectory(prefix="bench-gym-") as tmp,
        learning_mesh(Path(tmp)) as (node, rollouts),
    ):
        env = gym.make(
            AIM_ROBOT_ID,
            endpoint=node.net.connect[0],
            robot=node.keys.robot,
            budget=shots,
            until_hit=False,
        )
        try:
            for k in range(repeats):
                step_ms: list[float] = []
                roll_ms: list[float] = []
                for name in _order(k, ("env", "learn")):
                    if name == "env":
                        stamps: list[float] = []
                        run_learner(
                            env,
                            "archer",
                            seed=k,
                            rng=np.random.default_rng(k),
                            on_step=lambda shot, info, s=stamps: s.append(time.perf_counter()),
                        )
                        step_ms = [1e3 * (b - a) for a, b in itertools.pairwise(stamps)]
                    else:
                        request = {"algo": "archer", "seed": k, "rollouts": shots}
                        request |= {"until_hit": False}
                        key = node.keys.learner_rpc()
                        session = rpc_call(node, key, "start", request, timeout=60)["session"]
                        final = follow(node, session, rollouts, lambda m: None, poll=0.2)
                        records = read_records(Path(final["journal"]))[0]
                        done = [r for r in records if isinstance(r, DoneRecord)]
                        roll_ms = [1e3 * (b.t - a.t) for a, b in itertools.pairwise(done)]
                per_step.append(statistics.median(step_ms))
                per_rollout.append(statistics.median(roll_ms))
                ratios.append(per_step[-1] / per_rollout[-1])
                print(
                    f"repeat {k + 1}: env {per_step[-1]:.1f} ms/step, learn "
                    f"{per_rollout[-1]:.1f} ms/rollout",
                    flush=True,
                )
        finally:
            env.close()
    ratio = median_spread(ratios, ".3f")
    goal = "met" if statistics.median(ratios) <= 1.1 else "not met"
    print(f"\n### `{AIM_ROBOT_ID}` against `archery learn` ({repeats} repeats × {shots} shots)\n")
    print("| path | ms per shot (median of a repeat's; median [min, max]) |\n|---|---|")
    print(f"| `{AIM_ROBOT_ID}` step, ARCHER via `run_learner` | {median_spread(per_step, '.1f')} |")
    print(
        f"| `archery learn` rollout (the learner service) | {median_spread(per_rollout, '.1f')} |"
    )
    print(f"\nenvironment / learn: **{ratio}×**; goal ≤ 1.1×: **{goal}**")


def main(argv: list[str] | None = None) -> int:
    """Run the three parts; print markdown for RESULTS.md."""
    parser = argparse.ArgumentParser(prog="python -m benchmarks.bench_gym", description=__doc__)
    parser.add_argument("--repeats", type=int, default=5, help="interleaved repeats (≥ 5)")
    parser.add_argument("--steps", type=int, default=3000, help="shots per step-rate repeat")
    parser.add_argument("--sessions", type=int, default=40, help="sessions per learner")
    parser.add_argument("--robot-shots", type=int, default=12, help="shots per robot repeat")
    parser.add_argument(
        "--only", choices=PARTS, action="append", help="run only this part (repeatable)"
    )
    parser.add_argument("--smoke", action="store_true", help="every part at its smallest budget")
    args = parser.parse_args(argv)
    if args.smoke:
        args.repeats, args.steps, args.sessions, args.robot_shots = 1, 50, 2, 3
    print(
        f"- {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, {os.cpu_count()} cores, "
        f"{cpu_model()}, Python {platform.python_version()}: `python -m benchmarks.bench_gym "
        f"{' '.join(sys.argv[1:] if argv is None else argv)}`"
    )
    parts = args.only or PARTS
    if "steps" in parts:
        _step_rates(args.repeats, args.steps)
    if "learners" in parts:
        _learners(args.repeats, args.sessions, 8 if args.smoke else 60)
    if "robot" in parts:
        _robot(args.repeats, args.robot_shots)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
