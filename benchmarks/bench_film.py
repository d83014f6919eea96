"""Benchmark of `archery film` and of the recording's 3D records.

Run `python -m benchmarks.bench_film [--repeats 5] [--rollouts 6] [--smoke]` (`--smoke`: one
repeat of each part, 2-rollout sessions, 2 frames per render probe; seconds, nothing recorded).
It prints:

* the time to film one shot (`film_session`, 960×540 at 30 fps, H.264): seconds per film and
  per second of video, `--repeats` times;
* a scene frame's cost with the robot's meshes (`sim.scene_view.SceneView`, 960×540) on each
  GL backend in its own process, interleaved: EGL (this machine has no GPU: Mesa's llvmpipe
  behind EGL) and OSMesa (MUJOCO_GL=osmesa, libOSMesa), against the lean target-camera frame
  the camera service renders (`sim.render.SceneRenderer`, 1280×720, no meshes) in the same
  process: ms per frame and the ratio;
* the recording's size per rollout with the 3D records (`archery record`) against without
  (`--no-transforms`): pairs of `--rollouts`-rollout sessions on one mesh (`archery up`'s
  Launcher, robot at rtf 0), each recorded by one recorder of `ROBOT/**`, the pair's order
  alternating; MB per rollout (the start's fixed records taken out: the URDF and the scene's
  meshes, measured from a recording without messages) and the ratio.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from archery.apps.film.film import film_session
from archery.apps.learn.follow import follow
from archery.apps.topics.recording import Recorder
from archery.apps.up.launch_config import SERVICES
from archery.mesh.node import Node
from archery.protocol.journal_records import DoneRecord
from archery.protocol.messages import Rollout
from archery.services.learner.journal import read_records
from benchmarks.bench_record import mesh_launcher
from benchmarks.machine import cpu_model
from benchmarks.observers import stop
from benchmarks.spread import median_spread
from tests.rpc import rpc_call
from tests.spawn import spawn

__all__ = ["main"]

_FRAME_PROBE = """
import sys, time, numpy as np
from archery.sim.render import SceneRenderer
from archery.sim.scene_view import SceneView
frames = int(sys.argv[1])
with SceneView(width=960, height=540) as view, SceneRenderer() as lean:
    q = view._renderer.model.qpos0.copy()
    qs = []
    for i in range(frames + 1):
        x = q.copy(); x[0] += 0.01 * i; qs.append(x)
    view.render(qs[0]); lean.render(qs[0])
    t = time.perf_counter(); [view.render(x) for x in qs[1:]]; full = time.perf_counter() - t
    t = time.perf_counter(); [lean.render(x) for x in qs[1:]]; thin = time.perf_counter() - t
print(full / frames, thin / frames)
"""


def _frame_cost(backend: str, frames: int) -> tuple[float, float] | str:
    """(s per full frame, s per lean frame) on `backend`, or why it could not render."""
    env = os.environ | {
        "MUJOCO_GL": backend,
        "PYOPENGL_PLATFORM": backend,  # else the parent's EGL choice is inherited
        "PYTHONPATH": str(Path(__file__).parents[1]),
    }
    done = subprocess.run(
        [sys.executable, "-c", _FRAME_PROBE, str(frames)],
        capture_output=True,
        text=True,
        env=env,
        timeout=1200,
    )
    if done.returncode != 0:
        return (done.stderr.strip().splitlines() or ["failed"])[-1]
    full, lean = done.stdout.split()
    return float(full), float(lean)


def _session(node: Node, rollouts: object, seed: int, budget: int) -> tuple[Path, int]:
    """One session of `budget` rollouts (not ending at a hit): its journal and done rollouts."""
    request = {"algo": "archer", "seed": seed, "rollouts": budget, "until_hit": False}
    session = rpc_call(node, node.keys.learner_rpc(), "start", request, timeout=60)["session"]
    final = follow(node, session, rollouts, lambda m: None, poll=0.2)  # type: ignore[arg-type]  # a Subscription
    journal = Path(final["journal"])
    done = sum(isinstance(r, DoneRecord) for r in read_records(journal)[0])
    return journal, done


def _record(endpoint: str, robot: str, path: Path, transforms: bool) -> subprocess.Popen[str]:
    """`archery record` of `ROBOT/**` into `path` (with the 3D records or not), subscribed."""
    flags = () if transforms else ("--no-transforms",)
    net = ("--connect", endpoint, "--robot", robot)
    return spawn("record", "--out", str(path), *flags, *net, ready="archery record: recording")


def _fixed_bytes(tmp: Path) -> int:
    """Bytes of a recording with the 3D records' start (URDF, scene) and no message."""
    from archery.apps.topics.robot_frames import RobotFrames

    path = tmp / "empty.mcap"
    Recorder(path, "bench", ["bench/**"], frames=RobotFrames("bench")).close()
    bare = tmp / "bare.mcap"
    Recorder(bare, "bench", ["bench/**"]).close()
    return path.stat().st_size - bare.stat().st_size


def _sizes(args: argparse.Namespace, tmp: Path) -> tuple[dict[bool, list[float]], Path]:
    """Bytes per rollout of recorded sessions with and without the 3D records, and the last
    session's journal."""
    launcher = mesh_launcher(tmp, "bench", tmp / "model.json")
    launcher.up(180)
    sizes: dict[bool, list[float]] = {True: [], False: []}
    journal = tmp / "none"
    try:
        with Node(None, launcher.net) as node:
            rollouts = node.subscribe(node.keys.learner_rollouts(), Rollout, mode="fifo")
            node.wait_alive(SERVICES, timeout=30)
            _session(node, rollouts, 1000, 2)  # warm-up (calibration): unmeasured
            for i in range(args.repeats):
                order = (True, False) if i % 2 == 0 else (False, True)
                for transforms in order:
                    path = tmp / f"r{i}-{int(transforms)}.mcap"
                    recorder = _record(launcher.endpoint, "bench", path, transforms)
                    try:
                        journal, done = _session(node, rollouts, i, args.rollouts)
                    finally:
                        stop(recorder)
                    sizes[transforms].append(path.stat().st_size / done)
                print(
                    f"repeat {i}: per rollout with {sizes[True][-1] / 1e6:.2f} MB, without "
                    f"{sizes[False][-1] / 1e6:.2f} MB",
                    flush=True,
                )
    finally:
        launcher.stop_all()
    return sizes, journal


def _renders(
    args: argparse.Namespace,
) -> tuple[dict[str, list[tuple[float, float]]], dict[str, str]]:
    """Per backend, (s per full frame, s per lean frame) of each repeat; why a backend failed."""
    cost: dict[str, list[tuple[float, float]]] = {"egl": [], "osmesa": []}
    failed: dict[str, str] = {}
    for i in range(args.repeats):
        for backend in ("egl", "osmesa") if i % 2 == 0 else ("osmesa", "egl"):
            if backend in failed:
                continue
            got = _frame_cost(backend, args.frames)
            if isinstance(got, str):
                failed[backend] = got
            else:
                cost[backend].append(got)
        print(f"render repeat {i} done", flush=True)
    return cost, failed


def _films(args: argparse.Namespace, journal: Path, tmp: Path) -> tuple[list[float], float]:
    """Seconds to film rollout 1 of `journal`, per repeat, and the video's length (s)."""
    films: list[float] = []
    seconds_of_video = 0.0
    for i in range(args.repeats):
        start = time.perf_counter()
        result = film_session(journal, 1, out=tmp / f"film{i}.mp4", quiet=True)
        films.append(time.perf_counter() - start)
        seconds_of_video = result.frames / 30
        print(f"film {i}: {films[-1]:.1f} s", flush=True)
    return films, seconds_of_video


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark; exit status 0."""
    parser = argparse.ArgumentParser(prog="python -m benchmarks.bench_film", description=__doc__)
    parser.add_argument("--repeats", type=int, default=5, help="repeats of each figure (≥ 5)")
    parser.add_argument("--rollouts", type=int, default=6, help="rollouts per recorded session")
    parser.add_argument("--frames", type=int, default=10, help="frames per render probe")
    parser.add_argument(
        "--parts",
        default="size,render,film",
        help="which figures: size, render, film (film alone films the test journal's rollout 1)",
    )
    parser.add_argument(
        "--smoke", action="store_true", help="one repeat of each part at its smallest (seconds)"
    )
    args = parser.parse_args(argv)
    if args.smoke:
        args.repeats, args.rollouts, args.frames = 1, 2, 2
    parts = set(args.parts.split(","))
    tmp = Path(tempfile.mkdtemp(prefix="bench-film-"))
    load = os.getloadavg()[0]
    print(f"machine: {cpu_model()}, {os.cpu_count()} cores; {time.strftime('%Y-%m-%d %H:%M')}")
    journal = Path(__file__).parents[1] / "tests" / "journals" / "old_format.jsonl"
    if "size" in parts:
        sizes, journal = _sizes(args, tmp)
        fixed = _fixed_bytes(tmp)
    if "render" in parts:
        cost, failed = _renders(args)
    if "film" in parts:
        films, seconds_of_video = _films(args, journal, tmp)

    print(f"\n--- bench_film (load average {load:.1f} at the start, {os.getloadavg()[0]:.1f} now)")
    if "film" in parts:
        print(f"time to film one shot (960×540, 30 fps, {seconds_of_video:.1f} s of video):")
        print(
            f"  {median_spread(films, '.1f', ' s')}; per second of video ×"
            f"{median_spread([f / seconds_of_video for f in films], '.1f')}"
        )
    if "render" in parts:
        print(
            "a scene frame with the robot's meshes (960×540) against the lean target frame "
            "(1280×720, no meshes), ms per frame:"
        )
        for backend in ("egl", "osmesa"):
            if backend in failed:
                print(f"  {backend}: not available here ({failed[backend]})")
                continue
            full = [1e3 * f for f, _ in cost[backend]]
            lean = [1e3 * t for _, t in cost[backend]]
            ratio = [f / t for f, t in cost[backend]]
            print(
                f"  {backend}: full {median_spread(full, '.0f')}, lean "
                f"{median_spread(lean, '.0f')}, ratio ×{median_spread(ratio, '.1f')}"
            )
        if cost["egl"] and cost["osmesa"]:
            pairs = zip(cost["osmesa"], cost["egl"], strict=False)
            ratio = [o / e for (o, _), (e, _) in pairs]
            print(f"  osmesa against egl, full frame: ×{median_spread(ratio, '.1f')}")
    if "size" in parts:
        per_with = [(s - fixed / args.rollouts) / 1e6 for s in sizes[True]]
        per_without = [s / 1e6 for s in sizes[False]]
        ratio = [w / o for w, o in zip(per_with, per_without, strict=True)]
        print(f"recording size per rollout ({args.rollouts}-rollout sessions; MB):")
        print(
            f"  with the 3D records {median_spread(per_with, '.3f')} (plus {fixed / 1e6:.1f} MB "
            f"once: URDF and meshes), without {median_spread(per_without, '.3f')}: "
            f"×{median_spread(ratio, '.3f')}"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
