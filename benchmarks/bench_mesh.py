"""Mesh benchmark: the protocol layer against raw zenoh-python, same router, same run.

Measures 1280×720 RGB frames per second (lossless publisher → subscriber that decodes each
frame) and RPC round trips (median, p99) through a real router on loopback, for raw Zenoh and
for `protocol.Node`, and prints the cost ratio (protocol / raw; the goal is ≤ 1.2).

Run: `python -m benchmarks.bench_mesh [--frames 300] [--calls 3000] [--repeats 3]`
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import threading
import time

import numpy as np
import zenoh
from rich.progress import Progress

from protocol.messages import Image
from protocol.netflags import NetConfig, open_session
from protocol.node import Node
from protocol.router import free_tcp_endpoint, spawn_router

WIDTH, HEIGHT = 1280, 720


def _raw_frames(a: zenoh.Session, b: zenoh.Session, key: str, frames: int) -> float:
    """Frames/s of raw bytes from session a to session b (receiver copies the payload)."""
    payload = np.random.default_rng(0).integers(0, 255, WIDTH * HEIGHT * 3, np.uint8).tobytes()
    done = threading.Event()
    count = [0, 0.0]

    def on_sample(sample: zenoh.Sample) -> None:
        sample.payload.to_bytes()
        count[0] += 1
        if count[0] == frames:
            count[1] = time.perf_counter()
            done.set()

    sub = b.declare_subscriber(key, on_sample)
    pub = a.declare_publisher(
        key,
        congestion_control=zenoh.CongestionControl.BLOCK,
        reliability=zenoh.Reliability.RELIABLE,
    )
    while not pub.matching_status.matching:
        time.sleep(0.01)
    start = time.perf_counter()
    for _ in range(frames):
        pub.put(payload)
    if not done.wait(60):
        raise RuntimeError(f"raw: only {count[0]} of {frames} frames arrived")
    pub.undeclare()
    sub.undeclare()
    return frames / (count[1] - start)


def _node_frames(a: Node, b: Node, key: str, frames: int) -> float:
    """Frames/s of `Image` messages through the protocol layer (encode, decode, validate)."""
    rgb = np.random.default_rng(0).integers(0, 255, (HEIGHT, WIDTH, 3), np.uint8)
    image = Image.from_numpy(rgb)
    done = threading.Event()
    stamps: list[float] = []

    def on_image(message: Image) -> None:
        stamps.append(time.perf_counter())
        if len(stamps) == frames:
            done.set()

    sub = b.subscribe(key, Image, mode="latest", callback=on_image)
    pub = a.publisher(key, Image, lossless=True)
    pub.wait_matched(10)
    start = time.perf_counter()
    for i in range(frames):
        pub.put(Image.from_numpy(rgb, frame=i) if i == 0 else image)
    if not done.wait(60):
        raise RuntimeError(f"protocol: only {len(stamps)} of {frames} frames arrived")
    pub.close()
    sub.close()
    return frames / (stamps[-1] - start)


def _raw_rpc(a: zenoh.Session, b: zenoh.Session, key: str, calls: int) -> list[float]:
    """Round-trip times (ms) of raw queries answered by a raw queryable echoing the payload."""

    def on_query(query: zenoh.Query) -> None:
        query.reply(query.key_expr, query.payload.to_bytes() if query.payload else b"")

    queryable = b.declare_queryable(key, on_query)
    querier = a.declare_querier(key, timeout=5.0)
    payload = b"x" * 64
    while not list(querier.get(payload=payload)):
        time.sleep(0.01)
    times = []
    for _ in range(calls):
        t0 = time.perf_counter()
        replies = list(querier.get(payload=payload))
        times.append((time.perf_counter() - t0) * 1e3)
        assert replies and replies[0].ok is not None
    querier.undeclare()
    queryable.undeclare()
    return times


def _node_rpc(a: Node, b: Node, key: str, calls: int) -> list[float]:
    """Round-trip times (ms) of `Node.call` answered by `Node.serve` (decode, dispatch, encode)."""
    b.serve(key, {"echo": lambda args: args})
    args = {"theta": [0.17, 0.03, -0.03]}
    a.call(key, "echo", args)
    times = []
    for _ in range(calls):
        t0 = time.perf_counter()
        a.call(key, "echo", args)
        times.append((time.perf_counter() - t0) * 1e3)
    return times


def _p99(values: list[float]) -> float:
    return float(np.percentile(values, 99))


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark and print a table with ratios."""
    parser = argparse.ArgumentParser(prog="python -m benchmarks.bench_mesh", description=__doc__)
    parser.add_argument("--frames", type=int, default=300)
    parser.add_argument("--calls", type=int, default=3000)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args(argv)
    endpoint = free_tcp_endpoint()
    router = spawn_router(endpoint)
    net = NetConfig(connect=(endpoint,), robot="bench")
    results: dict[str, list[float]] = {k: [] for k in ("raw_fps", "node_fps")}
    raw_rtt: list[float] = []
    node_rtt: list[float] = []
    try:
        raw_a, raw_b = open_session(net), open_session(net)
        node_a, node_b = Node("bench_a", net), Node("bench_b", net)
        with Progress() as progress:
            task = progress.add_task("mesh benchmark", total=args.repeats * 4)
            for r in range(args.repeats):
                # interleave raw and protocol runs so machine noise hits both alike
                results["raw_fps"].append(_raw_frames(raw_a, raw_b, f"bench/raw/f{r}", args.frames))
                progress.advance(task)
                results["node_fps"].append(
                    _node_frames(node_a, node_b, f"bench/cam{r}/target:o", args.frames)
                )
                progress.advance(task)
                raw_rtt += _raw_rpc(raw_a, raw_b, f"bench/raw/rpc{r}", args.calls)
                progress.advance(task)
                node_rtt += _node_rpc(node_a, node_b, f"bench/rpc{r}/rpc:i", args.calls)
                progress.advance(task)
        node_a.close()
        node_b.close()
        raw_a.close()
        raw_b.close()
    finally:
        router.terminate()
        router.wait()
    raw_fps, node_fps = (
        statistics.median(results["raw_fps"]),
        statistics.median(results["node_fps"]),
    )
    rows = [
        ("1280x720 RGB frames/s", raw_fps, node_fps, raw_fps / node_fps),
        (
            "RPC round trip median (ms)",
            statistics.median(raw_rtt),
            statistics.median(node_rtt),
            statistics.median(node_rtt) / statistics.median(raw_rtt),
        ),
        ("RPC round trip p99 (ms)", _p99(raw_rtt), _p99(node_rtt), _p99(node_rtt) / _p99(raw_rtt)),
    ]
    cpu = platform.processor() or platform.machine()
    print(f"\nmachine: {cpu}, {os.cpu_count()} cores, Python {platform.python_version()}")
    print(f"{args.repeats} repeats × {args.frames} frames, {args.calls} calls, router on loopback")
    print(f"{'figure':<28} {'raw zenoh':>10} {'protocol':>10} {'cost ratio':>11}")
    for name, raw, ours, ratio in rows:
        print(f"{name:<28} {raw:>10.3f} {ours:>10.3f} {ratio:>10.2f}×")
    print("cost ratio = protocol time / raw time (frames: raw fps / protocol fps); goal ≤ 1.2×")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
