"""Secure-mode benchmark: what mutual TLS and the router's access control cost against plain TCP.

Everything runs on loopback in the same run, plain (`tcp/`) against secure (`tls/`: mutual TLS
with a fresh deployment of `archery keys init`, the router enforcing its `acl.json5`), each
figure measured in interleaved repeats (plain first on even repeats, secure first on odd ones)
and reported as the median over repeats of secure/plain, with the spread (min–max):

1. Through two routers (`archery router`), with the deployment's identities in secure mode,
   over the protocol layer: the learner calls `ROBOT/detector/rpc:i` served by the detector
   (`Node.call` answered by `Node.serve`; RPC round-trip median and p99, ms; an echo of θ
   under the first verb the ACL grants the learner there, `echo_verbs.granted_verbs`, so the
   call passes the per-verb rules on its `PORT/VERB` key, plain and secure alike), and the
   camera streams lossless 1280×720 `Image` frames on `ROBOT/cam/target:o` to the operator
   (what `archery view` reads), which decodes them (frames/s). Goals: ≤1.3× latency, ≥0.8×
   throughput.
2. Two whole meshes (`apps.up.launcher.Launcher`: a router and the five services as child
   processes, each service with its own identity in secure mode), one plain and one secure,
   both up at once on different loopback ports: a learning session of `--rollouts` rollouts
   (archer, `until_hit` off, the same seed on both, after one warm-up session each) is run
   alternately on each, started and followed as `archery learn` does (the `operator`
   identity). Per-rollout wall time = (arrival of the last done rollout − the start request)
   / rollouts. Goal: ≤1.1×.

Run: `python -m benchmarks.bench_secure [--calls 2000] [--frames 200] [--repeats 5]
[--sessions 7] [--rollouts 5]`. `--smoke`: both parts at their smallest budget, 1 repeat of 5
calls and 2 frames, and 1 session of 1 rollout per mesh after the warm-up ones (tens of
seconds, most of it the two meshes' start-up; its ratios are noise).
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from archery.apps.learn.follow import follow
from archery.apps.progress import progress_bar
from archery.apps.up.launch_config import SERVICES
from archery.apps.up.launcher import Launcher
from archery.mesh.credentials import init_deployment
from archery.mesh.netflags import NetConfig
from archery.mesh.node import Node
from archery.mesh.publisher import Publisher
from archery.mesh.router import free_tcp_endpoint, spawn_router
from archery.mesh.subscription import Subscription
from archery.protocol.journal_records import DoneRecord
from archery.protocol.messages import Image, Rollout
from benchmarks.echo_verbs import ECHO_ARGS, granted_verbs, named_echo
from benchmarks.machine import cpu_model
from tests.rpc import rpc_call

ROBOT = "bench"
WIDTH, HEIGHT = 1280, 720


class Mesh:
    """Learner, detector, camera and operator nodes on one router, the verb served and the
    frame stream open."""

    def __init__(self, endpoint: str, secure: str | None) -> None:
        def node(identity: str) -> Node:
            net = NetConfig(connect=(endpoint,), robot=ROBOT, secure=secure, identity=identity)
            return Node(None, net)

        self.nodes = [node(n) for n in ("learner", "detector", "camera", "operator")]
        self.learner, self.detector, self.camera, self.operator = self.nodes
        self.key = self.detector.keys.detector_rpc()
        self.verb, served = named_echo(granted_verbs(ROBOT, "learner", self.key)[0])
        self.detector.serve(self.key, served)
        self.frames = 0
        self._cond = threading.Condition()
        self.operator.subscribe(
            self.operator.keys.cam_frames(), Image, mode="fifo", callback=self._on_image
        )
        self.pub: Publisher[Image] = self.camera.publisher(
            self.camera.keys.cam_frames(), Image, lossless=True
        )
        if not self.pub.wait_matched(10):
            raise RuntimeError(f"no subscriber matched the frames through {endpoint}")
        deadline = time.monotonic() + 10
        while True:  # the queryable must be known at the router first
            try:
                self.learner.call_typed(self.key, self.verb, ECHO_ARGS, timeout=1.0)
                break
            except Exception:
                if time.monotonic() > deadline:
                    raise

    def _on_image(self, message: Image) -> None:
        with self._cond:
            self.frames += 1
            self.last = time.perf_counter()
            self._cond.notify_all()

    def rpc_times(self, calls: int) -> list[float]:
        times = []
        for _ in range(calls):
            t0 = time.perf_counter()
            self.learner.call_typed(self.key, self.verb, ECHO_ARGS)
            times.append((time.perf_counter() - t0) * 1e3)
        return times

    def frame_rate(self, image: Image, frames: int) -> float:
        with self._cond:
            self.frames = 0
        start = time.perf_counter()
        for _ in range(frames):
            self.pub.put(image)
        with self._cond:
            if not self._cond.wait_for(lambda: self.frames >= frames, timeout=60):
                raise RuntimeError(f"only {self.frames} of {frames} frames arrived")
            return frames / (self.last - start)

    def close(self) -> None:
        for node in self.nodes:
            node.close()


class Session:
    """`archery learn` against one running mesh: start a session, follow it to its end."""

    def __init__(self, launcher: Launcher, rollouts: int) -> None:
        self.node = Node(None, launcher.net)  # the operator identity in secure mode
        self.rollouts: Subscription[Rollout] = self.node.subscribe(
            self.node.keys.learner_rollouts(), Rollout, mode="fifo"
        )
        self.node.wait_alive(SERVICES, timeout=60)
        self.request = {
            "algo": "archer",
            "rollouts": rollouts,
            "seed": 0,
            "until_hit": False,
            "options": {},
        }

    def per_rollout(self) -> float:
        """Run one session; seconds from the start request to the last done rollout, per
        rollout."""
        done: list[float] = []

        def on_rollout(message: Rollout) -> None:
            if isinstance(message.record, DoneRecord):
                done.append(time.perf_counter())

        start = time.perf_counter()
        status = rpc_call(
            self.node, self.node.keys.learner_rpc(), "start", self.request, timeout=120
        )
        final = follow(self.node, status["session"], self.rollouts, on_rollout, poll=0.05)
        n = self.request["rollouts"]
        if final.get("state") != "finished" or len(done) != n:
            raise RuntimeError(f"session {final.get('state')} with {len(done)} of {n} rollouts")
        return (done[-1] - start) / n

    def close(self) -> None:
        self.node.close()


def interleaved(repeats: int, run: Callable[[str], None]) -> None:
    """`run(mode)` for both modes `repeats` times, alternating which goes first."""
    for r in range(repeats):
        for mode in ("plain", "secure") if r % 2 == 0 else ("secure", "plain"):
            run(mode)


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark and print the table of ratios."""
    parser = argparse.ArgumentParser(prog="python -m benchmarks.bench_secure", description=__doc__)
    parser.add_argument("--calls", type=int, default=2000, help="RPC calls per repeat")
    parser.add_argument("--frames", type=int, default=200, help="frames per repeat")
    parser.add_argument("--repeats", type=int, default=5, help="repeats of the RPC and frames")
    parser.add_argument("--sessions", type=int, default=7, help="sessions per mesh (≥5)")
    parser.add_argument("--rollouts", type=int, default=5, help="rollouts per session")
    parser.add_argument(
        "--smoke",
        action="store_true",
        help="1 repeat of 5 calls and 2 frames, 1 session of 1 rollout per mesh: no figures",
    )
    args = parser.parse_args(argv)
    if args.smoke:
        args.calls, args.frames, args.repeats, args.sessions, args.rollouts = 5, 2, 1, 1, 1
    if args.sessions < 1 or args.repeats < 1 or args.rollouts < 1:
        parser.error("--repeats, --sessions and --rollouts must be at least 1")
    rgb = np.random.default_rng(0).integers(0, 255, (HEIGHT, WIDTH, 3), np.uint8)
    image = Image.from_numpy(rgb)
    figures: dict[str, dict[str, list[float]]] = {
        t: {"median": [], "p99": [], "fps": [], "rollout": []} for t in ("plain", "secure")
    }
    with tempfile.TemporaryDirectory() as tmp, progress_bar() as progress:
        deployment = str(init_deployment(Path(tmp) / "deploy", robot=ROBOT))
        task = progress.add_task(
            "RPC and frames", total=2 * args.repeats + 2 + 2 * (args.sessions + 1)
        )

        def endpoints() -> dict[str, str]:
            return {
                "plain": free_tcp_endpoint(),
                "secure": free_tcp_endpoint().replace("tcp/", "tls/"),
            }

        # 1. RPC round trips and frames through two routers, nothing else running.
        ep = endpoints()
        routers = [spawn_router(ep["plain"]), spawn_router(ep["secure"], secure=deployment)]
        try:
            meshes = {"plain": Mesh(ep["plain"], None), "secure": Mesh(ep["secure"], deployment)}

            def rpc_and_frames(mode: str) -> None:
                times = meshes[mode].rpc_times(args.calls)
                figures[mode]["median"].append(statistics.median(times))
                figures[mode]["p99"].append(float(np.percentile(times, 99)))
                figures[mode]["fps"].append(meshes[mode].frame_rate(image, args.frames))
                progress.advance(task)

            interleaved(args.repeats, rpc_and_frames)
            for mesh in meshes.values():
                mesh.close()
        finally:
            for proc in routers:
                proc.terminate()
                proc.wait()

        # 2. Learning sessions on two whole meshes, plain and secure, both up.
        ep = endpoints()
        launchers: dict[str, Launcher] = {}
        sessions: dict[str, Session] = {}
        try:
            for mode in ("plain", "secure"):
                progress.update(task, description=f"starting the {mode} mesh")
                launchers[mode] = Launcher(
                    ep[mode],
                    ROBOT,
                    Path(tmp) / f"logs-{mode}",
                    {"learner": ["--runs", str(Path(tmp) / f"runs-{mode}")]},
                    secure=deployment if mode == "secure" else None,
                )
                launchers[mode].up(120)
                sessions[mode] = Session(launchers[mode], args.rollouts)
                progress.advance(task)
            progress.update(task, description="learning sessions")
            for mode in ("plain", "secure"):  # warm-up: calibration, first renders, caches
                sessions[mode].per_rollout()
                progress.advance(task)

            def session(mode: str) -> None:
                figures[mode]["rollout"].append(1e3 * sessions[mode].per_rollout())
                progress.advance(task)

            interleaved(args.sessions, session)
        finally:
            for client in sessions.values():
                client.close()
            for launcher in launchers.values():
                launcher.stop_all()

    print(f"\nmachine: {cpu_model()}; on loopback, plain tcp/ against secure tls/ + ACL")
    print(f"{args.repeats} interleaved repeats × {args.calls} calls and {args.frames} frames;")
    print(
        f"{args.sessions} interleaved sessions × {args.rollouts} rollouts on two whole meshes "
        f"(router + 5 services each)"
    )
    print(
        f"{'figure':<24} {'plain':>9} {'secure':>9} {'secure/plain':>13} {'spread':>14} {'goal':>7}"
    )
    for name, key, goal in (
        ("RPC median (ms)", "median", "≤1.3×"),
        ("RPC p99 (ms)", "p99", "≤1.3×"),
        ("1280x720 frames/s", "fps", "≥0.8×"),
        ("session ms/rollout", "rollout", "≤1.1×"),
    ):
        plain, secure = figures["plain"][key], figures["secure"][key]
        ratios = [s / p for s, p in zip(secure, plain, strict=True)]
        print(
            f"{name:<24} {statistics.median(plain):>9.3f} {statistics.median(secure):>9.3f} "
            f"{statistics.median(ratios):>12.2f}× {min(ratios):>6.2f}–{max(ratios):.2f}× "
            f"{goal:>7}"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
