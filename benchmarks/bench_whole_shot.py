"""Benchmark of the whole shot (`--shot whole`) beside the posture-only shot.

Run `python -m benchmarks.bench_whole_shot [--sessions 10] [--shots 100] [--rollouts 20]`:

* the DMPs' reproduction error against the shipped demonstration (joint RMS over both arms'
  14 joints and every sample, rad; `services.learner.movement.Movement.error`);
* grasp and nock success over `--shots` whole-shot movements (`WholeMovement.perform`, then
  the release) at θ drawn uniformly in the controller's θ box, on a robot at rtf 0 alone on a
  router: each outcome counted (grasped and nocked, grasp_missed, nock_missed, θ out of the
  string arm's reach, …);
* rollouts to the 5 cm ring with ARCHER, `--sessions` sessions (seeds 0, 1, …) of `--rollouts`
  rollouts each on a mesh of the five services whose robot runs `--shot whole` and, interleaved
  seed by seed, on one whose robot runs `--shot posture` (the baseline, today's default), both
  up for the whole run at rtf 0: median [q1, q3] of the first hit (the detector's), sessions
  that hit, and the wall time per attempt (s; the session's wall time over its done and
  aborted attempts) with its ratio to the posture shot's; Fig. 6 of both (the true distance
  per rollout, median and interquartile band).

Prints Markdown tables; writes `runs/bench-whole-shot/bench.json` and `fig6-whole-shot.png`.
`--smoke`: one session of each shot of 6 rollouts and 3 movements, output in a temporary
folder.
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

from apps.learn.follow import follow
from apps.progress import progress_bar
from apps.up.launch_config import SERVICES, MeshConfig, RobotSpec, RouterSpec, ServiceSpec
from apps.up.launcher import Launcher
from benchmarks.machine import cpu_model
from benchmarks.spread import median_spread
from mesh.node import Node
from mesh.router import free_tcp_endpoint
from protocol.demonstration import parse_demonstration
from protocol.errors import ArcheryError
from protocol.journal_records import DoneRecord
from protocol.messages import Rollout
from protocol.verbs import learner as lv
from protocol.verbs import robot as rv
from protocol.verbs.controller import THETA_MAX, THETA_MIN
from services.learner.config import SHIPPED_DEMONSTRATION
from services.learner.journal import read_records
from services.learner.movement import Movement
from services.learner.whole_movement import WholeMovement
from sim.scene_config import SceneConfig

__all__ = ["main"]

SHOTS = ("posture", "whole")


def _mesh(shot: str, logs: Path, services: tuple[str, ...] = SERVICES) -> Launcher:
    """A router and `services` of one robot at rtf 0 running `shot`, up."""
    mesh = MeshConfig(
        RouterSpec(free_tcp_endpoint()),
        (RobotSpec(f"bench{shot}{os.getpid()}", services),),
        {
            "robot": ServiceSpec(("--rtf", "0", "--shot", shot)),
            "learner": ServiceSpec(("--runs", str(logs.parent / "sessions"))),
        },
    )
    launcher = Launcher(logs=logs / shot, mesh=mesh)
    launcher.up(180)
    return launcher


def _success(shots: int, out: Path) -> dict[str, Any]:
    """`shots` whole movements at random θ in the box on a robot alone; each outcome counted."""
    launcher = _mesh("whole", out / "logs-success", ("robot",))
    rng = np.random.default_rng(0)
    outcomes: dict[str, int] = {}
    walls: list[float] = []
    sim: list[float] = []  # simulated s of each movement that reached the release
    try:
        with Node(None, launcher.net) as node:
            node.wait_alive(["robot"], 60)
            key = node.keys.archery_rpc()
            status = node.call_typed(key, rv.ARCHERY_STATUS)
            movement = Movement(parse_demonstration(SHIPPED_DEMONSTRATION.read_bytes()))
            whole = WholeMovement(
                node, 30.0, movement, SceneConfig(**status.scene), status.world["reference_speed"]
            )
            try:
                with progress_bar() as bar:
                    task = bar.add_task("grasp and nock at random θ", total=shots)
                    for _ in range(shots):
                        theta = rng.uniform(THETA_MIN, THETA_MAX)
                        start = time.perf_counter()
                        try:
                            begun = node.call_typed(key, rv.ARCHERY_STATUS).sim_time
                            whole.perform(theta)
                            drawn = node.call_typed(key, rv.ARCHERY_STATUS).sim_time
                            sim.append(drawn - begun)
                            whole.arms.act("release")
                            code = "grasped_and_nocked"
                        except ArcheryError as exc:
                            code = exc.code
                        walls.append(time.perf_counter() - start)
                        outcomes[code] = outcomes.get(code, 0) + 1
                        bar.advance(task)
            finally:
                whole.close()
    finally:
        launcher.stop_all()
    return {
        "outcomes": outcomes,
        "wall_s_median": statistics.median(walls),
        "sim_s_median": statistics.median(sim) if sim else None,
        "demonstrated_sim_s": movement.release,
    }


def _session(launcher: Launcher, seed: int, rollouts: int) -> dict[str, Any]:
    """One ARCHER session of `rollouts` rollouts (not ended at a hit) on `launcher`'s mesh:
    the first hit, the attempts, the wall time and each rollout's θ, r and true r (m)."""
    with Node(None, launcher.net) as node:
        stream = node.subscribe(node.keys.learner_rollouts(), Rollout, mode="fifo")
        node.wait_alive(SERVICES, 60)
        start = time.perf_counter()
        args = lv.StartArgs(algo="archer", seed=seed, rollouts=rollouts, until_hit=False)
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
    from apps.experiment.config import AlgorithmRun
    from apps.experiment.plots import plot_convergence

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
    parser.add_argument("--sessions", type=int, default=10, help="ARCHER sessions per shot")
    parser.add_argument("--rollouts", type=int, default=12, help="rollouts of each session")
    parser.add_argument("--shots", type=int, default=100, help="movements at random θ")
    parser.add_argument("--out", default="runs/bench-whole-shot", help="output directory")
    parser.add_argument(
        "--smoke",
        action="store_true",
        help="1 session per shot of 6 rollouts, 3 movements; output in a temporary folder",
    )
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="bench-whole-shot-") as tmp:
        if args.smoke:
            args.sessions, args.rollouts, args.shots, args.out = 1, 6, 3, tmp
        return _run(args)


def _run(args: argparse.Namespace) -> int:
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    demo = parse_demonstration(SHIPPED_DEMONSTRATION.read_bytes())
    rms = Movement(demo).error(demo)
    success = _success(args.shots, out)
    sessions: dict[str, list[dict[str, Any]]] = {shot: [] for shot in SHOTS}
    meshes = {shot: _mesh(shot, out / "logs") for shot in SHOTS}
    try:
        with progress_bar() as bar:
            task = bar.add_task("ARCHER sessions", total=args.sessions * len(SHOTS))
            for seed in range(args.sessions):  # interleaved: each seed on both shots in turn
                for shot in SHOTS:
                    sessions[shot].append(_session(meshes[shot], seed, args.rollouts))
                    bar.advance(task)
    finally:
        for launcher in meshes.values():
            launcher.stop_all()
    result = {
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "machine": cpu_model(),
        "dmp_rms_rad": rms,
        "success": success,
        "sessions": sessions,
    }
    (out / "bench.json").write_text(json.dumps(result, indent=1, allow_nan=False))
    _fig6(sessions, out / "fig6-whole-shot.png", args.rollouts)
    print(f"\n{result['date']}, {result['machine']}\n")
    print(f"DMP reproduction error (joint RMS, 14 joints): {rms:.2e} rad\n")
    total = sum(success["outcomes"].values())
    print(f"Whole-shot movements at random θ in the box ({total}):\n")
    print("| outcome | count | share |\n|---|---|---|")
    for code, n in sorted(success["outcomes"].items(), key=lambda kv: -kv[1]):
        print(f"| {code} | {n} | {100 * n / total:.0f} % |")
    print(
        f"\nwall per movement and release: {success['wall_s_median']:.2f} s (median); simulated "
        f"time of a movement to the release: {success['sim_s_median']} s (median; the "
        f"demonstration's {success['demonstrated_sim_s']:.2f} s)\n"
    )
    print("| shot | sessions hit | rollouts to 5 cm, median [q1, q3] | wall s per attempt |")
    print("|---|---|---|---|")
    walls = {s: [x["wall_s_per_attempt"] for x in sessions[s]] for s in SHOTS}
    for shot in SHOTS:
        hits = [float(x["hit_at"]) for x in sessions[shot] if x["hit_at"] is not None]
        to_hit = _quartiles(hits) if hits else "–"
        print(
            f"| {shot} | {len(hits)}/{len(sessions[shot])} | {to_hit} | "
            f"{median_spread(walls[shot], '.2f')} |"
        )
    ratios = [w / p for w, p in zip(walls["whole"], walls["posture"], strict=True)]
    print(f"\nwall per attempt, whole / posture (per seed): ×{median_spread(ratios, '.2f')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
