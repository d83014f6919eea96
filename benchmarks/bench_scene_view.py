"""Benchmark of the dashboard's scene view: what watching the whole robot costs the learning loop.

Run `MUJOCO_GL=egl python -m benchmarks.bench_scene_view [--repeats 5] [--rollouts 8]
[--rtf 1]`. It starts a whole mesh (`archery up`'s Launcher, the robot at `--rtf`, default 1:
the wall-clock pace of a watched session) and one `archery dashboard`, then runs learning
sessions (ARCHER) under two conditions, interleaved in a rotating order `--repeats` times:

* closed: a client polls the dashboard as its page does with the scene panel closed
  (`/api/state` every 0.5 s, `/api/frame.png` whenever the frame's version changes);
* open: the same with the scene panel open (`/api/state?scene=1`, and `/api/scene.jpg`
  whenever the scene view's version changes): the camera renders the whole robot with its
  meshes about once a second. The session starts once the page has its first scene view (the
  camera builds the view on the first request, and keeps it while asked for within 30 s): the
  time to that first view is reported apart.

Per condition: the median over each session's rollouts of the wall time per rollout (between
consecutive done records, the first left out); the figure is the median over repeats of the
open session's time against the same repeat's closed one, with its spread (min, max). Also
each session's CPU time per rollout of the camera, and the scene views the client received.

`--smoke`: 1 repeat (each condition once) of 2-rollout sessions with the robot at rtf 0, on the
same mesh and dashboard (tens of seconds; its figures are noise), in a temporary directory,
removed after.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from datetime import UTC, datetime
from pathlib import Path

from archery.apps.dashboard.watch import SCENE_INTEREST
from archery.apps.up.launch_config import SERVICES
from archery.mesh.node import Node
from archery.mesh.router import free_tcp_endpoint
from archery.protocol.messages import Rollout
from archery.services.camera.scene_view import PERIOD
from benchmarks.bench_record import _per_rollout, mesh_launcher
from benchmarks.machine import cpu_model
from benchmarks.observers import PageClient, cpu_seconds, stop
from benchmarks.spread import median_spread
from tests.spawn import spawn

__all__ = ["main"]

CONDITIONS = ("closed", "open")


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark; exit status 0."""
    os.environ.setdefault("MUJOCO_GL", "egl")
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.bench_scene_view", description=__doc__
    )
    parser.add_argument("--repeats", type=int, default=5, help="pairs of sessions (≥ 5)")
    parser.add_argument("--rollouts", type=int, default=8, help="rollouts per session")
    parser.add_argument("--rtf", type=float, default=1.0, help="the robot's real-time factor")
    parser.add_argument(
        "--smoke",
        action="store_true",
        help="1 repeat of 2-rollout sessions at rtf 0, in a temporary directory: no figures",
    )
    args = parser.parse_args(argv)
    if args.smoke:
        args.repeats, args.rollouts, args.rtf = 1, 2, 0.0
        with tempfile.TemporaryDirectory(prefix="bench-scene-view-") as tmp:
            return _run(args, Path(tmp))
    return _run(args, Path(tempfile.mkdtemp(prefix="bench-scene-view-")))


def _run(args: argparse.Namespace, tmp: Path) -> int:
    """The benchmark at the budgets of `args`, the mesh's files under `tmp`; the report printed."""
    started = datetime.now(UTC)
    launcher = mesh_launcher(tmp, "bench", tmp / "model.json", args.rtf)
    launcher.up(180)
    endpoint = launcher.endpoint
    camera = {"camera": launcher.children["camera"].proc.pid}  # type: ignore[union-attr]
    times: dict[str, list[float]] = {name: [] for name in CONDITIONS}
    cpu: dict[str, list[float]] = {name: [] for name in CONDITIONS}
    first_view: list[float] = []  # s until the page had a scene view, per open session
    port = free_tcp_endpoint().rsplit(":", 1)[1]
    flags = ["--connect", endpoint, "--robot", "bench"]
    dashboard = spawn("dashboard", "--port", port, *flags, ready="archery dashboard: serving")
    url = f"http://127.0.0.1:{port}/"
    try:
        with Node(None, launcher.net) as node:
            rollouts = node.subscribe(node.keys.learner_rollouts(), Rollout, mode="fifo")
            node.wait_alive(SERVICES, timeout=30)
            _per_rollout(node, rollouts, 1000, args.rollouts)  # warm-up (calibration): untimed
            for i in range(args.repeats):
                order = CONDITIONS if i % 2 == 0 else CONDITIONS[::-1]
                for name in order:
                    page = PageClient(url, scene=name == "open")
                    if name == "open":  # the view built (once, or after 30 s unasked): untimed
                        waited = time.monotonic()
                        while page.scenes == 0:
                            if time.monotonic() - waited > 300:
                                raise RuntimeError("no scene view within 300 s")
                            time.sleep(0.1)
                        first_view.append(time.monotonic() - waited)
                    try:
                        before = cpu_seconds(camera)["camera"]
                        per_rollout, _ = _per_rollout(node, rollouts, i, args.rollouts)
                        used = cpu_seconds(camera)["camera"] - before
                    finally:
                        page.close()
                    if name == "open":  # the dashboard stops asking, the camera's last render
                        time.sleep(SCENE_INTEREST + 2 * PERIOD)  # ends: a closed start (untimed)
                    times[name].append(per_rollout)
                    cpu[name].append(used / args.rollouts)
                    print(
                        f"  repeat {i} {name}: {per_rollout * 1e3:.0f} ms/rollout, camera CPU "
                        f"{used / args.rollouts * 1e3:.0f} ms/rollout; page: {page.states} "
                        f"states, {page.frames} frames, {page.scenes} scene views, "
                        f"{page.errors} errors",
                        flush=True,
                    )
                print(f"repeat {i}: open ×{times['open'][-1] / times['closed'][-1]:.3f}")
    finally:
        stop(dashboard)
        launcher.stop_all()
    ratios = [a / b for a, b in zip(times["open"], times["closed"], strict=True)]
    print("\n--- bench_scene_view")
    print(
        f"{started:%Y-%m-%d %H:%M} UTC, {os.cpu_count()} cores ({cpu_model()}); robot at rtf "
        f"{args.rtf:g}; {args.repeats} interleaved repeats of {args.rollouts}-rollout sessions"
    )
    for name in CONDITIONS:
        print(
            f"  {name}: {median_spread([t * 1e3 for t in times[name]], '.0f', ' ms')} per "
            f"rollout; camera CPU {median_spread([c * 1e3 for c in cpu[name]], '.0f', ' ms')} "
            f"per rollout"
        )
    print(f"  open / closed: ×{median_spread(ratios, '.3f')} (goal ≤ ×1.05)")
    print(
        f"  the page's first scene view after opening the panel: "
        f"{median_spread(first_view, '.1f', ' s')} (the first includes building the view)"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
