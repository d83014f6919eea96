"""Benchmark of the whole shot (`--shot whole`) beside the posture-only shot.

Run `python -m benchmarks.bench_whole_shot [--sessions 10] [--shots 100] [--rollouts 15]`:
the DMPs' reproduction error (joint RMS, rad); `--shots` whole movements at random θ in the box
(the controller's `posture` with `shot: whole`, then the release) on a robot at rtf 0 and
`--paced` at `--paced-rtf`: each outcome, and each movement's simulated time against the
demonstration's (goal within 5 %); then sessions of seeds 0, 1, … interleaved seed by seed:
ARCHER on the posture shot (the baseline), ARCHER and archer-prior on the whole shot, all at
rtf 0 (goals: whole-shot ARCHER median ≤ 5 rollouts to the 5 cm ring, every seed within 15;
archer-prior ≤ 2; wall per attempt whole / posture ≤ 4×); Fig. 6 of ARCHER's two shots.
Writes `runs/bench-whole-shot/bench.json` and `fig6-whole-shot.png`; `--smoke`: the smallest
budget in a temporary folder.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from archery.apps.learn.follow import follow
from archery.apps.progress import progress_bar
from archery.apps.up.launch_config import SERVICES, MeshConfig, RobotSpec, RouterSpec, ServiceSpec
from archery.apps.up.launcher import Launcher
from archery.mesh.node import Node
from archery.mesh.router import free_tcp_endpoint
from archery.protocol.demonstration import parse_demonstration
from archery.protocol.errors import ArcheryError
from archery.protocol.journal_records import DoneRecord
from archery.protocol.messages import Rollout
from archery.protocol.theta import THETA_BOX
from archery.protocol.verbs import controller as cv
from archery.protocol.verbs import learner as lv
from archery.protocol.verbs import robot as rv
from archery.services.controller.demonstration_file import SHIPPED_DEMONSTRATION
from archery.services.controller.movement import Movement
from archery.services.learner.journal import read_records
from benchmarks.machine import cpu_model
from benchmarks.spread import median_spread

__all__ = ["main"]

SHOTS = ("posture", "whole")
#: The sessions of each seed, interleaved: (shot, algorithm)
RUNS = (("posture", "archer"), ("whole", "archer"), ("whole", "archer-prior"))


def _mesh(
    shot: str, logs: Path, services: tuple[str, ...] = SERVICES, rtf: float = 0.0
) -> Launcher:
    """A router and `services` of one robot at `rtf` running `shot`, up."""
    mesh = MeshConfig(
        RouterSpec(free_tcp_endpoint()),
        (RobotSpec(f"bench{shot}{os.getpid()}", services),),
        {
            "robot": ServiceSpec(("--rtf", f"{rtf:g}", "--shot", shot)),
            "learner": ServiceSpec(("--runs", str(logs.parent / "sessions"))),
        },
    )
    launcher = Launcher(logs=logs / shot, mesh=mesh)
    launcher.up(180)
    return launcher


def _success(shots: int, out: Path, rtf: float) -> dict[str, Any]:
    """`shots` whole movements at random θ in the box, each the controller's posture with
    `shot: whole` then the release, on a robot at `rtf` with its controller; each outcome
    counted, the simulated time of each movement kept."""
    launcher = _mesh("whole", out / f"logs-success-{rtf:g}", ("robot", "controller"), rtf)
    rng = np.random.default_rng(0)
    outcomes: dict[str, int] = {}
    walls: list[float] = []
    sim: list[float] = []  # simulated s of each movement that reached the release
    leads: list[float] = []  # simulated s from where the robot stood to the movement's start
    try:
        with Node(None, launcher.net) as node:
            node.wait_alive(["robot", "controller"], 60)
            key = node.keys.archery_rpc()
            posture = node.keys.cartesian_rpc("archery")
            with progress_bar() as bar:
                task = bar.add_task(f"grasp and nock at random θ, rtf {rtf:g}", total=shots)
                for _ in range(shots):
                    theta = [float(v) for v in rng.uniform(THETA_BOX.low, THETA_BOX.high)]
                    args = cv.PostureArgs(theta=theta, shot="whole")
                    start = time.perf_counter()
                    try:
                        reply = node.call_typed(posture, cv.POSTURE, args, timeout=300)
                        sim.append(reply.movement_sim_s)
                        leads.append(reply.lead_sim_s)
                        node.call_typed(key, rv.RELEASE, timeout=60)
                        code = "grasped_and_nocked"
                    except ArcheryError as exc:
                        code = exc.code
                        node.call_typed(key, rv.RESET, rv.ResetArgs(), timeout=60)
                    walls.append(time.perf_counter() - start)
                    outcomes[code] = outcomes.get(code, 0) + 1
                    bar.advance(task)
    finally:
        launcher.stop_all()
    demo = parse_demonstration(SHIPPED_DEMONSTRATION.read_bytes())
    demonstrated = Movement(demo).release - demo.samples[0].t
    return {
        "rtf": rtf,
        "outcomes": outcomes,
        "wall_s_median": statistics.median(walls),
        "sim_s": sim,
        "sim_s_median": statistics.median(sim) if sim else None,
        "lead_s": leads,
        "demonstrated_sim_s": demonstrated,
    }


def _session(launcher: Launcher, seed: int, rollouts: int, algo: str) -> dict[str, Any]:
    """One session of `algo` of `rollouts` rollouts (not ended at a hit) on `launcher`'s mesh:
    the first hit, the attempts, the wall time and each rollout's θ, r and true r (m)."""
    with Node(None, launcher.net) as node:
        stream = node.subscribe(node.keys.learner_rollouts(), Rollout, mode="fifo")
        node.wait_alive(SERVICES, 60)
        start = time.perf_counter()
        args = lv.StartArgs(algo=algo, seed=seed, rollouts=rollouts, until_hit=False)
        status = node.call_typed(node.keys.learner_rpc(), lv.START, args, timeout=60)
        final = follow(node, str(status.session), stream, lambda m: None)
        wall = time.perf_counter() - start
    done = [r for r in read_records(Path(final["journal"]))[0] if isinstance(r, DoneRecord)]
    attempts = int(final["rollouts"]) + int(final.get("aborted", 0))
    return {
        "seed": seed,
        "hit_at": next((r.rollout for r in done if r.hit), None),
        "rollouts": final["rollouts"],
        "aborted": final.get("aborted", 0),
        "wall_s": wall,
        "wall_s_per_attempt": wall / max(1, attempts),
        "theta": [r.theta for r in done],
        "r_m": [r.r_m for r in done],
        "truth_r_m": [r.truth_r_m if r.truth_r_m is not None else r.r_m for r in done],
    }


def _fig6(sessions: dict[str, list[dict[str, Any]]], path: Path, rollouts: int) -> None:
    """Fig. 6 of ARCHER on the whole shot beside the posture shot (the true distances) over
    the sessions that ran all `rollouts` (a failed session is counted in the table only)."""
    from archery.apps.experiment.config import AlgorithmRun
    from archery.apps.experiment.plots import plot_convergence

    runs = {
        shot: AlgorithmRun(
            name="archer",
            thetas=np.array([s["theta"] for s in done]),
            r_observed=np.array([s["r_m"] for s in done]),
            r_true=np.array([s["truth_r_m"] for s in done]),
            wall_time=sum(s["wall_s"] for s in done),
        )
        for shot, all_done in sessions.items()
        if (done := [s for s in all_done if len(s["theta"]) == rollouts])
    }
    labels = {"posture": "ARCHER, posture shot", "whole": "ARCHER, whole shot (DMPs)"}
    title = "ARCHER on the MuJoCo iCub: the whole shot beside the posture shot"
    plot_convergence(runs, labels, path, title=title)


def _quartiles(values: list[float]) -> str:
    q1, median, q3 = np.percentile(values, [25, 50, 75])
    return f"{median:g} [{q1:g}, {q3:g}]"


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark; exit status 0."""
    os.environ.setdefault("MUJOCO_GL", "egl")
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.bench_whole_shot", description=__doc__
    )
    parser.add_argument("--sessions", type=int, default=10, help="sessions (seeds) per run")
    parser.add_argument("--rollouts", type=int, default=15, help="rollouts of each session")
    parser.add_argument("--shots", type=int, default=100, help="movements at random θ, rtf 0")
    parser.add_argument("--paced", type=int, default=5, help="movements at --paced-rtf")
    parser.add_argument("--paced-rtf", type=float, default=1.0, help="rtf of those movements")
    parser.add_argument("--out", default="runs/bench-whole-shot", help="output directory")
    parser.add_argument(
        "--smoke",
        action="store_true",
        help="1 session per run of 6 rollouts, 3 movements at rtf 0 and 1 at rtf 4; output in "
        "a temporary folder",
    )
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="bench-whole-shot-") as tmp:
        if args.smoke:
            args.sessions, args.rollouts, args.shots, args.out = 1, 6, 3, tmp
            args.paced, args.paced_rtf = 1, 4.0
        return _run(args)


def _run(args: argparse.Namespace) -> int:
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    demo = parse_demonstration(SHIPPED_DEMONSTRATION.read_bytes())
    rms = Movement(demo).error(demo)
    success = _success(args.shots, out, 0.0)
    paced = _success(args.paced, out, args.paced_rtf)
    sessions: dict[str, list[dict[str, Any]]] = {f"{s}/{a}": [] for s, a in RUNS}
    meshes = {shot: _mesh(shot, out / "logs") for shot in SHOTS}
    try:
        with progress_bar() as bar:
            task = bar.add_task("learning sessions", total=args.sessions * len(RUNS))
            for seed in range(args.sessions):  # interleaved: each seed on each run in turn
                for shot, algo in RUNS:
                    run = _session(meshes[shot], seed, args.rollouts, algo)
                    sessions[f"{shot}/{algo}"].append(run)
                    bar.advance(task)
    finally:
        for launcher in meshes.values():
            launcher.stop_all()
    result = {
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "machine": cpu_model(),
        "dmp_rms_rad": rms,
        "success": success,
        "paced": paced,
        "sessions": sessions,
    }
    (out / "bench.json").write_text(json.dumps(result, indent=1, allow_nan=False))
    archer = {shot: sessions[f"{shot}/archer"] for shot in SHOTS}
    _fig6(archer, out / "fig6-whole-shot.png", args.rollouts)
    print(f"\n{result['date']}, {result['machine']}\n")
    print(f"DMP reproduction error (joint RMS, 14 joints): {rms:.2e} rad\n")
    for moved in (success, paced):
        total = sum(moved["outcomes"].values())
        print(f"Whole-shot movements at random θ in the box, rtf {moved['rtf']:g} ({total}):\n")
        print("| outcome | count | share |\n|---|---|---|")
        for code, n in sorted(moved["outcomes"].items(), key=lambda kv: -kv[1]):
            print(f"| {code} | {n} | {100 * n / total:.0f} % |")
        ratio = [t / moved["demonstrated_sim_s"] for t in moved["sim_s"]]
        print(
            f"\nwall per movement and release: {moved['wall_s_median']:.2f} s (median); "
            f"simulated time of a movement to the release against the demonstration's "
            f"{moved['demonstrated_sim_s']:.2f} s: ×{median_spread(ratio, '.4f')} (goal within "
            f"5 %); before it, from where the robot stood (after a release, the drawn "
            f"posture) to the demonstrated start: {median_spread(moved['lead_s'], '.2f')} s\n"
        )
    print("| shot | algorithm | sessions hit | rollouts to 5 cm, median [q1, q3] | worst seed |")
    print("|---|---|---|---|---|")
    for name, runs in sessions.items():
        shot, algo = name.split("/")
        hits = [float(x["hit_at"]) for x in runs if x["hit_at"] is not None]
        to_hit = _quartiles(hits) if hits else "–"
        worst = f"{max(hits):g}" if len(hits) == len(runs) else "no hit"
        print(f"| {shot} | {algo} | {len(hits)}/{len(runs)} | {to_hit} | {worst} |")
    walls = {s: [x["wall_s_per_attempt"] for x in archer[s]] for s in SHOTS}
    print("\n| shot | wall s per attempt (ARCHER) |\n|---|---|")
    for shot in SHOTS:
        print(f"| {shot} | {median_spread(walls[shot], '.2f')} |")
    ratios = [w / p for w, p in zip(walls["whole"], walls["posture"], strict=True)]
    print(
        f"\nwall per attempt at rtf 0, whole / posture (per seed): "
        f"×{median_spread(ratios, '.2f')} (goal ≤ 4)"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
