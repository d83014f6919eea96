"""Benchmark of the robot and controller services over the mesh: posture → release → landed.

Run `python -m benchmarks.bench_robot_service [--rollouts N]`. It starts an in-process Zenoh
router and `archery robot` (rtf 0) and `archery controller` as real child processes, then, as a
learner would, asks for the archery posture of N seeded random θ in the posture box, nocks,
releases and waits for the landing event. Figures (wall time unless said otherwise):

* start-up until both services are alive;
* per rollout: posture RPC (solve, move, wait for motion done), nock, release (the flight),
  the landed/missed event after the release reply, and the whole rollout;
* simulated seconds per wall second during the posture moves;
* ‖θ − θ_measured‖ of the postures;
* a cheap controlboard RPC round trip (getPositions).

`--smoke`: 2 rollouts on the same router and services (seconds; its figures are noise).
"""

from __future__ import annotations

import argparse
import os
import platform
import subprocess
import sys
import time

import numpy as np

from archery.mesh.netflags import NetConfig
from archery.mesh.node import Node
from archery.mesh.router import free_tcp_endpoint, open_router
from archery.protocol.messages import WorldEvent
from archery.protocol.theta import THETA_BOX
from tests.rpc import rpc_call

__all__ = ["main"]


def _spawn(verb: str, net: NetConfig, *flags: str) -> subprocess.Popen[bytes]:
    argv = [sys.executable, "-m", "archery.apps.cli", verb, "--connect", net.connect[0]]
    return subprocess.Popen([*argv, "--robot", net.robot, *flags], stdin=subprocess.DEVNULL)


def _row(name: str, values: list[float], unit: str = "ms", scale: float = 1e3) -> str:
    v = np.asarray(values) * scale
    return (
        f"| {name} | {np.median(v):.2f} | {np.percentile(v, 90):.2f} | {v.min():.2f} | "
        f"{v.max():.2f} | {unit} |"
    )


def _rollouts(node: Node, count: int, seed: int) -> dict[str, list[float]]:
    keys = node.keys
    events = node.subscribe(keys.world_events(), WorldEvent, mode="fifo")
    rng = np.random.default_rng(seed)
    out: dict[str, list[float]] = {
        k: [] for k in ("posture", "nock", "release", "event", "total", "rtf", "error", "rpc")
    }
    sim = rpc_call(node, keys.archery_rpc(), "status")["sim_time"]
    for _ in range(count):
        theta = rng.uniform(THETA_BOX.low, THETA_BOX.high).tolist()
        t0 = time.perf_counter()
        reply = rpc_call(
            node, keys.cartesian_rpc("archery"), "posture", {"theta": theta}, timeout=60
        )
        t1 = time.perf_counter()
        rpc_call(node, keys.archery_rpc(), "nock")
        t2 = time.perf_counter()
        shot = rpc_call(node, keys.archery_rpc(), "release", timeout=60)
        t3 = time.perf_counter()
        while True:
            event = events.get(10)
            if event.kind in ("landed", "missed") and event.shot == shot["shot"]:
                break
        t4 = time.perf_counter()
        if not reply["reached"]:
            raise RuntimeError(f"posture for θ={theta} not reached: {reply['reason']}")
        out["posture"].append(t1 - t0)
        out["nock"].append(t2 - t1)
        out["release"].append(t3 - t2)
        out["event"].append(t4 - t3)
        out["total"].append(t4 - t0)
        out["rtf"].append((reply["sim_time"] - sim) / reply["wall_s"])
        out["error"].append(reply["measured_error_m"])
        sim = shot["sim_time"]
    for _ in range(200):
        t0 = time.perf_counter()
        rpc_call(node, keys.part_rpc("left_arm"), "getPositions")
        out["rpc"].append(time.perf_counter() - t0)
    return out


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark and print a Markdown table."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rollouts", type=int, default=50, help="rollouts to time")
    parser.add_argument("--seed", type=int, default=0, help="seed of the θ draws")
    parser.add_argument("--smoke", action="store_true", help="2 rollouts: every part, no figures")
    args = parser.parse_args(argv)
    if args.smoke:
        args.rollouts = 2
    endpoint = free_tcp_endpoint()
    net = NetConfig(connect=(endpoint,), robot="bench")
    with open_router(endpoint):
        start = time.perf_counter()
        procs = [_spawn("robot", net, "--rtf", "0"), _spawn("controller", net)]
        try:
            with Node(None, net) as node:
                node.wait_alive(["robot", "controller"], 120)
                startup = time.perf_counter() - start
                rpc_call(
                    node,
                    node.keys.cartesian_rpc("archery"),
                    "posture",
                    {"theta": [0.17, 0.03, -0.03]},
                )
                results = _rollouts(node, args.rollouts, args.seed)
        finally:
            for proc in procs:
                proc.terminate()
            codes = [proc.wait(30) for proc in procs]
    print(
        f"- Machine: {os.cpu_count()} cores, {platform.processor() or platform.machine()}, "
        f"Python {platform.python_version()}"
    )
    print(
        f"- Start-up until both services are alive: {startup:.2f} s; exit codes on SIGTERM {codes}"
    )
    print(f"- {args.rollouts} rollouts, θ uniform in the posture box (seed {args.seed})\n")
    print("| figure | median | p90 | min | max | unit |\n|---|---|---|---|---|---|")
    for name, key in (
        ("posture RPC (solve, move, motion done)", "posture"),
        ("nock RPC", "nock"),
        ("release RPC (whole flight)", "release"),
        ("landed/missed event after the release reply", "event"),
        ("whole rollout: posture → release → event", "total"),
        ("getPositions RPC round trip", "rpc"),
    ):
        print(_row(name, results[key]))
    print(_row("sim s per wall s during the posture moves", results["rtf"], "×", 1.0))
    print(_row("‖θ − θ_measured‖", results["error"], "mm", 1e3))
    return 0 if all(code == 0 for code in codes) else 1


if __name__ == "__main__":
    sys.exit(main())
