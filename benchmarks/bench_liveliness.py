"""How often a liveliness query misses a token the router holds, by what else the querying
session has declared: the figures behind `mesh.instances.InstanceWatch` waiting for a
replier's token by event rather than trusting a query.

A router process, one service holding its instance token, and one client session that asks
`ROBOT/alive/NAME/*` over and over, in three arrangements interleaved over the repeats:

- `alone`: no liveliness subscriber in the client (the baseline);
- `fresh subscriber`: a liveliness subscriber (with history) on the same key declared right
  before each query, and undeclared after it;
- `kept subscriber`: one such subscriber declared before the first query and kept.

Reported per arrangement: the queries that came back without the token (summed over repeats,
and per repeat as median [min, max]), and the wall time of those empty answers (ms).

Run: `.venv/bin/python -m benchmarks.bench_liveliness [--queries N] [--repeats R]`.
`--smoke`: 1 repeat of 5 queries per arrangement (seconds; the counts are noise), on the same
router, service and client sessions.
"""

from __future__ import annotations

import argparse
import importlib.metadata
import os
import platform
import statistics
import time
from collections.abc import Callable
from datetime import UTC, datetime

import zenoh

from archery.apps.progress import progress_bar
from archery.mesh.instances import live_instances, zid_of
from archery.mesh.netflags import NetConfig
from archery.mesh.node import Node
from archery.mesh.router import free_tcp_endpoint, spawn_router
from benchmarks.machine import cpu_model
from benchmarks.spread import median_spread

NAME = "robot"
ARRANGEMENTS = ("alone", "fresh subscriber", "kept subscriber")


def _ask(client: Node, zid: str, queries: int, arrangement: str) -> list[float]:
    """Wall times (ms) of the queries of one repeat that came back without `zid`."""
    key = client.keys.alive_instances(NAME)
    liveliness = client.session.liveliness()

    def subscribe() -> zenoh.Subscriber:
        return liveliness.declare_subscriber(key, _ignore, history=True)

    kept = subscribe() if arrangement == "kept subscriber" else None
    empty = []
    try:
        for _ in range(queries):
            fresh = subscribe() if arrangement == "fresh subscriber" else None
            start = time.perf_counter()
            found = live_instances(client.session, client.keys, NAME)
            took = (time.perf_counter() - start) * 1e3
            if zid not in found:
                empty.append(took)
            if fresh is not None:
                fresh.undeclare()
    finally:
        if kept is not None:
            kept.undeclare()
    return empty


def _ignore(sample: zenoh.Sample) -> None:
    """A subscriber's callback that keeps nothing."""


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    parser.add_argument("--queries", type=int, default=500, help="queries per repeat")
    parser.add_argument("--repeats", type=int, default=5, help="interleaved repeats (≥ 5)")
    parser.add_argument(
        "--smoke", action="store_true", help="1 repeat of 5 queries: runs every arrangement"
    )
    args = parser.parse_args(argv)
    if args.smoke:
        args.queries, args.repeats = 5, 1
    print(f"{datetime.now(UTC):%Y-%m-%d %H:%M} UTC; {os.cpu_count()} CPUs, {cpu_model()}")
    zenoh_version = importlib.metadata.version("eclipse-zenoh")
    print(f"python {platform.python_version()}, eclipse-zenoh {zenoh_version}")
    endpoint = free_tcp_endpoint()
    router = spawn_router(endpoint)
    net = NetConfig(connect=(endpoint,), robot="probe")
    counts: dict[str, list[int]] = {a: [] for a in ARRANGEMENTS}
    times: dict[str, list[float]] = {a: [] for a in ARRANGEMENTS}
    try:
        with Node(NAME, net) as service, Node(None, net) as client:
            service.ready()
            zid = zid_of(service.session)
            steps: list[Callable[[], None]] = []
            for _ in range(args.repeats):
                for arrangement in ARRANGEMENTS:

                    def step(arrangement: str = arrangement) -> None:
                        empty = _ask(client, zid, args.queries, arrangement)
                        counts[arrangement].append(len(empty))
                        times[arrangement].extend(empty)

                    steps.append(step)
            with progress_bar() as bar:
                for step in bar.track(steps, description="repeats × arrangements"):
                    step()
    finally:
        router.terminate()
        router.wait(10)
    print(f"\n{args.queries} queries per repeat, {args.repeats} repeats")
    print("| arrangement | empty answers (all repeats) | per repeat | their wall time (ms) |")
    print("|---|---|---|---|")
    for arrangement in ARRANGEMENTS:
        total = sum(counts[arrangement])
        took = f"{statistics.median(times[arrangement]):.2f} median" if times[arrangement] else "–"
        print(
            f"| {arrangement} | {total} of {args.queries * args.repeats} "
            f"| {median_spread(counts[arrangement], '.0f')} | {took} |"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
