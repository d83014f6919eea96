"""`archery drill`: fault drills against real processes on loopback, and their table.

Each drill starts (or reuses) a mesh as `archery up` runs it (`apps.drills.mesh`), runs a
learning session on it, injects one fault and judges the outcome from the session's journal
(`apps.drills.verdict`). The drills are listed by `_catalogue`, how their times to detect and
recover are measured by `render`, and the goals beside `DETECT_GOALS`. Exit status 0 when
every drill passed, 1 otherwise, 2 for bad flags.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

from rich.console import Console
from rich.table import Table

from archery.apps.drills.flood import flood_drill
from archery.apps.drills.freeze import LEASE, freeze_service
from archery.apps.drills.kill import kill_learner, kill_learner_repeatedly, kill_service
from archery.apps.drills.mesh import DrillMesh
from archery.apps.drills.order import start_order_drill
from archery.apps.drills.router import router_outage
from archery.apps.drills.verdict import DrillResult
from archery.apps.progress import progress_bar
from archery.apps.up.launch_config import SERVICES
from archery.mesh.cliargs import (
    ArgumentParser,
    add_force_arg,
    check_output_file,
    check_writable_dir,
    count,
)
from archery.protocol.errors import ArcheryError, ConfigError

__all__ = ["DRILLS", "QUICK", "Drill", "Drills", "main", "render", "run_drills"]

# Goals (noted when missed, not verdicts), in s: a crash noticed within 1 s, a freeze within
# the lease + 1 s, the session going on within 5 s of the service's return.
DETECT_GOALS = {"kill": 1.0, "freeze": LEASE + 1.0}
RECOVER_GOAL = 5.0


class Drills:
    """What the drills of one run share: a work directory, the base seed and one mesh, started
    on first use and replaced when a drill leaves it broken."""

    def __init__(self, workdir: Path, seed: int) -> None:
        self.workdir = workdir
        self.seed = seed
        self._mesh: DrillMesh | None = None
        self._meshes = 0

    def mesh(self) -> DrillMesh:
        """A running mesh, every service alive."""
        if self._mesh is not None and self._mesh.problems():
            self.discard()
        if self._mesh is not None:
            try:
                self._mesh.wait_alive(timeout=30)
            except ArcheryError as exc:  # said, not silent: the next drill gets a fresh mesh
                print(
                    f"archery drill: the mesh is not whole ({exc}); starting a fresh one",
                    file=sys.stderr,
                    flush=True,
                )
                self.discard()
        if self._mesh is None:
            self._meshes += 1
            self._mesh = DrillMesh(self.workdir / f"mesh{self._meshes}")
        return self._mesh

    def discard(self) -> None:
        """Stop the shared mesh (the next drill starts a new one)."""
        if self._mesh is not None:
            self._mesh.close()
            self._mesh = None


@dataclass(frozen=True)
class Drill:
    """One drill: its name, family and how it runs (given the shared state and its seed)."""

    name: str
    family: str
    run: Callable[[Drills, int], DrillResult]


def _catalogue() -> dict[str, Drill]:
    """Every drill by name (see each family's module):

    * `kill-SERVICE`: SIGKILL of each service mid-session (`apps.drills.kill`);
    * `freeze-SERVICE`: SIGSTOP of each service for 12 s (beyond the 10 s Zenoh lease), then
      SIGCONT (`apps.drills.freeze`);
    * `router-2s`, `router-15s`: the router SIGKILLed and restarted 2 s / 15 s later
      (`apps.drills.router`);
    * `order-0` … `order-5`: the router started in each position among the services
      (`apps.drills.order`);
    * `flood-20000`, `flood-2000`: 20,000 (2,000) valid and invalid joint commands on
      `ROBOT/left_arm/command:i` (`apps.drills.flood`);
    * `kill-learner-x20`, `kill-learner-x3`: the learner SIGKILLed 20 (3) times at seeded
      random points, resumed each time.
    """
    drills: list[Drill] = []
    for service in SERVICES:
        if service == "learner":
            drills.append(Drill("kill-learner", "kill", lambda d, s: kill_learner(d.mesh(), s)))
        else:
            drills.append(
                Drill(
                    f"kill-{service}",
                    "kill",
                    lambda d, s, n=service: kill_service(d.mesh(), n, s),  # type: ignore[misc]  # mypy can't type lambda defaults (mypy#15459)
                )
            )
    drills += [
        Drill(f"freeze-{n}", "freeze", lambda d, s, n=n: freeze_service(d.mesh(), n, s))  # type: ignore[misc]  # mypy can't type lambda defaults (mypy#15459)
        for n in SERVICES
    ]
    drills += [
        Drill(f"router-{o:g}s", "router", lambda d, s, o=o: router_outage(d.mesh(), o, s))  # type: ignore[misc]  # mypy can't type lambda defaults (mypy#15459)
        for o in (2.0, 15.0)
    ]
    drills += [
        Drill(f"order-{k}", "order", lambda d, s, k=k: start_order_drill(d.workdir, k, s))  # type: ignore[misc]  # mypy can't type lambda defaults (mypy#15459)
        for k in range(len(SERVICES) + 1)
    ]
    drills += [
        Drill(f"flood-{c}", "flood", lambda d, s, c=c: flood_drill(d.mesh(), c, s))  # type: ignore[misc]  # mypy can't type lambda defaults (mypy#15459)
        for c in (20_000, 2_000)
    ]
    drills += [
        Drill(
            f"kill-learner-x{k}",
            "kill",
            lambda d, s, k=k: kill_learner_repeatedly(d.mesh(), k, s),  # type: ignore[misc]  # mypy can't type lambda defaults (mypy#15459)
        )
        for k in (20, 3)
    ]
    return {d.name: d for d in drills}


DRILLS = _catalogue()
# `--quick`: about a minute
QUICK = ("kill-camera", "kill-detector", "router-2s", "flood-2000", "kill-learner-x3")
FULL = tuple(n for n in DRILLS if n not in ("flood-2000", "kill-learner-x3"))


def _goals(drill: Drill, result: DrillResult) -> None:
    """Note the goals a passed drill missed."""
    goal = DETECT_GOALS.get(drill.family)
    if goal is not None and result.detect_s is not None and result.detect_s > goal:
        result.notes.append(f"goal missed: detected after {result.detect_s:.2f} s > {goal:g} s")
    late = result.recover_s is not None and result.recover_s > RECOVER_GOAL
    if drill.family != "order" and late:
        result.notes.append(
            f"goal missed: went on after {result.recover_s:.2f} s > {RECOVER_GOAL:g} s"
        )


def run_drills(
    names: Sequence[str],
    workdir: Path,
    seed: int = 0,
    on_start: Callable[[str], None] | None = None,
) -> list[DrillResult]:
    """Run the named drills in order; their results (a drill that raised has failed)."""
    shared = Drills(workdir, seed)
    results = []
    try:
        for number, name in enumerate(names):
            drill = DRILLS[name]
            if on_start is not None:
                on_start(name)
            if drill.family == "order":
                shared.discard()  # it starts a mesh of its own: one at a time
            started = time.monotonic()
            try:
                result = drill.run(shared, seed + number)
            except Exception as exc:  # the drill fails; the next one gets a fresh mesh
                result = DrillResult(name, False, notes=[f"{type(exc).__name__}: {exc}"])
                shared.discard()
            _goals(drill, result)
            result.details["wall_s"] = round(time.monotonic() - started, 1)
            results.append(result)
    finally:
        shared.discard()
    return results


def _seconds(value: float | None) -> str:
    return "—" if value is None else f"{value:.2f}"


def render(results: Sequence[DrillResult]) -> Table:
    """The results as a rich table. Times are wall-clock seconds (`time.time()`, the clock of
    the journal records' `t`):

    * **detect**: from the fault (the signal sent) to the first sign that the mesh noticed it:
      the service's liveliness token going on the router (the learner's rig dates the loss by
      the same tokens), `up`'s supervisor reporting the exit, the learner's status listing the
      service in `waiting_for`, or a `service_lost` abort in the journal, whichever came first
      (the learner's own reaction, its status or journal, is in the notes and `--json`). The
      router and the learner: the supervisor's report or their token.
    * **recover**: from the service's return (its liveliness token back: the restarted
      process, or the frozen one reconnected after SIGCONT; the router listening again; the
      end of the flood; the last process started for the start-order drills) to the
      session's next done rollout (the journal's `t`). For repeated kills, the worst of them.
    * **lost** / **dup**: rollouts lost and duplicated, see `apps.drills.verdict`.
    """
    table = Table(title="archery drill", show_lines=False)
    for column, justify in (
        ("drill", "left"),
        ("verdict", "left"),
        ("detect (s)", "right"),
        ("recover (s)", "right"),
        ("lost", "right"),
        ("dup", "right"),
        ("notes", "left"),
    ):
        table.add_column(column, justify=justify, no_wrap=column != "notes")  # type: ignore[arg-type]  # rich's JustifyMethod literals
    for r in results:
        table.add_row(
            r.name,
            "[green]pass[/]" if r.passed else "[red]FAIL[/]",
            _seconds(r.detect_s),
            _seconds(r.recover_s),
            str(r.lost),
            str(r.duplicated),
            "; ".join(r.notes),
        )
    return table


def build_parser() -> argparse.ArgumentParser:
    """The flags of `archery drill`."""
    parser = ArgumentParser(prog="archery drill", description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help=f"only {', '.join(QUICK)}")
    parser.add_argument("--json", metavar="OUT", help="write the results as JSON to OUT (.json)")
    add_force_arg(parser, "an existing --json file")
    parser.add_argument(
        "--only",
        action="append",
        metavar="NAME",
        help=f"run only this drill (repeatable): {', '.join(DRILLS)}",
    )
    parser.add_argument(
        "--seed", type=count, default=0, help="seed of the sessions and kill points (>= 0)"
    )
    parser.add_argument(
        "--workdir",
        metavar="DIR",
        help="logs and journals (default: a new temporary directory, kept)",
    )
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run `archery drill`; exit status 0 only when every drill passed."""
    parser = build_parser()
    args = parser.parse_args(argv)
    names = list(QUICK if args.quick else FULL)
    if args.only:
        unknown = [n for n in args.only if n not in DRILLS]
        if unknown:
            parser.error(f"no drill {unknown[0]!r}; drills: {', '.join(DRILLS)}")
        names = list(dict.fromkeys(args.only))
    try:
        if args.json:
            check_output_file(args.json, "--json", (".json",), force=args.force)
        if args.workdir:
            check_writable_dir(Path(args.workdir), "--workdir", create=True)
    except ConfigError as exc:
        print(f"archery drill: {exc}", file=sys.stderr)
        return 2
    workdir = Path(args.workdir or tempfile.mkdtemp(prefix="archery-drill-"))
    # A table too wide for 80 columns: wrapped at 160 when not on a terminal (a file, CI).
    console = Console() if sys.stdout.isatty() else Console(width=160)
    with progress_bar(transient=True) as progress:
        task = progress.add_task("drills", total=len(names))
        seen: list[str] = []

        def on_start(name: str) -> None:
            if seen:
                progress.advance(task)
            seen.append(name)
            progress.update(task, description=name)

        results = run_drills(names, workdir, args.seed, on_start)
        progress.advance(task)
    console.print(render(results))
    passed = all(r.passed for r in results)
    console.print(
        f"{sum(r.passed for r in results)} of {len(results)} drills passed; logs and journals "
        f"in {workdir}"
    )
    if args.json:
        document = {
            "seed": args.seed,
            "passed": passed,
            "workdir": str(workdir),
            "drills": [r.to_dict() for r in results],
        }
        Path(args.json).write_text(json.dumps(document, indent=2) + "\n")
    return 0 if passed else 1


if __name__ == "__main__":
    sys.exit(main())
