"""`archery experiment --world mesh`: the paper's Section IV experiment on a fleet of MuJoCo
iCubs over the mesh.

Every (algorithm, session) pair is one learning session of the learner (`Session`, the same
closed loop and journal as `archery learn`), journaled in `OUT/sessions/ALGO-sNN/journal.jsonl`
with the learner seed of the ballistic world's session NN, the robot's default start θ and θ
box, and the whole rollout budget (no stop at the first hit, so Fig. 6 has every rollout).
`_Experiment` shares them out among the robots and survives a lost robot; docs/fleet.md
tells the rest. Pure wiring: the sessions' maths is in `services.learner.session`
and the algorithms.
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import msgspec

from archery.apps.experiment.config import AlgorithmRun, ExperimentConfig, ExperimentError
from archery.apps.experiment.fleet import FleetRobot, NoRobot, StackWatch, open_fleet
from archery.apps.experiment.mesh_out import (
    FleetFailure,
    SessionItem,
    journal_path,
    prepare_out,
    runs_from_journals,
    session_config,
    session_ended,
    session_records,
)
from archery.apps.progress import progress_bar
from archery.apps.waits import announce
from archery.mesh.liveliness import OnWait
from archery.mesh.logs import DEFAULT_SPEC
from archery.mesh.netflags import NetConfig
from archery.mesh.signals import shutdown_on_signals
from archery.protocol.errors import ArcheryError, BadRequest, ConfigError
from archery.protocol.journal_records import DoneRecord, JournalRecord
from archery.protocol.robotspec import THETA0
from archery.protocol.theta import ThetaBox
from archery.services.learner.algorithms.registry import ALGORITHMS
from archery.services.learner.errors import RigError, ServiceLost
from archery.services.learner.journal import JournalError
from archery.services.learner.session import Session

__all__ = [
    "BALLISTIC_ONLY",
    "Interrupted",
    "MeshSettings",
    "check_mesh_flags",
    "fleet_box",
    "mesh_experiment_config",
    "run_from_args",
    "run_mesh_experiment",
    "write_mesh_figures",
]

log = logging.getLogger("archery.experiment")
MAX_FAILURES = 3  # a session failing this often on a live robot ends the experiment


class Interrupted(ArcheryError):
    """The experiment was stopped before every session finished; `--resume` continues it."""

    code = "interrupted"


@dataclass(frozen=True)
class MeshSettings:
    """How the experiment reaches and uses the fleet.

    Attributes:
        net: the network settings of the experiment's own Zenoh session.
        robots: the robot prefixes to use; None: every robot stack alive at the start.
        robot_wait: a robot lost this long (s) gives its session to another robot; no robot
            alive this long ends the experiment (resumable).
        rpc_timeout: longest wait for a service's reply (s).
        start_timeout: how long to wait for the robots at the start (s).
    """

    net: NetConfig
    robots: tuple[str, ...] | None = None
    robot_wait: float = 10.0
    rpc_timeout: float = 10.0
    start_timeout: float = 5.0


class _Queue:
    """The sessions still to run, shared by the robots' workers."""

    def __init__(self, items: list[SessionItem]) -> None:
        self.todo: deque[SessionItem] = deque(items)
        self.running = 0
        self.failures: dict[SessionItem, int] = {}
        self.error: ArcheryError | None = None
        self.cond = threading.Condition()
        self.abort = threading.Event()

    def take(self) -> SessionItem | None:
        """The next session (None: nothing left to run, or aborted)."""
        with self.cond:
            self.cond.wait_for(lambda: self.todo or not self.running or self.abort.is_set())
            if self.abort.is_set() or not self.todo:
                return None
            self.running += 1
            return self.todo.popleft()

    def finish(self, item: SessionItem, again: bool) -> None:
        """`item` is no longer running: done, or (`again`) back at the head of the queue."""
        with self.cond:
            self.running -= 1
            if again:
                self.todo.appendleft(item)
            self.cond.notify_all()

    def fail(self, error: ArcheryError) -> None:
        """End the experiment with `error` (the first one wins)."""
        with self.cond:
            self.error = self.error or error
            self.abort.set()
            self.cond.notify_all()

    def stop(self) -> None:
        """End the experiment: no new session starts; running ones stop after their rollout."""
        with self.cond:
            self.abort.set()
            self.cond.notify_all()

    def empty(self) -> bool:
        """Nothing left to run or running."""
        with self.cond:
            return not self.todo and not self.running


class _Experiment:
    """The workers (one thread per robot) over one queue, and their counters.

    The sessions wait in one work queue; each robot of the fleet takes the next one as soon as
    it is free, so a fast robot does more. A robot whose stack is lost (any of its robot,
    camera, detector or controller gone for `robot_wait` s) gives its session back to the
    queue, where the next free robot resumes it from its journal: the learner is restored from
    the last done rollout and an attempt left open is run again, so an attempt counts once and
    no session is lost. The lost robot takes work again once its stack is back. An experiment
    cut short (Ctrl-C, a crash, no robot left) continues with `--resume OUT`: finished sessions
    are read back from their journals, the others resume where they stopped.
    """

    def __init__(self, config: ExperimentConfig, out: Path, settings: MeshSettings) -> None:
        self.config = config
        self.out = out
        self.settings = settings
        items = [SessionItem(name, s) for s in range(config.sessions) for name in config.algorithms]
        self.done_before = 0
        todo = []
        for item in items:
            records = session_records(journal_path(out, item))
            self.done_before += sum(isinstance(r, DoneRecord) for r in records)
            if not session_ended(records):
                todo.append(item)
        self.total_sessions = len(items)
        self.finished = len(items) - len(todo)
        self.rollouts = 0  # done rollouts in this run
        self.moved = 0  # sessions given back by a lost robot
        self.queue = _Queue(todo)
        self.stops: dict[str, threading.Event] = {}
        self.lock = threading.Lock()

    def _on_record(self, record: JournalRecord) -> None:
        if isinstance(record, DoneRecord):
            with self.lock:
                self.rollouts += 1

    def _open(self, item: SessionItem, robot: FleetRobot) -> Session:
        path = journal_path(self.out, item)
        kw: dict[str, Any] = {
            "on_record": self._on_record,
            "service_wait": self.settings.robot_wait,
        }
        if path.exists():
            return Session.resume(path, robot.rig, item.name, **kw)
        config = session_config(self.config, item)
        return Session.create(config, robot.rig, path.parent.parent, item.name, **kw)

    def _robot_ready(self, robot: FleetRobot) -> bool:
        """Wait until the robot's stack is alive (True), or nothing is left to do (False)."""
        logged = False
        while not self.queue.abort.is_set() and not self.queue.empty():
            try:
                if robot.rig.wait_services(1.0, self.queue.abort):
                    if logged:
                        log.warning("robot %s is back: it takes sessions again", robot.prefix)
                    return True
            except ServiceLost:
                if not logged:
                    log.warning("robot %s is not alive: it takes no session", robot.prefix)
                    logged = True
        return False

    def work(self, robot: FleetRobot) -> None:
        """One robot's worker: take the next session, run it, give it back if the robot is
        lost; until nothing is left."""
        while self._robot_ready(robot):
            item = self.queue.take()
            if item is None:
                return
            again = True
            try:
                again = self._run(item, robot)
            except ArcheryError as exc:
                self.queue.fail(exc)
            except Exception as exc:  # a bug must end the run, not hang it
                log.exception("session %s on %s", item.name, robot.prefix)
                self.queue.fail(ArcheryError(f"internal error in session {item.name}: {exc!r}"))
            finally:
                self.queue.finish(item, again)

    def _run(self, item: SessionItem, robot: FleetRobot) -> bool:
        """Run `item` on `robot`; True if it must run again (elsewhere or later)."""
        stop = threading.Event()
        with self.lock:
            self.stops[robot.prefix] = stop
        if self.queue.abort.is_set():
            return True
        try:
            session = self._open(item, robot)
        except ServiceLost as exc:
            log.warning("robot %s lost before session %s: %s", robot.prefix, item.name, exc)
            return True
        except (BadRequest, JournalError, RigError) as exc:
            if robot.rig.missing():
                return True
            raise FleetFailure(f"session {item.name} on {robot.prefix}: {exc.message}") from None
        log.info("session %s on robot %s", item.name, robot.prefix)
        status = session.run(stop)
        if status.state == "finished":
            with self.lock:
                self.finished += 1
            return False
        if self.queue.abort.is_set():
            return True
        if robot.rig.missing():
            with self.lock:
                self.moved += 1
            log.warning(
                "robot %s lost during session %s (%s): the session goes to the next free robot",
                robot.prefix,
                item.name,
                status.cause,
            )
            return True
        failures = self.queue.failures[item] = self.queue.failures.get(item, 0) + 1
        if failures >= MAX_FAILURES:
            raise FleetFailure(
                f"session {item.name} failed {failures} times on live robots, last on "
                f"{robot.prefix}: {status.cause}; see {session.journal.path}"
            )
        log.warning("session %s failed on %s: %s; it runs again", item.name, robot.prefix, status)
        return True

    def stop_all(self) -> None:
        """Stop the queue and every running session (after its current rollout)."""
        self.queue.stop()
        with self.lock:
            for stop in self.stops.values():
                stop.set()

    def progress(self, elapsed: float) -> tuple[int, str]:
        """(sessions finished, "R rollouts/s, T left")."""
        with self.lock:
            finished, rollouts = self.finished, self.rollouts
        rate = rollouts / elapsed if elapsed > 0 else 0.0
        total = self.total_sessions * self.config.rollouts
        left = total - self.done_before - rollouts
        eta = f"{left / rate / 60:.1f} min left" if rate > 0 else "time left unknown"
        return finished, f"{rate:.2f} rollouts/s, {eta}"


def _bar(disable: bool) -> Any:
    """The experiment's bar: sessions done of total, then rollouts/s and the time left."""
    from rich.progress import TextColumn

    return progress_bar(TextColumn("sessions, {task.fields[info]}"), disable=disable)


def run_mesh_experiment(
    config: ExperimentConfig,
    out: Path,
    settings: MeshSettings,
    stop: threading.Event,
    *,
    progress: bool = True,
    on_start: Callable[[list[str]], None] | None = None,
    on_wait: OnWait | None = None,
) -> tuple[ExperimentConfig, dict[str, AlgorithmRun]]:
    """Run (or continue) every session of `config` not finished in `out` on the fleet, with a
    progress bar on stderr; then read every session back from its journal.

    Returns:
        `config` with the fleet's θ box as its bounds, and every algorithm's sessions.

    Args:
        stop: set it (e.g. on SIGINT) to stop after the running rollouts (resumable).
        on_start: called with the robots used, once they are found.
        on_wait: called once if the robots are not alive at the start, as that wait begins
            (`open_fleet`).

    Raises:
        ConfigError: a named robot is not alive.
        NoRobot: no robot alive at the start, or none for `robot_wait` s during the run.
        Interrupted: `stop` was set before the end.
        ExperimentError: a session failed again and again on live robots.
    """
    with open_fleet(
        settings.net, settings.robots, settings.start_timeout, settings.rpc_timeout, on_wait
    ) as fleet:
        config = replace(config, bounds=fleet_box(fleet))
        work = _Experiment(config, out, settings)
        prefixes = [r.prefix for r in fleet]
        if on_start is not None:
            on_start(prefixes)
        threads = [
            threading.Thread(target=work.work, args=(r,), name=f"robot {r.prefix}", daemon=True)
            for r in fleet
        ]
        start = time.monotonic()
        none_since: float | None = None
        with (
            StackWatch(fleet[0].node.session) as watch,
            _bar(not progress) as bar,
        ):
            task = bar.add_task(
                f"{len(fleet)} robot{'s' * (len(fleet) > 1)}",
                total=work.total_sessions,
                completed=work.finished,
                info="",
            )
            for thread in threads:
                thread.start()
            while any(t.is_alive() for t in threads):
                finished, info = work.progress(time.monotonic() - start)
                bar.update(task, completed=finished, info=info)
                if stop.wait(0.5):
                    work.stop_all()
                if set(prefixes) & set(watch.robots()):
                    none_since = None
                else:
                    none_since = none_since or time.monotonic()
                    if time.monotonic() - none_since > settings.robot_wait:
                        work.queue.fail(
                            NoRobot(
                                f"no robot of {', '.join(prefixes)} alive for "
                                f"{settings.robot_wait:g} s; start them and continue with "
                                f"--resume {out}"
                            )
                        )
                        work.stop_all()
            finished, info = work.progress(time.monotonic() - start)
            bar.update(task, completed=finished, info=info)
    if work.queue.error is not None:
        raise work.queue.error
    if stop.is_set() and not work.queue.empty():
        raise Interrupted(
            f"stopped with {work.total_sessions - work.finished} sessions unfinished; continue "
            f"with --resume {out}"
        )
    if work.moved:
        log.info("%d sessions moved to another robot after a robot was lost", work.moved)
    return config, runs_from_journals(config, out)


def fleet_box(fleet: list[FleetRobot]) -> ThetaBox:
    """The θ box (m) of the fleet's controllers: every learner searches in it.

    Raises:
        ConfigError: the robots' boxes differ (choose robots of one kind with --robots).
        RigError: a controller did not tell its box.
    """
    boxes = {robot.prefix: robot.rig.theta_box() for robot in fleet}
    first = fleet[0].prefix
    for prefix, box in boxes.items():
        if box != boxes[first]:
            raise ConfigError(
                f"robots {first} and {prefix} have different θ boxes "
                f"({msgspec.to_builtins(boxes[first])} and {msgspec.to_builtins(box)} m); use "
                "robots of one kind (--robots)"
            )
    return boxes[first]


#: Flags of the ballistic world that the MuJoCo robot does not take from the experiment.
BALLISTIC_ONLY = (
    "--distance",
    "--wind",
    "--wind-change",
    "--drag",
    "--noise",
    "--bow-stiffness",
    "--start",
    "--from",
)


def check_mesh_flags(args: argparse.Namespace, parser: argparse.ArgumentParser) -> None:
    """Refuse the ballistic world's scene flags with --world mesh (the robot's scene is set on
    `archery robot`); and --resume without --world mesh is refused by the caller.

    Raises:
        ExperimentError: one of `BALLISTIC_ONLY` was given.
    """
    for flag in BALLISTIC_ONLY:
        dest = "from_" if flag == "--from" else flag[2:].replace("-", "_")
        if getattr(args, dest) != parser.get_default(dest):
            raise ExperimentError(
                f"{flag} sets the ballistic world; with --world mesh the scene is the robot's "
                f"(`archery robot --help`)"
            )


def mesh_experiment_config(config: ExperimentConfig) -> ExperimentConfig:
    """`config` for the robot: its start θ is the robot's (`protocol.robotspec.THETA0`)."""
    return replace(config, scenario=replace(config.scenario, start=THETA0))


def run_from_args(
    args: argparse.Namespace, parser: argparse.ArgumentParser, config: ExperimentConfig, out: Path
) -> tuple[ExperimentConfig, dict[str, AlgorithmRun]]:
    """What `archery experiment --world mesh` runs: checks, the fleet, every session.

    Returns:
        The config as run (the robot's start θ) and every algorithm's sessions.

    Raises:
        ExperimentError, ConfigError: bad input (exit status 2).
        NoRobot, Interrupted, FleetFailure, JournalError: the run could not finish (exit 1).
    """
    check_mesh_flags(args, parser)
    config = mesh_experiment_config(config)
    robots = None
    if args.robots is not None:
        robots = tuple(p.strip() for p in args.robots.split(",") if p.strip())
        if not robots or len(set(robots)) != len(robots):
            raise ExperimentError(f"--robots needs distinct robot prefixes, got {args.robots!r}")
    settings = MeshSettings(
        NetConfig.from_args(args),
        robots,
        start_timeout=_seconds(args.wait, "--wait"),
        robot_wait=_seconds(args.robot_wait, "--robot-wait"),
    )
    prepare_out(out, config, resume=args.resume is not None)
    # Until the robots are found, Ctrl-C ends the wait at once (exit status 130, no session
    # started); from then on it stops after the running rollouts (resumable).
    stop = threading.Event()
    if args.log_level == DEFAULT_SPEC:
        # A line per rollout or abort of every robot would bury the bar; the journals hold them.
        logging.getLogger("archery.learner").setLevel(logging.ERROR)

    def started(prefixes: list[str]) -> None:
        shutdown_on_signals(stop)
        print(f"archery experiment: robots {', '.join(prefixes)}", file=sys.stderr, flush=True)

    return run_mesh_experiment(
        config,
        out,
        settings,
        stop,
        progress=not args.no_progress,
        on_start=started,
        on_wait=announce("experiment"),
    )


def _seconds(text: str, flag: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and 0.5 <= value <= 3600):
        raise ExperimentError(f"{flag} needs seconds in [0.5, 3600], got {text!r}")
    return value


def write_mesh_figures(
    out: Path, config: ExperimentConfig, runs: dict[str, AlgorithmRun], band: str = "median"
) -> None:
    """fig6.png (distance per rollout over sessions, `band` as `plots.plot_convergence`) and
    fig5.png (session 0's impacts on the target face per algorithm) of a run on the robot."""
    from archery.apps.experiment.plots import plot_convergence
    from archery.apps.experiment.plots_mesh import plot_impacts

    labels = {name: ALGORITHMS[name].label for name in runs}
    title = f"{config.sessions} sessions × {config.rollouts} rollouts; MuJoCo iCub over the mesh"
    if config.power_scale is not None:
        title += f", PoWER's R = exp(−‖r‖/{100 * config.power_scale:g} cm)"
    plot_convergence(runs, labels, out / "fig6.png", title=title, band=band)
    plot_impacts(runs, labels, out / "fig5.png", session=0, title=title)
