"""Benchmark of `archery foxglove`'s memory beside clients that never read.

Run `python -m benchmarks.bench_foxglove_clients [--repeats 5] [--clients 20] [--frames 100]`.
A mesh (`archery up` on a free loopback port) runs throughout. Each repeat starts a fresh
bridge for each of two conditions, interleaved (the order alternating): one client, and
`--clients` clients (Foxglove's own client, tests/foxglove_client `--stall`), each subscribing
to the camera's raw frames (2.8 MB each) and then never reading again. Once all have
subscribed, the bridge runs while the camera publishes `--frames` more frames; then its peak
RSS (`VmHWM`: the process's own high-water mark since it started) is read and it is stopped
with SIGTERM (the seconds it takes to exit and its exit status are printed too). It prints the
peak RSS of each condition and their ratio per repeat, median [min, max] (goal ≤ 1.5×).

`--smoke`: 1 repeat, 3 clients, 10 frames.
"""

from __future__ import annotations

import argparse
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from archery.mesh.netflags import NetConfig
from archery.mesh.node import Node, open_node
from archery.mesh.router import free_tcp_endpoint
from archery.protocol.messages import Image
from archery.protocol.robotspec import SERVICES
from benchmarks.machine import cpu_model
from benchmarks.spread import median_spread

__all__ = ["main"]

CLIENT = Path(__file__).resolve().parent.parent / "tests" / "foxglove_client"
ROBOT = "benchfoxc"


def _peak_rss(pid: int) -> int:
    """A process's peak resident memory since it started (bytes, `VmHWM`)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) * 1024
    raise RuntimeError("no VmHWM in /proc")


def _one(endpoint: str, node: Node, frames: list[float], clients: int, more: int) -> dict[str, Any]:
    """One bridge with `clients` stalled camera clients while `more` frames are published."""
    bridge = subprocess.Popen(
        [sys.executable, "-m", "archery.apps.cli", "foxglove", "--connect", endpoint,
         "--robot", ROBOT, "--port", "0", "--max-clients", str(max(16, clients + 4))],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )  # fmt: skip
    assert bridge.stdout is not None
    line = bridge.stdout.readline()
    if not line.startswith("archery foxglove: serving"):
        bridge.kill()
        raise RuntimeError(f"the bridge did not start: {line!r}")
    url = line.split(" on ", 1)[1].split()[0]
    stalled = subprocess.Popen(
        ["node", str(CLIENT / "client.mjs"), url, "--stall", str(clients), "--want",
         "/camera/image"],
        stdout=subprocess.PIPE,
        text=True,
    )  # fmt: skip
    try:
        assert stalled.stdout is not None
        if '"stalled"' not in stalled.stdout.readline():
            raise RuntimeError("the clients did not subscribe")
        seen = len(frames)
        deadline = time.monotonic() + 120
        while len(frames) < seen + more and time.monotonic() < deadline:
            time.sleep(0.05)
        peak = _peak_rss(bridge.pid)
        started = time.monotonic()
        bridge.send_signal(signal.SIGTERM)
        _, err = bridge.communicate(timeout=60)
        stop = time.monotonic() - started
    finally:
        stalled.send_signal(signal.SIGTERM)
        stalled.communicate(timeout=30)
        if bridge.poll() is None:
            bridge.kill()
            bridge.wait()
    return {
        "peak": peak,
        "stop": stop,
        "status": bridge.returncode,
        "traceback": "Traceback" in err,
        "frames": len(frames) - seen,
    }


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark; exit status 0 (1 when Node is missing)."""
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.bench_foxglove_clients", description=__doc__
    )
    parser.add_argument("--repeats", type=int, default=5, help="interleaved pairs (≥ 5)")
    parser.add_argument("--clients", type=int, default=20, help="stalled clients against one")
    parser.add_argument("--frames", type=int, default=100, help="camera frames while they stall")
    parser.add_argument("--smoke", action="store_true", help="1 repeat, 3 clients, 10 frames")
    args = parser.parse_args(argv)
    if args.smoke:
        args.repeats, args.clients, args.frames = 1, 3, 10
    if shutil.which("node") is None:
        print("bench_foxglove_clients: Node is not installed", file=sys.stderr)
        return 1
    if not (CLIENT / "node_modules" / "@foxglove" / "ws-protocol").is_dir():
        subprocess.run(["npm", "ci", "--no-audit", "--no-fund"], cwd=CLIENT, check=True)
    print(f"machine: {cpu_model()}", flush=True)
    endpoint = free_tcp_endpoint()
    with tempfile.TemporaryDirectory() as tmp:
        up = subprocess.Popen(
            [sys.executable, "-m", "archery.apps.cli", "up", "--listen", endpoint, "--robot", ROBOT,
             "--logs", f"{tmp}/logs", "--runs", f"{tmp}/runs"],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )  # fmt: skip
        try:
            with open_node(NetConfig(connect=(endpoint,), robot=ROBOT), 60) as node:
                node.wait_alive(SERVICES, timeout=120)
                frames: list[float] = []
                sub = node.subscribe(
                    node.keys.cam_frames(), Image, callback=lambda m: frames.append(m.stamp)
                )
                rows = []
                for i in range(args.repeats):
                    order = (1, args.clients) if i % 2 == 0 else (args.clients, 1)
                    row = {n: _one(endpoint, node, frames, n, args.frames) for n in order}
                    one, many = row[1], row[args.clients]
                    print(
                        f"  repeat {i}: peak RSS 1 client {one['peak'] / 2**20:.0f} MiB, "
                        f"{args.clients} clients {many['peak'] / 2**20:.0f} MiB "
                        f"(×{many['peak'] / one['peak']:.3f}); stop {one['stop']:.2f} s / "
                        f"{many['stop']:.2f} s, exit {one['status']} / {many['status']}"
                        f"{', TRACEBACK' if one['traceback'] or many['traceback'] else ''}",
                        flush=True,
                    )
                    rows.append(row)
                sub.close()
        finally:
            up.terminate()
            up.wait(60)
    n = args.clients
    one_mib = [r[1]["peak"] / 2**20 for r in rows]
    many_mib = [r[n]["peak"] / 2**20 for r in rows]
    ratios = [r[n]["peak"] / r[1]["peak"] for r in rows]
    stops = [r[c]["stop"] for r in rows for c in (1, n)]
    print(f"{len(rows)} interleaved repeats, {args.frames} camera frames while the clients stall:")
    print(
        f"  peak RSS: 1 client {median_spread(one_mib, '.0f', ' MiB')}, {n} clients "
        f"{median_spread(many_mib, '.0f', ' MiB')}; ratio ×{median_spread(ratios, '.3f')} "
        "(goal ≤ 1.5×)"
    )
    exits = sorted({r[c]["status"] for r in rows for c in (1, n)})
    print(f"  stop on SIGTERM: {median_spread(stops, '.2f', ' s')}, exit statuses {exits}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
