"""Typed RPC verbs against plain-data requests: round-trip latency over a real router.

Both paths call the same typed server (a verb table served by `Node.serve`) with the same
request (θ and a timeout) and get the same reply (θ, a time, a flag): the plain-data path sends
the args as a dict and reads the reply as plain data (`tests.rpc.rpc_call`: what a client
without the project's types, e.g. in another language, does); the typed path builds the args
Struct and decodes the reply into its Struct (`Node.call_typed`). Repeats interleave the two
so machine noise hits both alike; the goal is typed ≤ 1.05× plain.

    python -m benchmarks.bench_verbs [--calls 2000] [--repeats 7]

`--smoke`: 1 repeat of 5 calls per path after a warm-up of 5 (seconds; its ratios are noise).
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time
from typing import Annotated

import msgspec
import numpy as np

from archery.mesh.netflags import NetConfig
from archery.mesh.node import Node
from archery.mesh.router import free_tcp_endpoint, spawn_router
from archery.protocol.verbs import Args, Reply, Verb, VerbTable
from tests.rpc import rpc_call

THETA = [0.17, 0.03, -0.03]


class AimArgs(Args, frozen=True):
    theta: Annotated[list[float], msgspec.Meta(min_length=3, max_length=3)]
    timeout: Annotated[float, msgspec.Meta(ge=0.1, le=3600.0)] | None = None


class AimReply(Reply, frozen=True):
    theta: list[float]
    time: float
    reached: bool


AIM = Verb("aim", AimArgs, AimReply, "benchmark verb")
TABLE = VerbTable("bench", ("bench/rpc:i",), (AIM,))


def _plain(a: Node, key: str, calls: int) -> list[float]:
    args = {"theta": THETA, "timeout": 5.0}
    times = []
    for _ in range(calls):
        t0 = time.perf_counter()
        reply = rpc_call(a, key, "aim", args)
        times.append((time.perf_counter() - t0) * 1e3)
    assert reply["reached"]
    return times


def _typed(a: Node, key: str, calls: int) -> list[float]:
    args = AimArgs(theta=THETA, timeout=5.0)
    times = []
    for _ in range(calls):
        t0 = time.perf_counter()
        reply = a.call_typed(key, AIM, args)
        times.append((time.perf_counter() - t0) * 1e3)
    assert reply.reached
    return times


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark and print medians, p99s and typed/plain ratios with their spread."""
    parser = argparse.ArgumentParser(prog="python -m benchmarks.bench_verbs", description=__doc__)
    parser.add_argument("--calls", type=int, default=2000, help="calls per path and repeat")
    parser.add_argument("--repeats", type=int, default=7, help="interleaved repeats (≥ 5)")
    parser.add_argument(
        "--smoke", action="store_true", help="1 repeat of 5 calls per path: no figures"
    )
    args = parser.parse_args(argv)
    if args.smoke:
        args.calls, args.repeats = 5, 1
    elif args.repeats < 5:
        parser.error("--repeats must be at least 5")
    warm_up = 5 if args.smoke else 200
    endpoint = free_tcp_endpoint()
    router = spawn_router(endpoint)
    net = NetConfig(connect=(endpoint,), robot="bench")
    typed_key, plain_key = "bench/typed/rpc:i", "bench/plain/rpc:i"
    per_repeat: list[tuple[list[float], list[float]]] = []
    try:
        with Node("bench_server", net) as server, Node(None, net) as client:
            served = TABLE.bind_names(
                {"aim": lambda a: AimReply(theta=a.theta, time=1.0, reached=True)}
            )
            server.serve(plain_key, served)
            server.serve(
                typed_key,
                TABLE.bind_names(
                    {"aim": lambda a: AimReply(theta=a.theta, time=1.0, reached=True)}
                ),
            )
            _plain(client, plain_key, warm_up)  # warm up both paths
            _typed(client, typed_key, warm_up)
            for r in range(args.repeats):
                if r % 2:  # alternate which path goes first
                    typed = _typed(client, typed_key, args.calls)
                    plain = _plain(client, plain_key, args.calls)
                else:
                    plain = _plain(client, plain_key, args.calls)
                    typed = _typed(client, typed_key, args.calls)
                per_repeat.append((plain, typed))
    finally:
        router.terminate()
        router.wait()

    def p99(values: list[float]) -> float:
        return float(np.percentile(values, 99))

    all_u = [t for u, _ in per_repeat for t in u]
    all_t = [t for _, ty in per_repeat for t in ty]
    med_ratios = [statistics.median(ty) / statistics.median(u) for u, ty in per_repeat]
    p99_ratios = [p99(ty) / p99(u) for u, ty in per_repeat]
    cpu = platform.processor() or platform.machine()
    print(f"machine: {cpu}, {os.cpu_count()} cores, Python {platform.python_version()}")
    print(f"{args.repeats} interleaved repeats × {args.calls} calls per path, router on loopback")
    print(f"{'figure':<22} {'plain':>9} {'typed':>9} {'ratio':>7}  {'spread (min–max)':>18}")
    for name, u, ty, ratios in (
        ("RPC median (ms)", statistics.median(all_u), statistics.median(all_t), med_ratios),
        ("RPC p99 (ms)", p99(all_u), p99(all_t), p99_ratios),
    ):
        spread = f"{min(ratios):.3f}–{max(ratios):.3f}"
        print(f"{name:<22} {u:>9.3f} {ty:>9.3f} {ty / u:>6.3f}×  {spread:>18}")
    print("ratio = typed / plain (per-repeat ratios give the spread); goal ≤ 1.05×")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
