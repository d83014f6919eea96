"""Benchmark of `archery yarp` against the mesh it bridges, with YARP's own code on the other side.

Run `python -m benchmarks.bench_yarp [--repeats 5] [--window 10] [--calls 20]`. One mesh
(`archery up`, rtf 1), YARP's own `yarpserver` on loopback and `archery yarp --operator`; then,
each figure over `--repeats` interleaved repeats (median [min, max]):

- the encoder stream: joint states a YARP reader gets on `/ROBOT/left_arm/state:o` and
  `stateExt:o` in a window, against those the mesh's own `state:o` delivers to a node's
  subscriber in the same window (goal ≥ 95 %);
- a `positionMove` round trip through YARP's `remote_controlboard` against the mesh's own
  `positionMove` verb, the two alternating call by call (goal ≤ 1.5×);
- the bridge's CPU (user + system) in a window with one YARP reader on each of its output
  ports against one with none, the two alternating (no goal).

`--smoke`: 1 repeat, 1 s windows, 3 calls.
"""

from __future__ import annotations

import argparse
import math
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import psutil

from archery.apps.yarp.network import free_server_port
from archery.mesh.netflags import NetConfig
from archery.mesh.node import open_node
from archery.mesh.router import free_tcp_endpoint
from archery.protocol.messages import JointState
from archery.protocol.parts import PARTS
from archery.protocol.robotspec import SERVICES
from archery.protocol.verbs import robot as rv
from benchmarks.machine import cpu_model
from benchmarks.spread import median_spread

__all__ = ["main"]

ROBOT = "benchyarp"
ARM = "left_arm"
ELBOW = 3
OUTPUTS = [
    *(f"/{ROBOT}/{part}/{leaf}" for part in PARTS for leaf in ("state:o", "stateExt:o")),
    f"/{ROBOT}/cam/target:o",
    f"/{ROBOT}/detector/hit:o",
    f"/{ROBOT}/world/events:o",
]


def _ready(proc: subprocess.Popen[str], ready: str) -> None:
    assert proc.stdout is not None
    for line in proc.stdout:
        if line.startswith(ready):
            return
    raise RuntimeError(f"{proc.args!r} ended before {ready!r}")


class Setup:
    """The mesh, YARP's name server and the bridge, until `close`."""

    def __init__(self, tmp: Path) -> None:
        self.procs: list[subprocess.Popen[str]] = []
        endpoint = free_tcp_endpoint()
        cli = [sys.executable, "-m", "archery.apps.cli"]
        self.procs.append(
            subprocess.Popen(
                [
                    *cli,
                    "up",
                    "--listen",
                    endpoint,
                    "--robot",
                    ROBOT,
                    "--rtf",
                    "1",
                    "--logs",
                    str(tmp / "logs"),
                    "--runs",
                    str(tmp / "runs"),
                ],
                stdout=subprocess.PIPE,
                stderr=subprocess.DEVNULL,
                text=True,
            )
        )
        _ready(self.procs[-1], "archery up: all alive")
        self.node = open_node(NetConfig(connect=(endpoint,), robot=ROBOT), 60)
        self.node.wait_alive(SERVICES, timeout=120)
        port = free_server_port("127.0.0.1")
        conf = tmp / "yarp"
        conf.mkdir()
        (conf / "yarp.conf").write_text(f"127.0.0.1 {port} yarp\n")
        os.environ.update(YARP_CONFIG_HOME=str(conf), YARP_IP="127.0.0.1")
        self.procs.append(
            subprocess.Popen(
                [str(Path(sys.executable).parent / "yarpserver"), "--read", "--socket", str(port)],
                stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL,
                text=True,
                start_new_session=True,  # YARP's launcher script and the server: one group
            )
        )
        import yarp

        self.yarp = yarp
        yarp.Network.init()
        deadline = time.monotonic() + 30
        while not yarp.Network.checkNetwork(0.5):
            if time.monotonic() > deadline:
                raise RuntimeError("yarpserver did not answer")
        self.procs.append(
            subprocess.Popen(
                [
                    *cli,
                    "yarp",
                    "--connect",
                    endpoint,
                    "--robot",
                    ROBOT,
                    "--operator",
                    "--yarp-server",
                    f"127.0.0.1:{port}",
                ],
                stdout=subprocess.PIPE,
                stderr=subprocess.DEVNULL,
                text=True,
            )
        )
        _ready(self.procs[-1], "archery yarp: on YARP")
        self.bridge = psutil.Process(self.procs[-1].pid)

    def close(self) -> None:
        """The bridge, YARP's network here, the name server, the mesh: in that order."""
        self.node.close()
        up, server, bridge = self.procs
        for proc in (bridge, None, server, up):
            if proc is None:
                self.yarp.Network.fini()
                continue
            if proc is server:
                os.killpg(proc.pid, signal.SIGTERM)
            else:
                proc.terminate()
            proc.communicate(timeout=120)


def _cpu(process: psutil.Process) -> float:
    times = process.cpu_times()
    return float(times.user + times.system)


def stream(setup: Setup, window: float) -> tuple[float, float, float]:
    """(mesh states, YARP state:o vectors, YARP stateExt:o bottles) of the arm in one window."""
    yarp = setup.yarp
    counts = {"mesh": 0, "state": 0, "ext": 0}
    counting = threading.Event()

    def mesh(_: JointState) -> None:
        if counting.is_set():
            counts["mesh"] += 1

    sub = setup.node.subscribe(setup.node.keys.state(ARM), JointState, mode="fifo", callback=mesh)
    ports = {"state": yarp.BufferedPortVector(), "ext": yarp.BufferedPortBottle()}
    for key, port in ports.items():
        port.setStrict(True)  # every message, not only the newest
        port.open(f"/bench/{key}:i")
        leaf = "state:o" if key == "state" else "stateExt:o"
        yarp.Network.connect(f"/{ROBOT}/{ARM}/{leaf}", f"/bench/{key}:i")
    stop = threading.Event()

    def read(key: str, port: Any) -> None:
        while not stop.is_set():
            if port.read(True) is not None and counting.is_set():
                counts[key] += 1

    threads = [threading.Thread(target=read, args=item, daemon=True) for item in ports.items()]
    for thread in threads:
        thread.start()
    time.sleep(1.0)  # the connections made and the first messages through
    counting.set()
    time.sleep(window)
    counting.clear()
    stop.set()
    for port in ports.values():
        port.interrupt()
    for thread in threads:
        thread.join(timeout=5)
    for port in ports.values():
        port.close()
    setup.node.unsubscribe(sub)
    return counts["mesh"], counts["state"], counts["ext"]


def round_trips(setup: Setup, board: Any, calls: int) -> tuple[float, float]:
    """Median s of `calls` positionMove round trips through remote_controlboard and through
    the mesh's own verb, alternating call by call (the order swapping each pair)."""
    key = setup.node.keys.part_rpc(ARM)
    elbow = PARTS[ARM][ELBOW]
    times: dict[str, list[float]] = {"yarp": [], "mesh": []}
    for i in range(calls):
        goal = 50.0 + (i % 2) * 10.0  # deg: back and forth inside the elbow's range

        def by_yarp(goal: float = goal) -> None:
            if not board.positionMove(ELBOW, goal):
                raise RuntimeError("remote_controlboard's positionMove failed")

        def by_mesh(goal: float = goal) -> None:
            args = rv.PositionMoveArgs(position=[math.radians(goal)], names=[elbow])
            setup.node.call_typed(key, rv.POSITION_MOVE, args)

        pair = [("yarp", by_yarp), ("mesh", by_mesh)]
        for name, call in pair if i % 2 == 0 else pair[::-1]:
            start = time.perf_counter()
            call()
            times[name].append(time.perf_counter() - start)
    return statistics.median(times["yarp"]), statistics.median(times["mesh"])


def cpu(setup: Setup, window: float, readers: bool) -> float:
    """The bridge's CPU (s per s) in one window, with a reader on each output port or none."""
    yarp = setup.yarp
    ports = []
    if readers:
        for i, name in enumerate(OUTPUTS):
            port = yarp.BufferedPortImageRgb() if "cam" in name else yarp.BufferedPortBottle()
            port.open(f"/bench/reader{i}:i")
            port.setStrict(False)
            yarp.Network.connect(name, f"/bench/reader{i}:i")
            ports.append(port)
        time.sleep(1.0)
    before, start = _cpu(setup.bridge), time.monotonic()
    time.sleep(window)
    used = (_cpu(setup.bridge) - before) / (time.monotonic() - start)
    for port in ports:
        port.close()
    return used


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.bench_yarp", description=__doc__)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--window", type=float, default=10.0, help="s per stream/CPU window")
    parser.add_argument("--calls", type=int, default=20, help="round trips per repeat and path")
    parser.add_argument("--smoke", action="store_true")
    args = parser.parse_args(argv)
    if args.smoke:
        args.repeats, args.window, args.calls = 1, 1.0, 3
    print(f"bench_yarp: {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, {cpu_model()}, "
          f"{os.cpu_count()} cores, load {os.getloadavg()[0]:.1f}", flush=True)  # fmt: skip
    with tempfile.TemporaryDirectory(prefix="bench-yarp-") as folder:
        setup = Setup(Path(folder))
        try:
            yarp = setup.yarp
            options = yarp.Property()
            for k, value in (
                ("device", "remote_controlboard"),
                ("remote", f"/{ROBOT}/{ARM}"),
                ("local", "/bench/board"),
            ):
                options.put(k, value)
            driver = yarp.PolyDriver(options)
            if not driver.isValid():
                raise RuntimeError("remote_controlboard did not open")
            board = driver.viewIPositionControl()
            rates, trips, loads = [], [], []
            for repeat in range(args.repeats):
                mesh, state, ext = stream(setup, args.window)
                rates.append((state / mesh, ext / mesh))
                yarp_s, mesh_s = round_trips(setup, board, args.calls)
                trips.append((yarp_s, mesh_s))
                order = [False, True] if repeat % 2 == 0 else [True, False]
                used = {readers: cpu(setup, args.window, readers) for readers in order}
                loads.append((used[True], used[False]))
                print(
                    f"  repeat {repeat + 1}: mesh {mesh / args.window:.1f}/s, state:o "
                    f"{state / mesh:.3f}, stateExt:o {ext / mesh:.3f}; positionMove "
                    f"{yarp_s * 1e3:.2f} ms vs {mesh_s * 1e3:.2f} ms; bridge CPU "
                    f"{used[True]:.3f} vs {used[False]:.3f} s/s",
                    flush=True,
                )
            driver.close()
        finally:
            setup.close()
    print("bench_yarp results (median [min, max] over repeats):")
    print(
        f"  encoder stream, state:o / mesh: {median_spread([r[0] for r in rates], '.3f')}; "
        f"stateExt:o / mesh: {median_spread([r[1] for r in rates], '.3f')} (goal ≥ 0.95)"
    )
    print(
        f"  positionMove round trip, remote_controlboard / mesh: "
        f"{median_spread([y / m for y, m in trips], '.3f')}× "
        f"({median_spread([y * 1e3 for y, _ in trips])} ms vs "
        f"{median_spread([m * 1e3 for _, m in trips])} ms; goal ≤ 1.5×)"
    )
    print(
        f"  bridge CPU, a reader on each of its {len(OUTPUTS)} output ports / none: "
        f"{median_spread([a / b for a, b in loads], '.2f')}× "
        f"({median_spread([a for a, _ in loads], '.3f')} vs "
        f"{median_spread([b for _, b in loads], '.3f')} s of CPU per s)"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
