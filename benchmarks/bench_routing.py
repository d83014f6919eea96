"""Routing benchmark: what "all traffic meets at the router" costs against direct peer links.

Before, every process was a Zenoh peer that listened on every interface and linked directly to
the other peers it learned of by gossip, so a request went straight from caller to service.
Now every process is a client of the router it is given, and every message crosses the
router: two hops instead of one. This measures both topologies in the same run, through the
protocol layer (`Node.call` answered by `Node.serve`, `Image` frames published and decoded):

* direct: two peers, one listening on a loopback port and the other linked to it (and both to
  the router), as the old default did over the gossiped addresses;
* routed: two clients of the router (the default now).

Interleaved repeats; per repeat the RPC round trip median and p99 (ms) and 1280×720 frames/s;
reported as the median over repeats of routed/direct, with the spread (min–max).

Run: `python -m benchmarks.bench_routing [--calls 2000] [--frames 200] [--repeats 5]`.
`--smoke`: 1 repeat of 5 calls and 2 frames per topology, both topologies on the same router
(seconds; its ratios are noise).
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

from archery.apps.progress import progress_bar
from archery.mesh.netflags import NetConfig
from archery.mesh.node import Node
from archery.mesh.router import free_tcp_endpoint, spawn_router
from archery.protocol.messages import Image
from benchmarks.echo_verbs import ECHO, ECHO_ARGS, echo_verbs
from benchmarks.machine import cpu_model

WIDTH, HEIGHT = 1280, 720


def _rpc_times(a: Node, b: Node, key: str, calls: int) -> list[float]:
    """Round-trip times (ms) of `calls` echo calls from a to a verb served by b."""
    b.serve(key, echo_verbs())
    deadline = time.monotonic() + 10
    while True:  # the queryable must be known at the caller first
        try:
            a.call_typed(key, ECHO, ECHO_ARGS, timeout=1.0)
            break
        except Exception:
            if time.monotonic() > deadline:
                raise
    times = []
    for _ in range(calls):
        t0 = time.perf_counter()
        a.call_typed(key, ECHO, ECHO_ARGS)
        times.append((time.perf_counter() - t0) * 1e3)
    return times


def _frame_rate(a: Node, b: Node, key: str, frames: int) -> float:
    """Frames/s of lossless 1280×720 `Image` messages from a to b, decoded at b."""
    rgb = np.random.default_rng(0).integers(0, 255, (HEIGHT, WIDTH, 3), np.uint8)
    image = Image.from_numpy(rgb)
    stamps: list[float] = []

    def on_image(message: Image) -> None:
        stamps.append(time.perf_counter())

    sub = b.subscribe(key, Image, mode="fifo", callback=on_image)
    pub = a.publisher(key, Image, lossless=True)
    if not pub.wait_matched(10):
        raise RuntimeError(f"no subscriber matched {key}")
    start = time.perf_counter()
    for _ in range(frames):
        pub.put(image)
    deadline = time.monotonic() + 60
    while len(stamps) < frames:
        if time.monotonic() > deadline:
            raise RuntimeError(f"only {len(stamps)} of {frames} frames arrived on {key}")
        time.sleep(0.01)
    pub.close()
    sub.close()
    return frames / (stamps[-1] - start)


def _pairs(router: str) -> dict[str, tuple[Node, Node]]:
    """Caller/service node pairs for each topology."""
    direct_port = free_tcp_endpoint()
    service = Node(None, NetConfig(connect=(router,), listen=(direct_port,), mode="peer"))
    caller = Node(None, NetConfig(connect=(router, direct_port), mode="peer"))
    routed = (Node(None, NetConfig(connect=(router,))), Node(None, NetConfig(connect=(router,))))
    return {"direct": (caller, service), "routed": routed}


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark and print the table of ratios."""
    parser = argparse.ArgumentParser(prog="python -m benchmarks.bench_routing", description=__doc__)
    parser.add_argument("--calls", type=int, default=2000, help="RPC calls per repeat")
    parser.add_argument("--frames", type=int, default=200, help="1280×720 frames per repeat")
    parser.add_argument("--repeats", type=int, default=5, help="interleaved repeats")
    parser.add_argument(
        "--smoke", action="store_true", help="1 repeat of 5 calls and 2 frames: no figures"
    )
    args = parser.parse_args(argv)
    if args.smoke:
        args.calls, args.frames, args.repeats = 5, 2, 1
    router = free_tcp_endpoint()
    proc = spawn_router(router)
    figures: dict[str, dict[str, list[float]]] = {
        t: {"median": [], "p99": [], "fps": []} for t in ("direct", "routed")
    }
    try:
        pairs = _pairs(router)
        with progress_bar() as progress:
            task = progress.add_task("routing benchmark", total=args.repeats * 2)
            for r in range(args.repeats):
                order = ("direct", "routed") if r % 2 == 0 else ("routed", "direct")
                for topology in order:
                    a, b = pairs[topology]
                    times = _rpc_times(a, b, f"bench/{topology}{r}/rpc:i", args.calls)
                    figures[topology]["median"].append(statistics.median(times))
                    figures[topology]["p99"].append(float(np.percentile(times, 99)))
                    fps = _frame_rate(a, b, f"bench/{topology}{r}/target:o", args.frames)
                    figures[topology]["fps"].append(fps)
                    progress.advance(task)
        for a, b in pairs.values():
            a.close()
            b.close()
    finally:
        proc.terminate()
        proc.wait()
    print(f"\nmachine: {cpu_model()}; {args.repeats} interleaved repeats × {args.calls} calls")
    print(f"and {args.frames} frames; router on loopback")
    print(f"{'figure':<26} {'direct':>9} {'routed':>9} {'routed/direct':>14} {'spread':>14}")
    for name, key in (
        ("RPC median (ms)", "median"),
        ("RPC p99 (ms)", "p99"),
        ("1280x720 frames/s", "fps"),
    ):
        direct, routed = figures["direct"][key], figures["routed"][key]
        ratios = [r / d for r, d in zip(routed, direct, strict=True)]
        print(
            f"{name:<26} {statistics.median(direct):>9.3f} {statistics.median(routed):>9.3f} "
            f"{statistics.median(ratios):>13.2f}× {min(ratios):>6.2f}–{max(ratios):.2f}×"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
