"""The dashboard's request latency with 200 idle (half-open) connections open against none.

A dashboard (no session running: its own robot's watch finds no service) over a real router
on loopback answers GET /api/state and GET / (the page), each on a new connection as a page's
polls come; the same requests are timed with no other connection open and after 200
connections were opened that never send a request. The dashboard keeps `MAX_CONNECTIONS` of
them (idle until their `REQUEST_TIMEOUT`) and closes the others at once; each timed request
makes it close one more, which is opened again before the next request (and accepted: nothing
on its way while a request is timed), so every request meets the dashboard full of idle
connections. The two conditions alternate within each repeat so machine noise hits both alike;
the figure is each path's median latency and the ratio idle / none (the issue sets no goal; the
ratio is the cost of closing one idle connection for each request).

    python -m benchmarks.bench_dashboard [--requests 50] [--repeats 7] [--idle 200]

`--smoke`: 1 repeat of 3 requests per path and condition (seconds; its figures are noise).
"""

from __future__ import annotations

import argparse
import http.client
import os
import platform
import select
import socket
import statistics
import time

from archery.apps.dashboard.guard import MAX_CONNECTIONS, REQUEST_TIMEOUT, GuardedServer
from archery.apps.dashboard.server import Dashboard, bind
from archery.mesh.netflags import NetConfig
from archery.mesh.router import free_tcp_endpoint, spawn_router
from benchmarks.machine import cpu_model
from benchmarks.spread import median_spread

PATHS = ("/api/state", "/")


class Idle:
    """`count` connections to `server` that never send a request; the server keeps
    `max_connections` of them at most (it closes the others at once, for the new ones)."""

    def __init__(self, server: GuardedServer, count: int) -> None:
        self.server = server
        self.address = (str(server.server_address[0]), int(server.server_address[1]))
        self.sockets = [socket.create_connection(self.address, timeout=30) for _ in range(count)]
        self.closed = 0

    def top_up(self) -> None:
        """Drop the connections the server closed, then open new ones until it holds as many
        idle connections as it keeps (one per request served since the last call); returns
        once it does, so no connection is on its way when a request is timed."""
        readable, _, _ = select.select(self.sockets, [], [], 0)
        for closed in readable:
            closed.close()
            self.sockets.remove(closed)
            self.closed += 1
        most = self.server.max_connections
        deadline = time.monotonic() + 10
        while self.server.connections() != (most, most):
            assert time.monotonic() < deadline, self.server.connections()
            opened, waiting = self.server.connections()
            if opened == waiting:  # no request's connection still closing: open the missing
                for _ in range(most - opened):
                    self.sockets.append(socket.create_connection(self.address, timeout=30))
                while self.server.connections()[0] < most and time.monotonic() < deadline:
                    time.sleep(0.001)  # until the server accepted them
            else:
                time.sleep(0.001)

    def close(self) -> None:
        for connection in self.sockets:
            connection.close()


def _get(address: tuple[str, int], path: str) -> float:
    """One GET on a new connection; its latency (ms), from connecting to the body's end."""
    t0 = time.perf_counter()
    connection = http.client.HTTPConnection(*address, timeout=30)
    try:
        connection.request("GET", path)
        response = connection.getresponse()
        response.read()
    finally:
        connection.close()
    took = (time.perf_counter() - t0) * 1e3
    assert response.status == 200, (path, response.status)
    return took


def _measure(address: tuple[str, int], requests: int, idle: Idle | None) -> dict[str, list[float]]:
    """`requests` GETs of each path, alternating (ms each)."""
    times: dict[str, list[float]] = {path: [] for path in PATHS}
    for _ in range(requests):
        for path in PATHS:
            if idle is not None:
                idle.top_up()
            times[path].append(_get(address, path))
    return times


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark and print each path's latency with and without the idle connections."""
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.bench_dashboard", description=__doc__
    )
    parser.add_argument("--requests", type=int, default=50, help="GETs per path, condition, repeat")
    parser.add_argument("--repeats", type=int, default=7, help="interleaved repeats (≥ 5)")
    parser.add_argument("--idle", type=int, default=200, help="half-open connections (default 200)")
    parser.add_argument("--smoke", action="store_true", help="1 repeat of 3 GETs: no figures")
    args = parser.parse_args(argv)
    if args.smoke:
        args.requests, args.repeats = 3, 1
    elif args.repeats < 5:
        parser.error("--repeats must be at least 5")
    endpoint = free_tcp_endpoint()
    router = spawn_router(endpoint)
    net = NetConfig(connect=(endpoint,), robot="bench")
    results: list[dict[str, dict[str, list[float]]]] = []
    held: list[int] = []
    closed = 0
    try:
        with Dashboard(net, bind("127.0.0.1", 0)) as dash:
            address = (str(dash.server.server_address[0]), int(dash.server.server_address[1]))
            _measure(address, 3 if args.smoke else 20, None)  # warm up
            for r in range(args.repeats):
                repeat: dict[str, dict[str, list[float]]] = {}
                for condition in ("none", "idle") if r % 2 == 0 else ("idle", "none"):
                    idle = Idle(dash.server, args.idle) if condition == "idle" else None
                    try:
                        repeat[condition] = _measure(address, args.requests, idle)
                        if idle is not None:
                            held.append(dash.server.connections()[0])
                            closed += idle.closed
                    finally:
                        if idle is not None:
                            idle.close()
                results.append(repeat)
    finally:
        router.terminate()
        router.wait()
    print(f"machine: {cpu_model()}, {os.cpu_count()} cores, Python {platform.python_version()}")
    print(
        f"{args.repeats} interleaved repeats × {args.requests} GETs per path and condition, "
        f"a new connection each; {args.idle} half-open connections in 'idle' "
        f"(MAX_CONNECTIONS {MAX_CONNECTIONS}, REQUEST_TIMEOUT {REQUEST_TIMEOUT:g} s)"
    )
    if args.smoke:
        print("smoke run: no figures")
        return 0
    print(f"{'path':<12} {'none (ms)':>24} {'idle (ms)':>24} {'ratio idle/none':>26}")
    for path in PATHS:
        none = [statistics.median(rep["none"][path]) for rep in results]
        idle_ms = [statistics.median(rep["idle"][path]) for rep in results]
        ratios = [i / n for i, n in zip(idle_ms, none, strict=True)]
        print(
            f"{path:<12} {median_spread(none, '.2f'):>24} {median_spread(idle_ms, '.2f'):>24} "
            f"{median_spread(ratios, '.3f', '×'):>26}"
        )
    print(
        f"connections the dashboard held with the idle ones open: {median_spread(held, '.0f')}; "
        f"idle connections it closed (for new ones): {closed}"
    )
    print("each figure: median over repeats of the repeat's median [min, max]")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
