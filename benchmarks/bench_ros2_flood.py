"""Benchmark of `archery ros2 --operator` under a command flood: how long after the flood's end
the arm is at rest, against one command.

Run `python -m benchmarks.bench_ros2_flood [--repeats 5] [--count 20000] [--smoke]`. A router
and the robot service (`archery up`'s Launcher, rtf 1) and `archery ros2 --operator` as child
processes; this process puts raw Zenoh samples with rmw_zenoh's attachment on
`0/ROBOT/right_arm/command/…` (`std_msgs/msg/Float64MultiArray`, congestion control BLOCK:
every one reaches the router), as fast as it can. Per repeat, two conditions, interleaved (the
order alternating), each from the arm at rest at A to B (the elbow 0.1 rad away, A and B
swapping every measurement):

* `single` (the baseline): one command to B;
* `flood`: `--count` commands alternating A and B, the last one B.

Figure: the wall time from the last put until the first joint state of the arm within 5 mrad
of B with every joint's speed under 0.01 rad/s and its motion done (goal for the flood: ≤ 0.5 s
beyond the baseline; the issue: 30 s before), the ratio flood/single per repeat, and the flood's
own duration. `--smoke`: 1 repeat of a 2,000-command flood.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import zenoh

from archery.apps.ros2 import convert, typestore
from archery.apps.ros2.command import READY
from archery.apps.ros2.wire import Attachment, data_key
from archery.apps.up.launcher import Launcher
from archery.mesh.netflags import open_session
from archery.mesh.node import Node
from archery.mesh.router import free_tcp_endpoint
from archery.mesh.subscription import Subscription
from archery.protocol.messages import JointState
from archery.protocol.verbs import robot as rv
from benchmarks.machine import cpu_model
from benchmarks.spread import median_spread

__all__ = ["main"]

ROBOT = "benchflood"
PART = "right_arm"
ELBOW = 3  # the joint moved, in the part's order (r_elbow)
STEP = 0.1  # rad between A and B
CLOSE = 5e-3  # rad: at B
STILL = 0.01  # rad/s: at rest
REST_TIMEOUT = 120.0  # s: the longest a measurement waits for rest


class Arm:
    """The right arm's joint states as they arrive (wall arrival time, state)."""

    def __init__(self, node: Node) -> None:
        self._cond = threading.Condition()
        self._states: list[tuple[float, JointState]] = []
        self.sub: Subscription[JointState] = Subscription(
            node.session, node.keys.state(PART), JointState, "fifo", self._arrived
        )

    def _arrived(self, state: JointState) -> None:
        with self._cond:
            self._states.append((time.monotonic(), state))
            self._cond.notify_all()

    def at_rest(self, target: list[float], after: float) -> float:
        """The arrival time (monotonic s) of the first state after `after` at rest at
        `target`."""
        deadline = time.monotonic() + REST_TIMEOUT
        seen = 0
        with self._cond:
            while True:
                for arrived, state in self._states[seen:]:
                    if arrived >= after and _rests_at(state, target):
                        return arrived
                seen = len(self._states)
                left = deadline - time.monotonic()
                if left <= 0:
                    raise RuntimeError(f"the arm not at rest at {target} in {REST_TIMEOUT:g} s")
                self._cond.wait(left)

    def forget(self) -> None:
        with self._cond:
            self._states.clear()


def _rests_at(state: JointState, target: list[float]) -> bool:
    return (
        state.motion_done
        and all(abs(p - t) < CLOSE for p, t in zip(state.position, target, strict=True))
        and all(abs(v) < STILL for v in state.velocity)
    )


def _command(values: list[float]) -> bytes:
    layout = typestore.new("std_msgs/msg/MultiArrayLayout", dim=[], data_offset=0)
    message = typestore.new(
        convert.FLOAT_COMMAND, layout=layout, data=np.array(values, dtype=np.float64)
    )
    return typestore.serialize(message, convert.FLOAT_COMMAND)


def _measure(
    publisher: Any, arm: Arm, a: list[float], b: list[float], count: int
) -> tuple[float, float]:
    """(s from the last put until the arm rests at `b`, s the puts took) for `count` commands
    alternating `a` and `b`, the last `b` (count 1: `b` alone)."""
    to_a, to_b = _command(a), _command(b)
    gid = bytes(range(16))
    arm.forget()
    started = time.monotonic()
    for i in range(count):
        payload = to_b if (count - 1 - i) % 2 == 0 else to_a
        publisher.put(payload, attachment=Attachment(i + 1, time.time_ns(), gid).encode())
    ended = time.monotonic()
    return arm.at_rest(b, ended) - ended, ended - started


def _run(repeats: int, count: int, base: Path) -> dict[str, list[float]]:
    endpoint = free_tcp_endpoint()
    launcher = Launcher(endpoint, ROBOT, base / "logs", {"robot": ["--rtf", "1"]})
    launcher.up(180, services=["robot"])
    node_proc = None
    try:
        node_proc = subprocess.Popen(
            [sys.executable, "-m", "archery.apps.cli", "ros2", "--connect", endpoint,
             "--robot", ROBOT, "--operator"],
            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
        )  # fmt: skip
        assert node_proc.stdout is not None
        line = node_proc.stdout.readline()
        if not line.startswith(READY):
            raise RuntimeError(f"the node did not start: {line!r}")
        with Node(None, launcher.net) as node:
            arm = Arm(node)
            home = node.call_typed(node.keys.part_rpc(PART), rv.GET_TARGETS).position
            a = list(home)
            b = [*home[:ELBOW], home[ELBOW] + STEP, *home[ELBOW + 1 :]]
            session = open_session(launcher.net)
            ros_type = convert.FLOAT_COMMAND
            key = data_key(
                0, f"/{ROBOT}/{PART}/command", typestore.dds_type_name(ros_type),
                typestore.type_hash(ros_type),
            )  # fmt: skip
            publisher = session.declare_publisher(
                key, congestion_control=zenoh.CongestionControl.BLOCK
            )
            deadline = time.monotonic() + 30
            while not publisher.matching_status.matching:
                if time.monotonic() > deadline:
                    raise RuntimeError("the node's command subscription never matched")
                time.sleep(0.05)
            _measure(publisher, arm, a, b, 1)  # warm-up: the arm at b
            a, b = b, a
            out: dict[str, list[float]] = {"single": [], "flood": [], "flood_s": [], "ratio": []}
            for repeat in range(repeats):
                order = ("single", "flood") if repeat % 2 == 0 else ("flood", "single")
                got: dict[str, float] = {}
                for condition in order:
                    n = 1 if condition == "single" else count
                    rest, took = _measure(publisher, arm, a, b, n)
                    a, b = b, a
                    got[condition] = rest
                    if condition == "flood":
                        out["flood_s"].append(took)
                    print(f"  repeat {repeat + 1} {condition}: at rest {rest:.3f} s after "
                          f"the last of {n} (sent in {took:.3f} s)", flush=True)  # fmt: skip
                out["single"].append(got["single"])
                out["flood"].append(got["flood"])
                out["ratio"].append(got["flood"] / got["single"])
            publisher.undeclare()
            session.close()
            arm.sub.close()
            return out
    finally:
        if node_proc is not None and node_proc.poll() is None:
            node_proc.terminate()
            node_proc.wait(60)
        launcher.stop_all()


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark and print its figures."""
    os.environ.setdefault("MUJOCO_GL", "egl")
    parser = argparse.ArgumentParser(prog="python -m benchmarks.bench_ros2_flood")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--count", type=int, default=20_000)
    parser.add_argument("--smoke", action="store_true", help="1 repeat, 2,000 commands")
    args = parser.parse_args(argv)
    repeats, count = (1, 2_000) if args.smoke else (args.repeats, args.count)
    print(f"bench_ros2_flood: {time.strftime('%Y-%m-%d')}, {cpu_model()}, {os.cpu_count()} "
          f"cores; {repeats} repeats of {count} commands", flush=True)  # fmt: skip
    with tempfile.TemporaryDirectory() as tmp:
        out = _run(repeats, count, Path(tmp))
    print(f"at rest after one command (baseline): {median_spread(out['single'], '.3f', ' s')}")
    print(f"at rest after the flood's end:        {median_spread(out['flood'], '.3f', ' s')}")
    extra = [f - s for f, s in zip(out["flood"], out["single"], strict=True)]
    print(f"flood minus single (goal ≤ 0.5 s):    {median_spread(extra, '.3f', ' s')}")
    print(f"ratio flood/single:                   {median_spread(out['ratio'], '.2f', '×')}")
    print(f"the flood's own duration:             {median_spread(out['flood_s'], '.3f', ' s')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
