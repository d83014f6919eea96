"""Secure-mode benchmark: what mutual TLS and the router's access control cost against plain TCP.

Two routers run on loopback in the same run: a plain one (`tcp/`) and a secure one (`tls/`,
mutual TLS with a fresh deployment of `archery keys init`, access control of its
`acl.json5`). Through each, with the deployment's identities in secure mode, over the
protocol layer: the learner calls `ROBOT/detector/rpc:i` served by the detector (`Node.call`
answered by `Node.serve`), and the camera streams lossless 1280×720 `Image` frames on
`ROBOT/cam/target:o` to the detector, which decodes them.

Interleaved repeats; per repeat the RPC round-trip median and p99 (ms) and frames/s; reported as
the median over repeats of secure/plain, with the spread (min–max). Goals: ≤1.3× latency,
≥0.8× throughput.

Run: `python -m benchmarks.bench_secure [--calls 2000] [--frames 200] [--repeats 5]`
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
from rich.progress import Progress

from benchmarks.machine import cpu_model
from protocol.credentials import init_deployment
from protocol.messages import Image
from protocol.netflags import NetConfig
from protocol.node import Node, Publisher
from protocol.router import free_tcp_endpoint, spawn_router

ROBOT = "bench"
WIDTH, HEIGHT = 1280, 720
ARGS = {"theta": [0.17, 0.03, -0.03]}


class Mesh:
    """Learner, detector and camera nodes on one router, the verb served and the stream open."""

    def __init__(self, endpoint: str, secure: str | None) -> None:
        def node(identity: str) -> Node:
            net = NetConfig(connect=(endpoint,), robot=ROBOT, secure=secure, identity=identity)
            return Node(None, net)

        self.learner, self.detector, self.camera = map(node, ("learner", "detector", "camera"))
        self.key = self.detector.keys.detector_rpc()
        self.detector.serve(self.key, {"measure": lambda args: args})
        self.frames = 0
        self._cond = threading.Condition()
        self.detector.subscribe(
            self.detector.keys.cam_frames(), Image, mode="fifo", callback=self._on_image
        )
        self.pub: Publisher[Image] = self.camera.publisher(
            self.camera.keys.cam_frames(), Image, lossless=True
        )
        if not self.pub.wait_matched(10):
            raise RuntimeError(f"no subscriber matched the frames through {endpoint}")
        deadline = time.monotonic() + 10
        while True:  # the queryable must be known at the router first
            try:
                self.learner.call(self.key, "measure", ARGS, timeout=1.0)
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
            self.learner.call(self.key, "measure", ARGS)
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
        for node in (self.learner, self.detector, self.camera):
            node.close()


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark and print the table of ratios."""
    parser = argparse.ArgumentParser(prog="python -m benchmarks.bench_secure", description=__doc__)
    parser.add_argument("--calls", type=int, default=2000)
    parser.add_argument("--frames", type=int, default=200)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args(argv)
    rgb = np.random.default_rng(0).integers(0, 255, (HEIGHT, WIDTH, 3), np.uint8)
    image = Image.from_numpy(rgb)
    figures: dict[str, dict[str, list[float]]] = {
        t: {"median": [], "p99": [], "fps": []} for t in ("plain", "secure")
    }
    with tempfile.TemporaryDirectory() as tmp:
        deployment = str(init_deployment(Path(tmp) / "deploy", robot=ROBOT))
        plain_ep = free_tcp_endpoint()
        secure_ep = free_tcp_endpoint().replace("tcp/", "tls/")
        routers = [spawn_router(plain_ep), spawn_router(secure_ep, secure=deployment)]
        try:
            meshes = {"plain": Mesh(plain_ep, None), "secure": Mesh(secure_ep, deployment)}
            with Progress() as progress:
                task = progress.add_task("secure benchmark", total=args.repeats * 2)
                for r in range(args.repeats):
                    order = ("plain", "secure") if r % 2 == 0 else ("secure", "plain")
                    for mode in order:
                        times = meshes[mode].rpc_times(args.calls)
                        figures[mode]["median"].append(statistics.median(times))
                        figures[mode]["p99"].append(float(np.percentile(times, 99)))
                        figures[mode]["fps"].append(meshes[mode].frame_rate(image, args.frames))
                        progress.advance(task)
            for mesh in meshes.values():
                mesh.close()
        finally:
            for proc in routers:
                proc.terminate()
                proc.wait()
    print(f"\nmachine: {cpu_model()}; {args.repeats} interleaved repeats × {args.calls} calls")
    print(f"and {args.frames} frames; routers on loopback (plain tcp/, secure tls/ + ACL)")
    print(f"{'figure':<22} {'plain':>9} {'secure':>9} {'secure/plain':>13} {'spread':>14}")
    for name, key in (
        ("RPC median (ms)", "median"),
        ("RPC p99 (ms)", "p99"),
        ("1280x720 frames/s", "fps"),
    ):
        plain, secure = figures["plain"][key], figures["secure"][key]
        ratios = [s / p for s, p in zip(secure, plain, strict=True)]
        print(
            f"{name:<22} {statistics.median(plain):>9.3f} {statistics.median(secure):>9.3f} "
            f"{statistics.median(ratios):>12.2f}× {min(ratios):>6.2f}–{max(ratios):.2f}×"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
