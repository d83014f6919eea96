"""Benchmark of a wind change on the MuJoCo iCub: rollouts to hit the 5 cm ring again.

Run `MUJOCO_GL=egl python -m benchmarks.bench_robot_wind [--sessions 10]`. A router and the five
services run as child processes (`apps.up.launcher.Launcher`, as in `benchmarks.bench_prior`).
Each session learns in calm air; right after its first hit (the learner's `done` rollout on
`learner/rollout:o`), the benchmark calls the robot's `setWind` with `WIND`, so the wind turns
from the next rollout on, as `archery experiment --wind-change` does on the ballistic world. The
session then continues until it hits again, or `AFTER` rollouts later. Reported per learner:
rollouts to re-hit (the first rollout under the new wind counts as 1; `AFTER + 1` if none),
median [q1, q3], and sessions hitting again.

The change must land between two shots: the benchmark compares the robot's shot count (`status`,
after `setWind`) with the hit's shot (its `done` record in the journal) and counts a shot already
released under the old wind as a delay ("late shots"), moving the change one rollout on.

Writes bench.json under --out and prints the table.

`--smoke`: one session per learner on the same whole mesh, `SMOKE_BEFORE` rollouts to the first
hit and `SMOKE_AFTER` after the change (tens of seconds, most of it the mesh's start-up; its
figures are noise), bench.json in a temporary directory, removed after.
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

from benchmarks.learning_mesh import learning_mesh, progress_bar
from tests.rpc import rpc_call

__all__ = ["AFTER", "ALGORITHMS", "BEFORE", "WIND", "main"]

WIND = (0.0, 15.0, 0.0)  # m/s: moves a centred shot ~10 cm sideways on the target
ALGORITHMS = ("archer-prior", "archer-recent", "archer", "power")
BEFORE = {"archer-prior": 30, "archer-recent": 30, "archer": 30, "power": 60}  # to the first hit
AFTER = 30  # rollouts under the new wind to hit again
SMOKE_BEFORE, SMOKE_AFTER = 5, 3  # the smoke run's budgets (rollouts)


def _quartiles(values: np.ndarray) -> str:
    q1, median, q3 = np.percentile(values, [25, 50, 75])
    return f"{median:g} [{q1:g}, {q3:g}]"


def _session(
    node: Any, rollouts: Any, algo: str, seed: int, before: int, after: int
) -> dict[str, Any]:
    """One session of `algo`: up to `before` rollouts to the first hit, the wind changed after
    it, then up to `after` rollouts to hit again."""
    from archery.apps.learn.follow import follow
    from archery.protocol.journal_records import DoneRecord
    from archery.services.learner.journal import read_records

    robot, learner = node.keys.archery_rpc(), node.keys.learner_rpc()
    rpc_call(node, robot, "setWind", {"wind": [0.0, 0.0, 0.0]}, timeout=20)
    journal: list[Path] = []
    state: dict[str, Any] = {
        "first_hit": None,
        "change_at": None,
        "late_shots": 0,
        "rehit_at": None,
        "stopped": False,
    }

    def stop() -> None:
        if not state["stopped"]:
            state["stopped"] = True
            rpc_call(node, learner, "stop", timeout=20)

    def on_rollout(message: Any) -> None:
        record = message.record
        if not isinstance(record, DoneRecord):
            return
        index = record.index
        truth = None if record.truth_r_m is None else [100 * v for v in record.truth_r_m]
        if state["first_hit"] is None:
            if record.hit:
                rpc_call(node, robot, "setWind", {"wind": list(WIND)}, timeout=20)
                now = rpc_call(node, robot, "status", timeout=20)["shot"]
                records = read_records(journal[0])[0]
                shot = next(
                    r.shot for r in records if isinstance(r, DoneRecord) and r.index == index
                )
                late = now - shot
                state.update(first_hit=index, change_at=index + 1 + late, late_shots=late)
                state["truth_cm_hit"] = truth
            elif index >= before:
                stop()
        elif index >= state["change_at"]:
            if index == state["change_at"]:
                state["truth_cm_first_after"] = truth
            if record.hit and state["rehit_at"] is None:
                state["rehit_at"] = index
                stop()
            elif index >= state["change_at"] + after - 1:
                stop()

    request = {"algo": algo, "seed": seed, "rollouts": before + after + 2}
    request["until_hit"] = False
    start = time.perf_counter()
    started = rpc_call(node, learner, "start", request, timeout=60)
    session = started["session"]
    journal.append(Path(started["journal"]))
    final = follow(node, session, rollouts, on_rollout, poll=0.2)
    state["session"] = session
    state["wall_s"] = time.perf_counter() - start
    state["rollouts"] = final.get("rollouts")
    if state["rehit_at"] is not None:
        state["rehit"] = state["rehit_at"] - state["change_at"] + 1
    else:
        state["rehit"] = None if state["first_hit"] is None else after + 1
    return state


def main(argv: list[str] | None = None) -> int:
    """Run the sessions, print the table, write bench.json under --out."""
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.bench_robot_wind", description=__doc__
    )
    parser.add_argument("--out", default="runs/bench-robot-wind", help="output directory")
    parser.add_argument("--sessions", type=int, default=10, help="sessions per learner")
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    parser.add_argument(
        "--smoke",
        action="store_true",
        help=f"1 session per learner, {SMOKE_BEFORE} + {SMOKE_AFTER} rollouts, output in a "
        "temporary directory: no figures",
    )
    args = parser.parse_args(argv)
    if args.smoke:
        args.sessions = 1
        with tempfile.TemporaryDirectory(prefix="bench-robot-wind-") as tmp:
            before = dict.fromkeys(ALGORITHMS, SMOKE_BEFORE)
            return _run(args, Path(tmp).resolve(), before, SMOKE_AFTER)
    return _run(args, Path(args.out).resolve(), BEFORE, AFTER)


def _run(args: argparse.Namespace, out: Path, before: dict[str, int], after: int) -> int:
    """`args.sessions` sessions per learner (`before` rollouts to the first hit per learner,
    `after` after the change); the table printed, bench.json under `out`."""
    out.mkdir(parents=True, exist_ok=True)
    runs: dict[str, list[dict[str, Any]]] = {}
    with learning_mesh(out) as (node, rollouts), progress_bar(disable=args.no_progress) as bar:
        task = bar.add_task("robot wind", total=len(ALGORITHMS) * args.sessions)
        for algo in ALGORITHMS:
            bar.update(task, description=f"robot wind: {algo}")
            for seed in range(args.sessions):
                runs.setdefault(algo, []).append(
                    _session(node, rollouts, algo, seed, before[algo], after)
                )
                bar.advance(task)

    wind = ", ".join(f"{w:g}" for w in WIND)
    table = [
        f"| robot learner | rollouts to the first hit: median [q1, q3] | to hit again after the "
        f"wind turns to {wind} m/s: median [q1, q3] | sessions hitting again | late shots |",
        "|---|---|---|---|---|",
    ]
    summary: dict[str, Any] = {"wind": list(WIND), "after": after, "learners": {}}
    for algo in ALGORITHMS:
        sessions = runs[algo]
        first = np.array([s["first_hit"] or before[algo] + 1 for s in sessions])
        changed = [s for s in sessions if s["first_hit"] is not None]
        rehit = np.array([s["rehit"] for s in changed]) if changed else np.array([np.nan])
        again = sum(s["rehit_at"] is not None for s in changed)
        late = sum(s["late_shots"] for s in sessions)
        table.append(
            f"| {algo} | {_quartiles(first)} | {_quartiles(rehit)} "
            f"| {again}/{len(changed)} (of {len(sessions)}) | {late} |"
        )
        summary["learners"][algo] = {"sessions": sessions}
    print("\n".join(table))
    (out / "bench.json").write_text(json.dumps(summary, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
