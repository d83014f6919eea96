"""`archery experiment`: the paper's simulation experiment (Section IV, Fig. 5 and Fig. 6).

Every run also writes `learners.json`, each session's final learner state per algorithm;
`--from DIR` starts the sessions of a new run (another distance, another bow) from those of the
run in DIR (session s from DIR's session s, cycling when DIR has fewer): see
`Learner.seed_from` for what each algorithm carries over."""

from __future__ import annotations

import argparse
import csv
import json
import math
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from protocol.cliargs import ArgumentParser, check_new_file, check_writable_dir
from protocol.errors import ArcheryError, ConfigError
from protocol.netflags import add_network_args
from protocol.progress import progress_bar
from services.learner.algorithms.base import DEFAULT_BOUNDS, Bounds, Learner, LearnerError
from services.learner.algorithms.power import Power
from services.learner.algorithms.registry import (
    ALGORITHMS,
    check_transfer,
    make_learner,
    transferred_learner,
)
from services.learner.tools.censored import count_stats, format_counts, format_mean
from services.learner.tools.plots import BANDS
from sim.ballistic import BallisticError, BallisticWorld, Scenario
from sim.geometry import INNER_RING_RADIUS

__all__ = [
    "CURVE_COLUMNS",
    "DEFAULT_ALGORITHMS",
    "WORLDS",
    "AlgorithmRun",
    "ExperimentConfig",
    "ExperimentError",
    "Transfer",
    "WindChange",
    "build_parser",
    "main",
    "run_algorithm",
    "run_experiment",
    "summarise",
    "write_outputs",
]

DEFAULT_ALGORITHMS = ("archer", "power", "cma", "hill", "random")
# curves.csv: θ (m), the observed and the true reward vector (m), the true distance ‖r‖ (m).
CURVE_COLUMNS = (
    "algorithm",
    "session",
    "rollout",
    "theta_x",
    "theta_y",
    "theta_z",
    "r_x",
    "r_y",
    "r_true_x",
    "r_true_y",
    "distance",
)
WORLDS = ("ballistic", "mesh")  # mesh: the MuJoCo iCubs of a fleet (experiment_mesh)
LEARNERS_NAME = "learners.json"  # the final learner states of a run, what --from reads
LEARNERS_VERSION = 1


class ExperimentError(LearnerError):
    """An invalid experiment setting (world, algorithm list, budget, start θ)."""


@dataclass(frozen=True)
class WindChange:
    """The wind becomes `wind` (m/s, root frame) from rollout `at` (1-based) on."""

    at: int
    wind: tuple[float, float, float]

    @classmethod
    def parse(cls, text: str) -> WindChange:
        """`AT:VX,VY,VZ`, e.g. `20:0,-3,0`.

        Raises:
            ExperimentError: malformed text.
        """
        at, sep, wind = text.partition(":")
        try:
            rollout = int(at)
        except ValueError:
            rollout = -1
        values = _floats(wind, 3, "--wind-change") if sep and rollout >= 0 else ()
        if not values:
            raise ExperimentError(
                f"--wind-change needs AT:VX,VY,VZ (a rollout number, then the new wind in m/s), "
                f"got {text!r}"
            )
        return cls(rollout, (values[0], values[1], values[2]))

    def to_dict(self) -> dict[str, Any]:
        """Plain values for summary.json."""
        return {"at": self.at, "wind": list(self.wind)}


@dataclass(frozen=True)
class Transfer:
    """Final learner states of an earlier run that seed the sessions of a new one.

    Attributes:
        source: where they come from (the earlier run's directory).
        states: per algorithm, one learner state per session of the earlier run.
    """

    source: str
    states: dict[str, tuple[dict[str, Any], ...]]

    @classmethod
    def load(cls, directory: Path) -> Transfer:
        """The states an experiment wrote into `directory`.

        Raises:
            ExperimentError: no readable `learners.json` of this version there.
        """
        path = directory / LEARNERS_NAME
        try:
            data = json.loads(path.read_text())
        except (OSError, ValueError) as exc:
            raise ExperimentError(
                f"--from {str(directory)!r}: cannot read {LEARNERS_NAME} of an earlier "
                f"`archery experiment --out DIR` ({getattr(exc, 'strerror', None) or exc})"
            ) from None
        if not isinstance(data, dict) or data.get("version") != LEARNERS_VERSION:
            raise ExperimentError(
                f"--from {str(directory)!r}: {path} is not a version {LEARNERS_VERSION} "
                f"learner-state file"
            )
        states = data.get("algorithms")
        if not isinstance(states, dict) or not all(
            isinstance(v, list) and v and all(isinstance(x, dict) for x in v)
            for v in states.values()
        ):
            raise ExperimentError(f"--from {str(directory)!r}: {path} holds no learner states")
        return cls(str(directory), {name: tuple(v) for name, v in states.items()})

    def state(self, name: str, session: int) -> dict[str, Any]:
        """The state that seeds `session` of algorithm `name`."""
        states = self.states[name]
        return states[session % len(states)]


@dataclass(frozen=True)
class ExperimentConfig:
    """One experiment: every algorithm runs `sessions` sessions of `rollouts` rollouts.

    Session s of every algorithm sees the same observation-noise stream and its learner gets the
    same seed, both derived from (seed, s); so results do not depend on which algorithms run.

    Attributes:
        algorithms: names from `services.learner.algorithms.registry.ALGORITHMS`.
        sessions: number of independent learning sessions per algorithm.
        rollouts: rollout budget per session.
        seed: master seed.
        scenario: the simulated range.
        bounds: θ box (m) given to every learner.
        world: the simulator: "ballistic" (the paper's analytic model, here) or "mesh" (the
            MuJoCo robots of a fleet, `services.learner.tools.experiment_mesh`).
        wind_change: the wind changes during the sessions (None: it does not).
        transfer: start each session from an earlier run's learner (None: from scratch).
        power_scale: s (m) in PoWER's importance weights R = exp(−‖r‖/s) for every PoWER
            algorithm of the run (None: each one's own, `Power`); no other learner has one.
    """

    algorithms: tuple[str, ...] = DEFAULT_ALGORITHMS
    sessions: int = 40
    rollouts: int = 60
    seed: int = 0
    scenario: Scenario = field(default_factory=Scenario)
    bounds: Bounds = DEFAULT_BOUNDS
    world: str = "ballistic"
    wind_change: WindChange | None = None
    transfer: Transfer | None = None
    power_scale: float | None = None

    def __post_init__(self) -> None:
        if self.world not in WORLDS:
            raise ExperimentError(
                f"unknown world {self.world!r}; valid worlds: {', '.join(WORLDS)}"
            )
        if not self.algorithms:
            raise ExperimentError(f"no algorithm given; valid algorithms: {', '.join(ALGORITHMS)}")
        for name in self.algorithms:
            if name not in ALGORITHMS:
                raise ExperimentError(
                    f"unknown algorithm {name!r}; valid algorithms: {', '.join(ALGORITHMS)}"
                )
        scale = self.power_scale
        if scale is not None and not (
            isinstance(scale, int | float) and math.isfinite(scale) and 1e-4 <= scale <= 10
        ):
            raise ExperimentError(f"--power-scale must be in [0.0001, 10] m, got {scale!r}")
        if len(set(self.algorithms)) != len(self.algorithms):
            raise ExperimentError(f"algorithm list {list(self.algorithms)} repeats a name")
        for name, low in (("sessions", 1), ("rollouts", 1), ("seed", 0)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < low:
                raise ExperimentError(f"{name} must be an integer >= {low}, got {value!r}")
        if not self.bounds.contains(np.array(self.scenario.start)):
            raise ExperimentError(
                f"start θ {list(self.scenario.start)} m lies outside the θ bounds "
                f"low={list(self.bounds.low)}, high={list(self.bounds.high)}"
            )
        if self.wind_change is not None:
            at = self.wind_change.at
            if not 2 <= at <= self.rollouts:
                raise ExperimentError(
                    f"--wind-change rollout {at} must be in [2, {self.rollouts}] (the budget)"
                )
            self.changed_scenario()  # a wind without drag is rejected here
        if self.transfer is not None:
            for name in self.algorithms:
                check_transfer(name)
                if name not in self.transfer.states:
                    raise ExperimentError(
                        f"--from {self.transfer.source!r} has no {name} sessions; it has "
                        f"{', '.join(self.transfer.states) or 'none'}"
                    )
        for name in self.algorithms:
            probe = self.learner(name, 0)
            needed = probe.exploration_rollouts + 1
            if self.rollouts < needed:
                raise ExperimentError(
                    f"rollouts {self.rollouts} is below {name}'s exploration phase "
                    f"({probe.exploration_rollouts} rollouts) plus one learned rollout; "
                    f"use rollouts >= {needed}"
                )

    def seeds(self, session: int) -> tuple[np.random.SeedSequence, np.random.SeedSequence]:
        """(world noise seed, learner seed) of a session."""
        return (
            np.random.SeedSequence(self.seed, spawn_key=(session, 0)),
            np.random.SeedSequence(self.seed, spawn_key=(session, 1)),
        )

    def learner(self, name: str, session: int) -> Learner:
        """A fresh learner `name` for `session`, starting at the scenario's θ (and from the
        transferred learner of `session`, with `transfer`).

        Raises:
            StateError: the transferred state cannot seed it.
        """
        options = {}
        if self.power_scale is not None and ALGORITHMS[name].cls is Power:
            options["return_scale"] = float(self.power_scale)
        learner = make_learner(
            name,
            np.array(self.scenario.start),
            rng=np.random.default_rng(self.seeds(session)[1]),
            bounds=self.bounds,
            **options,
        )
        if self.transfer is None:
            return learner
        return transferred_learner(learner, self.transfer.state(name, session))

    def changed_scenario(self) -> Scenario:
        """The range after the wind change (the scenario itself without one).

        Raises:
            ScenarioError: the new wind needs drag and the scenario has none.
        """
        if self.wind_change is None:
            return self.scenario
        return replace(self.scenario, wind=self.wind_change.wind)

    def to_dict(self) -> dict[str, Any]:
        """The run settings as plain values."""
        return {
            "sessions": self.sessions,
            "rollouts": self.rollouts,
            "seed": self.seed,
            "algorithms": list(self.algorithms),
            "bounds": self.bounds.to_dict(),
            "from": None if self.transfer is None else self.transfer.source,
            "power_scale_m": self.power_scale,
        }


@dataclass(frozen=True)
class AlgorithmRun:
    """Everything one algorithm did in an experiment.

    Attributes:
        name: the algorithm's name.
        thetas: (sessions, rollouts, 3) θ of every rollout (m).
        r_observed: (sessions, rollouts, 2) reward vectors the learner was told (m).
        r_true: (sessions, rollouts, 2) true arrow − centre offsets (m).
        wall_time: seconds spent on this algorithm (learning and simulation).
        states: each session's final learner state.
    """

    name: str
    thetas: np.ndarray
    r_observed: np.ndarray
    r_true: np.ndarray
    wall_time: float
    states: tuple[dict[str, Any], ...] = ()

    @property
    def distances(self) -> np.ndarray:
        """(sessions, rollouts) true distance of each arrow to the centre (m)."""
        return np.hypot(self.r_true[..., 0], self.r_true[..., 1])

    def rollouts_to_hit(self) -> np.ndarray:
        """(sessions,) 1-based index of the first hit (‖r‖ < 5 cm); budget + 1 if none."""
        hits = self.distances < INNER_RING_RADIUS
        budget = hits.shape[1]
        return np.where(hits.any(axis=1), hits.argmax(axis=1) + 1, budget + 1)

    def rollouts_to_rehit(self, at: int) -> np.ndarray:
        """(sessions,) rollouts from `at` (1-based, counted as 1) to the first hit at or after it;
        budget − at + 2 if none."""
        hits = self.distances[:, at - 1 :] < INNER_RING_RADIUS
        return np.where(hits.any(axis=1), hits.argmax(axis=1) + 1, hits.shape[1] + 1)


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
    (median_censored …, `services.learner.tools.censored.count_stats`); hit_rate and hits, the
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
            if rehit is None
            else count_stats(rehit, config.rollouts - change.at + 1),
            "rehits": None
            if rehit is None
            else int(np.sum(rehit <= config.rollouts - change.at + 1)),
            "wall_time_s": run.wall_time,
        }
    scenario = {
        "world": config.world,
        **config.scenario.to_dict(),
        "wind_change": None if change is None else change.to_dict(),
    }
    return {"scenario": scenario, "run": config.to_dict(), "algorithms": algorithms}


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
        from services.learner.tools.plots import plot_convergence, plot_trajectories

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


def _floats(text: str, count: int, flag: str) -> tuple[float, ...]:
    parts = text.split(",")
    try:
        values = tuple(float(p) for p in parts)
    except ValueError:
        values = ()
    if len(values) != count or not all(math.isfinite(v) for v in values):
        what = "a number" if count == 1 else f"{count} comma-separated numbers"
        raise ExperimentError(f"{flag} needs {what}, got {text!r}")
    return values


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
    add("--no-progress", action="store_true", help="hide the progress bar")
    add("--no-figures", action="store_true", help="skip fig5.png and fig6.png")
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
    scenario = Scenario(
        distance=_floats(args.distance, 1, "--distance")[0],
        wind=_floats(args.wind, 3, "--wind"),
        drag=_floats(args.drag, 1, "--drag")[0],
        noise=_floats(args.noise, 1, "--noise")[0],
        bow_stiffness=_floats(args.bow_stiffness, 1, "--bow-stiffness")[0],
        start=_floats(args.start, 3, "--start"),
    )
    return ExperimentConfig(
        algorithms=tuple(a.strip() for a in args.algo.split(",") if a.strip()),
        sessions=_int(args.sessions, "--sessions"),
        rollouts=_int(args.rollouts, "--rollouts"),
        seed=_int(args.seed, "--seed"),
        scenario=scenario,
        world=args.world,
        wind_change=None if args.wind_change is None else WindChange.parse(args.wind_change),
        transfer=None if args.from_ is None else Transfer.load(Path(args.from_)),
        power_scale=None
        if args.power_scale is None
        else _floats(args.power_scale, 1, "--power-scale")[0],
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
        flag = "--out" if args.resume is None else "--resume"
        check_new_file(out, flag)
        check_writable_dir(out, flag, create=args.resume is None)  # before the work
        start = time.perf_counter()
        if config.world == "mesh":
            from services.learner.tools import experiment_mesh

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
    except (LearnerError, BallisticError, ConfigError) as exc:
        print(f"archery experiment: error: {exc}", file=sys.stderr)
        return 2
    except ArcheryError as exc:  # the mesh: no robot, interrupted, a session failing
        print(f"archery experiment: {exc}", file=sys.stderr)
        return 1
    _print_table(summary, wall_time)
    print(
        f"wrote {out}/summary.json, curves.csv, learners.json"
        + ("" if args.no_figures else ", fig5.png, fig6.png")
    )
    return 0
