"""`archery compare`: ARCHER and PoWER against pycma's CMA-ES and nevergrad's NGOpt, every one
through the task's Gymnasium environment (`archery/Aim-v0`, or `archery/AimRobot-v0` with
`--world mesh`), each over the same sessions: session K of every method sees the world of
`reset(seed=SEED, options={"session": K})`.

Writes into `--out`: `summary.json` (per method, the rollouts to the first hit, ‖r_true‖ < 5 cm:
median, quartiles, mean, hit rate; a session that never hits counts as budget + 1, as
`archery experiment` counts it), `curves.csv` (every shot: θ, r, r_true, m) and `fig6.png`
(the paper's Fig. 6: the median distance per rollout with the interquartile band); prints the
rollouts-to-hit table on stdout. Every session runs its whole budget (no stop at a hit), so
Fig. 6 has every rollout.
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from archery.apps.compare.optimizers import OPTIMIZERS, run_optimizer
from archery.apps.experiment.censored import count_stats, format_counts, format_mean
from archery.apps.experiment.config import CURVE_COLUMNS as EXPERIMENT_COLUMNS
from archery.apps.experiment.config import AlgorithmRun, ExperimentError, number
from archery.apps.gym.agent import run_learner
from archery.apps.gym.aim_robot import RobotUnavailable, ServiceLostError, ShotNotMeasured
from archery.apps.gym.registration import AIM_ID, AIM_ROBOT_ID
from archery.apps.progress import progress_bar
from archery.apps.waits import interrupted_line
from archery.mesh.cliargs import (
    ArgumentParser,
    add_force_arg,
    check_new_file,
    check_results_folder,
    check_writable_dir,
)
from archery.mesh.netflags import NetConfig, add_network_args
from archery.protocol.errors import ArcheryError
from archery.protocol.exit_status import BAD_INPUT, FAILURE, INTERRUPTED, for_error
from archery.protocol.vectors import parse_vector
from archery.services.learner.algorithms.base import LearnerError
from archery.services.learner.algorithms.registry import ALGORITHMS
from archery.sim.geometry import INNER_RING_RADIUS

__all__ = ["DEFAULT_METHODS", "build_parser", "compare", "main"]

DEFAULT_METHODS = ("archer", "power", "pycma", "ngopt")
#: (sessions, rollouts) per method when not given: the paper's on the analytic world, a short
#: run on the iCub.
DEFAULT_BUDGETS = {"ballistic": (40, 60), "mesh": (3, 10)}
#: curves.csv: the experiment's columns, each row's method first.
CURVE_COLUMNS = ("method", *EXPERIMENT_COLUMNS[1:])
Advance = Callable[[], None]


def label(name: str) -> str:
    """A method's label for tables and figures."""
    if name in OPTIMIZERS:
        return OPTIMIZERS[name][0]
    return ALGORITHMS[name].label


def compare(
    env: gym.Env[Any, Any],
    methods: Sequence[str],
    sessions: int,
    budget: int,
    seed: int,
    advance: Advance | None = None,
) -> dict[str, AlgorithmRun]:
    """Every method over `sessions` sessions of `env` (made with `budget` shots per episode;
    closed at the end); `advance()` after each shot."""

    def on_step(shot: int, info: dict[str, Any]) -> None:
        if advance is not None:
            advance()

    runs: dict[str, AlgorithmRun] = {}
    try:
        for name in methods:
            start = time.perf_counter()
            thetas = np.full((sessions, budget, 3), np.nan)
            r = np.full((sessions, budget, 2), np.nan)
            r_true = np.full((sessions, budget, 2), np.nan)
            for k in range(sessions):
                if name in OPTIMIZERS:
                    episode = run_optimizer(env, name, seed=seed, session=k, on_step=on_step)
                else:
                    episode = run_learner(env, name, seed=seed, session=k, on_step=on_step)
                n = len(episode.thetas)
                thetas[k, :n], r[k, :n] = episode.thetas, episode.r
                # the world's ground truth where it gives one, else what was measured
                truth = np.where(np.isnan(episode.r_true), episode.r, episode.r_true)
                r_true[k, :n] = truth
            runs[name] = AlgorithmRun(name, thetas, r, r_true, time.perf_counter() - start)
    finally:
        env.close()
    return runs


def summarise(runs: dict[str, AlgorithmRun], run_settings: dict[str, Any]) -> dict[str, Any]:
    """The content of summary.json (see the module docstring)."""
    methods = {}
    for name, run in runs.items():
        budget = run.thetas.shape[1]
        to_hit = run.rollouts_to_hit()
        final = run.distances[:, -1]
        methods[name] = {
            "label": label(name),
            "rollouts_to_hit": count_stats(to_hit, budget),
            "hits": int(np.sum(to_hit <= budget)),
            "hit_rate": float(np.mean(to_hit <= budget)),
            "final_distance": {"mean": float(np.nanmean(final)), "std": float(np.nanstd(final))},
            "wall_time_s": run.wall_time,
        }
    return {"run": run_settings, "hit_radius_m": INNER_RING_RADIUS, "methods": methods}


def write_outputs(
    out: Path, runs: dict[str, AlgorithmRun], summary: dict[str, Any], title: str
) -> None:
    """summary.json, curves.csv and fig6.png into `out`."""
    from archery.apps.experiment.plots import plot_convergence

    out.mkdir(parents=True, exist_ok=True)
    (out / "summary.json").write_text(json.dumps(summary, indent=2, allow_nan=False) + "\n")
    with (out / "curves.csv").open("w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(CURVE_COLUMNS)
        for name, run in runs.items():
            distances = run.distances
            for s in range(run.thetas.shape[0]):
                for k in range(run.thetas.shape[1]):
                    values = (*run.thetas[s, k], *run.r_observed[s, k], *run.r_true[s, k])
                    row = [*values, distances[s, k]]
                    writer.writerow([name, s, k + 1, *(repr(float(v)) for v in row)])
    labels = {name: label(name) for name in runs}
    plot_convergence(runs, labels, out / "fig6.png", title=title)


def print_table(summary: dict[str, Any]) -> None:
    """The rollouts-to-hit table on stdout."""
    from rich.console import Console
    from rich.markup import escape
    from rich.table import Table

    run = summary["run"]
    table = Table(
        title=f"{run['world']} world: {run['sessions']} sessions × {run['rollouts']} rollouts, "
        f"seed {run['seed']}"
    )
    for column in ("method", "to hit: median [q1, q3]", "mean", "hit rate", "final ‖r‖ (m)"):
        table.add_column(escape(column), justify="left" if column == "method" else "right")
    for name, m in summary["methods"].items():
        h = m["rollouts_to_hit"]
        final = m["final_distance"]
        table.add_row(
            escape(name),
            escape(format_counts(h)),
            format_mean(h),
            f"{m['hits']}/{run['sessions']} ({100 * m['hit_rate']:.0f} %)",
            f"{final['mean']:.3f} ± {final['std']:.3f}",
        )
    console = Console()
    console.print(table)
    console.print(
        f"A session that never hits counts as {run['rollouts'] + 1} rollouts: a median or "
        f"quartile on one is shown as > {run['rollouts']}, a mean over them as ≥."
    )


def build_parser() -> argparse.ArgumentParser:
    """The command-line options of `archery compare`."""
    parser = ArgumentParser(
        prog="archery compare",
        description="ARCHER and PoWER against pycma's CMA-ES and nevergrad's NGOpt through the "
        "task's Gymnasium environment; Fig. 6 and the rollouts-to-hit table.",
    )
    add = parser.add_argument
    add(
        "--world",
        choices=tuple(DEFAULT_BUDGETS),
        default="ballistic",
        help="ballistic: archery/Aim-v0, the analytic world (default); mesh: archery/AimRobot-v0, "
        "the MuJoCo iCub of --robot on the mesh at --connect (e.g. of `archery up`)",
    )
    add(
        "--methods",
        default=",".join(DEFAULT_METHODS),
        help=f"comma-separated: {', '.join(OPTIMIZERS)} or a learner of `archery experiment` "
        f"(default {','.join(DEFAULT_METHODS)})",
    )
    add("--sessions", default=None, help="sessions (seeds) per method (default 40; mesh: 3)")
    add("--rollouts", default=None, help="rollouts per session (default 60; mesh: 10)")
    add("--seed", default="0", help="master seed (default 0)")
    scene = parser.add_argument_group("--world ballistic: the scenario of `archery experiment`")
    scene.add_argument("--distance", default=None, help="target distance, m (default 2.2)")
    scene.add_argument("--wind", default=None, help="wind VX,VY,VZ in m/s; needs --drag")
    scene.add_argument("--drag", default=None, help="drag K, 1/m (default 0)")
    scene.add_argument("--noise", default=None, help="std of the noise on r, m (default 0)")
    scene.add_argument("--bow-stiffness", default=None, help="bow stiffness, N/m (default 300)")
    scene.add_argument("--start", default=None, help="start θ X,Y,Z in m")
    scene.add_argument(
        "--wind-change", default=None, metavar="AT:VX,VY,VZ", help="the wind from rollout AT on"
    )
    add(
        "--wait",
        default="10",
        metavar="S",
        help="--world mesh: s to wait for the router and the robot (default 10)",
    )
    add("--out", default="runs/compare", help="output directory (default runs/compare)")
    add_force_arg(parser, "the results of an earlier run in --out")
    add("--no-progress", action="store_true", help="hide the progress bar")
    add_network_args(parser)
    return parser


def _count(text: str | None, default: int, flag: str, low: int = 1) -> int:
    """The integer `text` of `flag` (>= `low`), `default` when not given."""
    if text is None:
        return default
    try:
        value = int(text)
    except ValueError:
        value = low - 1
    if value < low:
        raise ExperimentError(f"{flag} needs an integer >= {low}, got {text!r}")
    return value


def _scenario(args: argparse.Namespace) -> dict[str, Any]:
    """The Aim-v0 keywords of the scenario flags given."""
    keywords: dict[str, Any] = {}
    for flag in ("distance", "drag", "noise", "bow_stiffness"):
        text = getattr(args, flag)
        if text is not None:
            keywords[flag] = number(text, "--" + flag.replace("_", "-"))
    for flag, unit in (("wind", "m/s"), ("start", "m")):
        text = getattr(args, flag)
        if text is not None:
            vector = parse_vector(f"--{flag}", text, ExperimentError, unit=unit)
            keywords[flag] = tuple(vector.tolist())
    if args.wind_change is not None:
        keywords["wind_change"] = args.wind_change
    return keywords


def main(argv: Sequence[str] | None = None) -> int:
    """Run `archery compare [options]`: 0 on success, 2 on bad input, 1 when the robot or a
    service is not there, 130 on Ctrl-C."""
    parser = build_parser()
    args = parser.parse_args(list(sys.argv[1:] if argv is None else argv))
    out = Path(args.out)
    try:
        default_sessions, default_rollouts = DEFAULT_BUDGETS[args.world]
        sessions = _count(args.sessions, default_sessions, "--sessions")
        rollouts = _count(args.rollouts, default_rollouts, "--rollouts")
        seed = _count(args.seed, 0, "--seed", low=0)
        methods = tuple(m.strip() for m in args.methods.split(",") if m.strip())
        unknown = [m for m in methods if m not in OPTIMIZERS and m not in ALGORITHMS]
        if not methods or unknown or len(set(methods)) != len(methods):
            raise ExperimentError(
                f"--methods {args.methods!r}: each once, from {', '.join(OPTIMIZERS)}, "
                f"{', '.join(ALGORITHMS)}"
            )
        check_new_file(out, "--out")
        check_writable_dir(out, "--out", create=True)
        check_results_folder(
            out, "--out", ("summary.json", "curves.csv", "fig6.png"), force=args.force
        )
        if args.world == "ballistic":
            keywords = _scenario(args)
            env_id = AIM_ID
        else:
            if any(v is not None for v in _scenario_flags(args)):
                raise ExperimentError("the scenario flags are for --world ballistic")
            net = NetConfig.from_args(args)
            keywords = {
                "endpoint": net.connect[0],
                "robot": net.robot,
                "secure": net.secure,
                "identity": net.identity,
                "wait": number(args.wait, "--wait"),
            }
            env_id = AIM_ROBOT_ID
        keywords |= {"budget": rollouts, "until_hit": False}
        env = gym.make(env_id, **keywords)  # bad keywords, or no robot: before any work
        start = time.perf_counter()
        with progress_bar(disable=args.no_progress) as bar:
            total = len(methods) * sessions * rollouts
            task = bar.add_task(f"{len(methods)} methods × {sessions} sessions", total=total)
            runs = compare(env, methods, sessions, rollouts, seed, lambda: bar.advance(task))
        settings = {
            "world": args.world,
            "env": env_id,
            "keywords": {k: v for k, v in keywords.items() if k not in ("secure", "identity")},
            "sessions": sessions,
            "rollouts": rollouts,
            "seed": seed,
            "methods": list(methods),
            "wall_time_s": time.perf_counter() - start,
        }
        summary = summarise(runs, settings)
        title = f"{sessions} sessions × {rollouts} rollouts through {env_id}, seed {seed}"
        write_outputs(out, runs, summary, title)
    except KeyboardInterrupt:
        print(interrupted_line("compare"), file=sys.stderr)
        return INTERRUPTED
    except (RobotUnavailable, ServiceLostError, ShotNotMeasured) as exc:
        print(f"archery compare: {exc}", file=sys.stderr)
        return FAILURE
    except (LearnerError, ValueError) as exc:
        print(f"archery compare: error: {exc}", file=sys.stderr)
        return BAD_INPUT
    except ArcheryError as exc:
        status = for_error(exc.code)
        error = "error: " if status == BAD_INPUT else ""
        print(f"archery compare: {error}{exc}", file=sys.stderr)
        return status
    print_table(summary)
    print(f"wrote {out}/summary.json, curves.csv, fig6.png")
    return 0


def _scenario_flags(args: argparse.Namespace) -> list[object]:
    names = ("distance", "wind", "drag", "noise", "bow_stiffness", "start", "wind_change")
    return [getattr(args, n) for n in names]
