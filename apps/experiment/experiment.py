"""`archery experiment`: the paper's simulation experiment (Section IV, Fig. 5 and Fig. 6).

Every run also writes `learners.json`, each session's final learner state per algorithm;
`--from DIR` starts the sessions of a new run (another distance, another bow) from those of the
run in DIR (session s from DIR's session s, cycling when DIR has fewer): see
`Learner.seed_from` for what each algorithm carries over."""

from __future__ import annotations

import argparse
import csv
import json
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from archery.apps.capacity import MAX_SESSIONS, check_experiment
from archery.apps.experiment.censored import count_stats, format_counts, format_mean
from archery.apps.experiment.config import (
    CURVE_COLUMNS,
    DEFAULT_ALGORITHMS,
    LEARNERS_NAME,
    LEARNERS_VERSION,
    WORLDS,
    AlgorithmRun,
    ExperimentConfig,
    ExperimentError,
    Transfer,
    WindChange,
    number,
)
from archery.apps.experiment.plots import BANDS
from archery.apps.progress import progress_bar
from archery.mesh.cliargs import (
    ArgumentParser,
    add_force_arg,
    check_new_file,
    check_results_folder,
    check_writable_dir,
)
from archery.mesh.netflags import add_network_args
from archery.protocol.errors import ArcheryError
from archery.protocol.exit_status import BAD_INPUT, for_error
from archery.protocol.vectors import parse_vector
from archery.services.learner.algorithms.base import LearnerError
from archery.services.learner.algorithms.registry import (
    ALGORITHMS,
)
from archery.sim.ballistic import BallisticError, BallisticWorld, Scenario, ScenarioError

__all__ = ["build_parser", "main", "run_algorithm", "run_experiment", "summarise", "write_outputs"]


def run_algorithm(
    config: ExperimentConfig, name: str, on_rollout: Callable[[], None] | None = None
) -> AlgorithmRun:
    """Run all sessions of one algorithm in lockstep (the physics is vectorised over sessions)."""
    start = time.perf_counter()
    n_s, n_r = config.sessions, config.rollouts
    learners = [config.learner(name, s) for s in range(n_s)]
    world = BallisticWorld(config.scenario)
    changed = BallisticWorld(config.changed_scenario())
    change_at = config.wind_change.at if config.wind_change is not None else n_r + 1
    observers = []
    for s in range(n_s):
        observer = BallisticWorld(config.scenario)
        observer.reset(config.seeds(s)[0])
        observers.append(observer)
    thetas = np.empty((n_s, n_r, 3))
    r_observed = np.empty((n_s, n_r, 2))
    r_true = np.empty((n_s, n_r, 2))
    for k in range(n_r):
        batch = np.stack([learner.ask() for learner in learners])
        impacts = (world if k + 1 < change_at else changed).impacts(batch)
        for s, learner in enumerate(learners):
            r = observers[s].observe(impacts.r[s])
            learner.tell(batch[s], r)
            r_observed[s, k] = r
        thetas[:, k] = batch
        r_true[:, k] = impacts.r
        if on_rollout is not None:
            on_rollout()
    states = tuple(learner.state_dict() for learner in learners)
    return AlgorithmRun(name, thetas, r_observed, r_true, time.perf_counter() - start, states)


def run_experiment(config: ExperimentConfig, *, progress: bool = True) -> dict[str, AlgorithmRun]:
    """Run every algorithm of `config`, with a progress bar on stderr if `progress`."""
    runs: dict[str, AlgorithmRun] = {}
    with progress_bar(disable=not progress) as bar:
        total = len(config.algorithms) * config.rollouts
        task = bar.add_task(f"{config.sessions} sessions", total=total)
        for name in config.algorithms:
            bar.update(task, description=f"{name:>12} × {config.sessions} sessions")
            runs[name] = run_algorithm(config, name, lambda: bar.advance(task))
    return runs


def summarise(config: ExperimentConfig, runs: dict[str, AlgorithmRun]) -> dict[str, Any]:
    """The content of summary.json.

    Per algorithm: rollouts_to_hit (median, mean, quartiles over sessions) counts the first
    rollout whose true impact is inside the innermost ring (‖r‖ < 5 cm; a session that never hits
    counts as budget + 1), and says which of those statistics that count makes a bound only
    (median_censored …, `apps.experiment.censored.count_stats`); hit_rate and hits, the
    sessions that hit within the budget;
    final_distance, the true ‖r‖ (m) of the last rollout (mean and std over sessions). With a
    wind change at rollout AT, rollouts_to_rehit counts from AT (as 1) to the first hit at or
    after it (budget − AT + 2 if none) and rehits the sessions that hit again; both are null
    without a change.
    """
    algorithms = {}
    change = config.wind_change
    for name, run in runs.items():
        to_hit = run.rollouts_to_hit()
        final = run.distances[:, -1]
        rehit = None if change is None else run.rollouts_to_rehit(change.at)
        algorithms[name] = {
            "label": ALGORITHMS[name].label,
            "rollouts_to_hit": count_stats(to_hit, config.rollouts),
            "hit_rate": float(np.mean(to_hit <= config.rollouts)),
            "hits": int(np.sum(to_hit <= config.rollouts)),
            "final_distance": {"mean": float(final.mean()), "std": float(final.std())},
            "rollouts_to_rehit": None
            if rehit is None or change is None
            else count_stats(rehit, config.rollouts - change.at + 1),
            "rehits": None
            if rehit is None or change is None
            else int(np.sum(rehit <= config.rollouts - change.at + 1)),
            "wall_time_s": run.wall_time,
        }
    scenario = {
        "world": config.world,
        **config.scenario.to_dict(),
        "wind_change": None if change is None else change.to_dict(),
    }
    return {"scenario": scenario, "run": config.to_dict(), "algorithms": algorithms}


#: what a run writes into --out (a second run into the same folder needs --force)
RESULTS = ("summary.json", "curves.csv", LEARNERS_NAME, "fig5.png", "fig6.png")


def write_outputs(
    out: Path,
    config: ExperimentConfig,
    runs: dict[str, AlgorithmRun],
    *,
    figures: bool = True,
    band: str = "median",
) -> dict[str, Any]:
    """Write summary.json, curves.csv, learners.json (the final learner states, what `--from`
    reads) and (if `figures`) fig5.png and fig6.png into `out`; `band` is Fig. 6's ("median":
    median and interquartile band, "mean": mean ± std; `plots.BANDS`)."""
    out.mkdir(parents=True, exist_ok=True)
    summary = summarise(config, runs)
    (out / "summary.json").write_text(json.dumps(summary, indent=2, allow_nan=False) + "\n")
    learners = {name: list(run.states) for name, run in runs.items() if run.states}
    (out / LEARNERS_NAME).write_text(
        json.dumps({"version": LEARNERS_VERSION, "algorithms": learners}, allow_nan=False) + "\n"
    )
    with (out / "curves.csv").open("w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(CURVE_COLUMNS)
        for name, run in runs.items():
            distances = run.distances
            for s in range(config.sessions):
                for k in range(config.rollouts):
                    values = (
                        *run.thetas[s, k],
                        *run.r_observed[s, k],
                        *run.r_true[s, k],
                        distances[s, k],
                    )
                    writer.writerow([name, s, k + 1, *(repr(float(v)) for v in values)])
    if figures:
        from archery.apps.experiment.plots import plot_convergence, plot_trajectories

        labels = {name: ALGORITHMS[name].label for name in runs}
        plot_convergence(
            runs,
            labels,
            out / "fig6.png",
            title=_title(config),
            change_at=None if config.wind_change is None else config.wind_change.at,
            band=band,
        )
        plot_trajectories(
            BallisticWorld(config.scenario),
            runs,
            labels,
            out / "fig5.png",
            session=0,
            title=_title(config),
        )
    return summary


def _title(config: ExperimentConfig) -> str:
    s = config.scenario
    parts = [f"{config.world} world, target {s.distance:g} m"]
    if s.drag:
        parts.append(f"drag {s.drag:g}/m, wind {', '.join(f'{w:g}' for w in s.wind)} m/s")
    if s.noise:
        parts.append(f"noise {100 * s.noise:g} cm")
    if config.wind_change is not None:
        wind = ", ".join(f"{w:g}" for w in config.wind_change.wind)
        parts.append(f"wind {wind} m/s from rollout {config.wind_change.at}")
    if config.transfer is not None:
        parts.append(f"from {config.transfer.source}")
    if config.power_scale is not None:
        parts.append(f"PoWER's R = exp(−‖r‖/{100 * config.power_scale:g} cm)")
    return f"{config.sessions} sessions × {config.rollouts} rollouts; " + ", ".join(parts)


def build_parser() -> argparse.ArgumentParser:
    """The command-line options of `archery experiment`."""
    defaults = Scenario()
    parser = ArgumentParser(
        prog="archery experiment",
        description="Run the paper's simulation experiment: learners against the ballistic world.",
    )
    add = parser.add_argument
    add(
        "--world",
        default="ballistic",
        help=f"simulator: {', '.join(WORLDS)} (default ballistic; mesh: the MuJoCo iCubs alive "
        "on the mesh, e.g. of `archery up --robots N`)",
    )
    add(
        "--algo",
        default=",".join(DEFAULT_ALGORITHMS),
        help=f"comma-separated algorithms from: {', '.join(ALGORITHMS)} "
        f"(default {','.join(DEFAULT_ALGORITHMS)})",
    )
    add("--sessions", default="40", help="learning sessions per algorithm (default 40)")
    add("--rollouts", default="60", help="rollout budget per session (default 60)")
    add("--seed", default="0", help="master seed (default 0)")
    add("--distance", default=repr(defaults.distance), help="target distance, m (default 2.2)")
    add("--wind", default="0,0,0", help="wind VX,VY,VZ in m/s, root frame; needs --drag")
    add(
        "--wind-change",
        default=None,
        metavar="AT:VX,VY,VZ",
        help="the wind becomes VX,VY,VZ m/s from rollout AT on (needs --drag)",
    )
    add("--drag", default="0", help="drag K in a = −K‖v−w‖(v−w), 1/m (default 0)")
    add("--noise", default="0", help="std of the observation noise on r, m (default 0)")
    add(
        "--bow-stiffness",
        default=repr(defaults.bow_stiffness),
        help=f"linear bow stiffness, N per m of draw (default {defaults.bow_stiffness:g})",
    )
    add(
        "--start",
        default=",".join(repr(x) for x in defaults.start),
        help="start θ = string hand − bow hand X,Y,Z in m (default "
        + ",".join(f"{x:g}" for x in defaults.start)
        + ")",
    )
    add(
        "--from",
        dest="from_",
        metavar="DIR",
        help="start each session from the learner of an earlier run's --out DIR",
    )
    add(
        "--power-scale",
        default=None,
        metavar="S",
        help="s in PoWER's weights exp(−‖r‖/s), m (default 0.05, the 5 cm ring; 1 = metres)",
    )
    add(
        "--fig6",
        choices=BANDS,
        default="median",
        help="fig6.png: median with the interquartile band (default), or mean ± std",
    )
    add("--out", default="runs/experiment", help="output directory (default runs/experiment)")
    add_force_arg(parser, "the results of an earlier run in --out")
    add("--no-progress", action="store_true", help="hide the progress bar")
    add("--no-figures", action="store_true", help="skip fig5.png and fig6.png")
    add(
        "--allow-overload",
        action="store_true",
        help=f"run more than this machine holds (at most {MAX_SESSIONS} sessions per algorithm, "
        "and the rollouts in half the available memory: `apps.capacity`)",
    )
    mesh = parser.add_argument_group("--world mesh")
    mesh.add_argument(
        "--robots",
        metavar="PREFIX,PREFIX",
        help="the robots to use (default: every robot stack alive on the mesh)",
    )
    mesh.add_argument(
        "--resume",
        metavar="DIR",
        help="continue the experiment cut short in DIR (its --out), with the flags it ran with",
    )
    mesh.add_argument(
        "--wait",
        default="5",
        metavar="S",
        help="s to wait at the start for the robots to be alive (default 5)",
    )
    mesh.add_argument(
        "--robot-wait",
        default="10",
        metavar="S",
        help="s a robot may be lost before its session moves to another robot (default 10)",
    )
    add_network_args(parser)
    return parser


def _int(text: str, flag: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise ExperimentError(f"{flag} needs an integer, got {text!r}") from None


def _config_from_args(args: argparse.Namespace) -> ExperimentConfig:
    """Validate parsed options into an ExperimentConfig.

    Raises:
        ExperimentError, BallisticError: a value is malformed or out of range.
    """
    try:
        scenario = Scenario(
            distance=number(args.distance, "--distance"),
            wind=tuple(parse_vector("--wind", args.wind, ExperimentError, unit="m/s").tolist()),
            drag=number(args.drag, "--drag"),
            noise=number(args.noise, "--noise"),
            bow_stiffness=number(args.bow_stiffness, "--bow-stiffness"),
            start=tuple(parse_vector("--start", args.start, ExperimentError).tolist()),
        )
    except ScenarioError as exc:
        if exc.field is None:
            raise
        flag = "--" + exc.field.replace("_", "-")
        raise ExperimentError(f"{flag} {getattr(args, exc.field)}: {exc}") from None
    return ExperimentConfig(
        algorithms=tuple(a.strip() for a in args.algo.split(",") if a.strip()),
        sessions=_int(args.sessions, "--sessions"),
        rollouts=_int(args.rollouts, "--rollouts"),
        seed=_int(args.seed, "--seed"),
        scenario=scenario,
        world=args.world,
        wind_change=None if args.wind_change is None else WindChange.parse(args.wind_change),
        transfer=None if args.from_ is None else Transfer.load(Path(args.from_)),
        power_scale=None if args.power_scale is None else number(args.power_scale, "--power-scale"),
    )


def _print_table(summary: dict[str, Any], wall_time: float) -> None:
    """Print the per-algorithm results as a table on stdout."""
    from rich.console import Console
    from rich.markup import escape
    from rich.table import Table

    run = summary["run"]
    table = Table(
        title=f"{run['sessions']} sessions × {run['rollouts']} rollouts, seed {run['seed']}"
    )
    change = summary["scenario"]["wind_change"]
    columns = ["algorithm", "to hit: median [q1, q3]", "mean", "hit rate", "final ‖r‖ (m)"]
    if change is not None:
        columns += [f"re-hit after rollout {change['at']}: median [q1, q3]", "re-hits"]
    for column in columns:
        table.add_column(escape(column), justify="left" if column == "algorithm" else "right")
    for name, a in summary["algorithms"].items():
        h = a["rollouts_to_hit"]
        row = [
            name,
            escape(format_counts(h)),
            format_mean(h),
            f"{a['hits']}/{run['sessions']} ({100 * a['hit_rate']:.0f} %)",
            f"{a['final_distance']['mean']:.3f} ± {a['final_distance']['std']:.3f}",
        ]
        if change is not None:
            e = a["rollouts_to_rehit"]
            row += [
                escape(format_counts(e)),
                f"{a['rehits']}/{run['sessions']}",
            ]
        table.add_row(*row)
    Console().print(table)
    Console().print(
        f"A session that never hits counts as {run['rollouts'] + 1} rollouts: a median or "
        f"quartile on one is shown as > {run['rollouts']}, a mean over them as ≥ (a lower bound)."
    )
    Console().print(f"wall time {wall_time:.2f} s")


def main(argv: Sequence[str] | None = None) -> int:
    """Run `archery experiment [options]`; returns 0 on success, 2 on bad input, 1 when a run
    on the mesh could not finish (no robot alive, interrupted: `--resume DIR` continues it)."""
    parser = build_parser()
    args = parser.parse_args(list(sys.argv[1:] if argv is None else argv))
    out = Path(args.out if args.resume is None else args.resume)
    try:
        config = _config_from_args(args)
        check_experiment(
            len(config.algorithms), config.sessions, config.rollouts, args.allow_overload
        )
        flag = "--out" if args.resume is None else "--resume"
        check_new_file(out, flag)
        check_writable_dir(out, flag, create=args.resume is None)  # before the work
        if args.resume is None:
            check_results_folder(out, "--out", RESULTS, force=args.force)
        start = time.perf_counter()
        if config.world == "mesh":
            from archery.apps.experiment import experiment_mesh

            config, runs = experiment_mesh.run_from_args(args, parser, config, out)
        elif args.resume is not None or args.robots is not None:
            raise ExperimentError("--resume and --robots are for --world mesh")
        else:
            runs = run_experiment(config, progress=not args.no_progress)
        figures = not args.no_figures
        summary = write_outputs(
            out, config, runs, figures=figures and config.world != "mesh", band=args.fig6
        )
        if figures and config.world == "mesh":
            experiment_mesh.write_mesh_figures(out, config, runs, band=args.fig6)
        wall_time = time.perf_counter() - start
    except (LearnerError, BallisticError) as exc:
        print(f"archery experiment: error: {exc}", file=sys.stderr)
        return BAD_INPUT
    except ArcheryError as exc:  # a bad flag, or the mesh: no robot, interrupted, a failure
        status = for_error(exc.code)
        error = "error: " if status == BAD_INPUT else ""
        print(f"archery experiment: {error}{exc}", file=sys.stderr)
        return status
    _print_table(summary, wall_time)
    print(
        f"wrote {out}/summary.json, curves.csv, learners.json"
        + ("" if args.no_figures else ", fig5.png, fig6.png")
    )
    return 0
