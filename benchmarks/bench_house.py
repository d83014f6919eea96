"""The house rebuilt (issue 23) against the code before it: the runtime's cost, the product's
lines, and (with --suite) the test suite's wall time.

The code before is a `git archive` of --before (default a3f3eb1, the last commit before the
house) run with this interpreter and environment; the code after is this working tree. One
workload, written against both layouts (`protocol.node` before, `mesh.node` after), runs in a
fresh process per tree and repeat, alternating which tree goes first: a router, a server and a
client node in one process over loopback; typed RPC round trips (`Node.call_typed` against a
verb table served by `Node.serve`) and lossless 1280×720 RGB frames from one node to another.
Figures: the RPC median, the frame rate, and their after/before ratios per repeat (goal: the
runtime's split costs nothing, ratio ≤ 1.02× median).

    .venv/bin/python -m benchmarks.bench_house [--repeats 5] [--calls 2000] [--frames 200]
        [--before COMMIT] [--suite] [--smoke]

`--smoke` runs the same path at its smallest budget: one repeat per tree of 50 timed round trips
(after the workload's 200 unmeasured ones) and 10 frames, the code before being `git archive
HEAD` (this tree's last commit, so that the comparison runs without the history of a shallow
clone; the lines are counted in its `PRODUCT_BEFORE` packages); no test suite (`--suite` is
ignored).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchmarks.spread import median_spread
from benchmarks.trees import ROOT, env_for, header, interleaved, tree_at

PRODUCT_BEFORE = ("protocol", "services", "sim")
PRODUCT_AFTER = ("protocol", "mesh", "services", "apps", "sim")

WORKLOAD = r"""
import json, statistics, sys, threading, time
from typing import Annotated
import msgspec, numpy as np
try:
    from archery.mesh.netflags import NetConfig
    from archery.mesh.node import Node
    from archery.mesh.router import free_tcp_endpoint, open_router
except ImportError:  # the layout before the house
    from archery.protocol.netflags import NetConfig
    from archery.protocol.node import Node
    from archery.protocol.router import free_tcp_endpoint, open_router
from archery.protocol.messages import Image
from archery.protocol.verbs import Args, Reply, Verb, VerbTable

calls, frames = int(sys.argv[1]), int(sys.argv[2])


class Aim(Args, frozen=True):
    theta: Annotated[list[float], msgspec.Meta(min_length=3, max_length=3)]


class AimReply(Reply, frozen=True):
    theta: list[float]
    reached: bool


AIM = Verb("aim", Aim, AimReply, "echo θ")
TABLE = VerbTable("bench", ("bench/rpc:i",), (AIM,))
endpoint = free_tcp_endpoint()
out = {}
with open_router(endpoint):
    net = NetConfig(connect=(endpoint,), robot="bench")
    with Node("bench_server", net) as server, Node(None, net) as client:
        by_name = getattr(TABLE, "bind_names", TABLE.bind)  # before the typed binding: bind
        echo = by_name({"aim": lambda a: AimReply(theta=a.theta, reached=True)})
        server.serve("bench/bench/rpc:i", echo)
        args = Aim(theta=[0.17, 0.03, -0.03])
        ready = time.monotonic() + 10  # until the router has the server's queryable
        while True:
            try:
                client.call_typed("bench/bench/rpc:i", AIM, args)
                break
            except Exception:
                if time.monotonic() > ready:
                    raise
        for _ in range(200):
            client.call_typed("bench/bench/rpc:i", AIM, args)
        times = []
        for _ in range(calls):
            t0 = time.perf_counter()
            client.call_typed("bench/bench/rpc:i", AIM, args)
            times.append(time.perf_counter() - t0)
        out["rpc_ms"] = 1e3 * statistics.median(times)
        got = threading.Event()
        count = [0]

        def on_frame(image):
            count[0] += 1
            if count[0] >= frames:
                got.set()

        client.subscribe("bench/cam/target:o", Image, mode="fifo", callback=on_frame)
        pub = server.publisher("bench/cam/target:o", Image, lossless=True)
        pixels = np.zeros((720, 1280, 3), np.uint8)
        pub.wait_matched(10.0)
        t0 = time.perf_counter()
        for _ in range(frames):
            pub.put(Image.from_numpy(pixels, encoding="rgb8"))
        got.wait(60)
        out["fps"] = count[0] / (time.perf_counter() - t0)
print(json.dumps(out))
"""


def _workload(tree: Path, calls: int, frames: int) -> dict[str, float]:
    run = subprocess.run(
        [sys.executable, "-c", WORKLOAD, str(calls), str(frames)],
        cwd=tree,
        env=env_for(tree),
        capture_output=True,
        text=True,
        timeout=600,
    )
    if run.returncode != 0:
        raise RuntimeError(f"the workload failed in {tree}: {run.stderr[-3000:]}")
    return json.loads(run.stdout.strip().splitlines()[-1])


def _lines(tree: Path, packages: tuple[str, ...]) -> dict[str, int]:
    """Non-blank lines of the .py files of each package, and their files."""
    out: dict[str, int] = {}
    files = 0
    for package in packages:
        paths = sorted((tree / package).rglob("*.py"))
        files += len(paths)
        out[package] = sum(1 for p in paths for line in p.read_text().splitlines() if line.strip())
    out["files"] = files
    return out


def _suite(tree: Path) -> float:
    start = time.perf_counter()
    run = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-x", "-p", "no:cacheprovider"],
        cwd=tree,
        env=env_for(tree),
        capture_output=True,
        text=True,
        timeout=1800,
    )
    if run.returncode != 0:
        raise RuntimeError(f"the test suite failed in {tree}: {run.stdout[-3000:]}")
    return time.perf_counter() - start


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="bench_house", description=__doc__)
    parser.add_argument("--repeats", type=int, default=5, help="interleaved repeats (≥ 5)")
    parser.add_argument("--calls", type=int, default=2000, help="RPC round trips per repeat")
    parser.add_argument("--frames", type=int, default=200, help="1280×720 frames per repeat")
    parser.add_argument("--before", default="a3f3eb1", help="the commit before the house")
    parser.add_argument("--suite", action="store_true", help="also time both test suites once")
    parser.add_argument(
        "--smoke",
        action="store_true",
        help="smallest budget: 1 repeat, 50 calls, 10 frames, before = HEAD, no suite (overrides "
        "the flags above)",
    )
    args = parser.parse_args(argv)
    if args.smoke:
        args.repeats, args.calls, args.frames, args.before, args.suite = 1, 50, 10, "HEAD", False
    elif args.repeats < 5:
        parser.error("--repeats must be at least 5")
    header()
    with tempfile.TemporaryDirectory() as tmp:
        before = tree_at(args.before, Path(tmp))
        lines_before = _lines(before, PRODUCT_BEFORE)
        lines_after = _lines(ROOT, PRODUCT_AFTER)
        total_before = sum(lines_before.values()) - lines_before["files"]
        total_after = sum(lines_after.values()) - lines_after["files"]
        print(
            f"- Product lines (non-blank, .py): before {total_before} in {lines_before['files']} "
            f"files ({lines_before}); after {total_after} in {lines_after['files']} files "
            f"({lines_after})"
        )
        rpc: dict[str, list[float]] = {"before": [], "after": []}
        fps: dict[str, list[float]] = {"before": [], "after": []}
        for k, name, tree in interleaved(args.repeats, [("before", before), ("after", ROOT)]):
            got = _workload(tree, args.calls, args.frames)
            rpc[name].append(got["rpc_ms"])
            fps[name].append(got["fps"])
            print(f"  repeat {k + 1} {name}: {got}", file=sys.stderr, flush=True)
        rpc_ratio = [a / b for a, b in zip(rpc["after"], rpc["before"], strict=True)]
        fps_ratio = [b / a for a, b in zip(fps["after"], fps["before"], strict=True)]
        print(
            f"- Typed RPC round trip, median of {args.calls}, {args.repeats} interleaved repeats: "
            f"before {median_spread(rpc['before'], '.3f', ' ms')}, after "
            f"{median_spread(rpc['after'], '.3f', ' ms')}; after/before "
            f"{median_spread(rpc_ratio, '.3f', '×')} (goal ≤ 1.02×)"
        )
        print(
            f"- 1280×720 frames, {args.frames} per repeat: before "
            f"{median_spread(fps['before'], '.0f', ' fps')}, after "
            f"{median_spread(fps['after'], '.0f', ' fps')}; cost after/before "
            f"{median_spread(fps_ratio, '.3f', '×')} (goal ≤ 1.02×)"
        )
        if args.suite:
            suites = {"before": _suite(before), "after": _suite(ROOT)}
            print(
                f"- Test suite, one run each (`pytest`, the default selection): before "
                f"{suites['before']:.0f} s, after {suites['after']:.0f} s"
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
