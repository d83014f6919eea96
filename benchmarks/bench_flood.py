"""A posture under a flood of 50,000 valid joint commands, against the code before command
ownership and the rate limit: how long the arm's progress stalls.

The code before is a `git archive` of --before (default 3dac023) run with this interpreter and
environment; the code after is this working tree. One workload runs in a fresh process per tree,
scenario and repeat, alternating which tree goes first: a router, `archery robot` and `archery
controller --traj-time 2` as child processes, a flooder process and the measuring node. Per
repeat: an archery posture from home (its targets), a reset, the same posture unflooded, a reset,
then the posture flooded. The flooder publishes N pre-encoded copies of one command on
`left_arm/command:i` with congestion control BLOCK (every one reaches the router):

* `rival` (rtf 1): valid commands from another node that hold the arm where it is (its latest
  measured position), sent once the arm has started to move: the issue's flood;
* `rival-rtf0` (rtf 0, the default): the same, sent at the moment the posture is asked for, so
  the robot receives the flood and the posture's RPCs and commands together;
* `replay` (rtf 1, watchdog off): N copies of the controller's own left-arm command (its lease
  included, where there is one) taken off `command:i`, sent once the arm moves: the rate
  limit's case, as no ownership check refuses them (the watchdog would rightly hold a stream
  that stops mid-motion, so it is off to measure the loop alone).

Stall: the larger of (a) the longest wall-clock gap between two states of the left arm that
bring it closer to the posture's targets, from its first state until it is within 5 mrad of
them (until WATCH = 30 s after the flood when it never gets there; the posture's own timeout
is 30 s too), and (b) how much later than unflooded it got there. States come at 50 per
simulated second: an unhindered arm at rtf 1 shows gaps of ~20 ms. Goal: ≤ 0.5 s (the issue:
8.7–30.3 s before).

    .venv/bin/python -m benchmarks.bench_flood [--repeats 5] [--count 50000] [--before COMMIT]
        [--scenarios rival,rival-rtf0,replay] [--after-only] [--smoke]

`--smoke` runs the same workload at its smallest budget: every scenario once, on this tree only
(`--after-only`; the code before, `git archive HEAD`, is extracted but not run), with a flood of
500 commands (about 20 s: the rtf-1 postures take 2 s each).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

from benchmarks.spread import median_spread
from benchmarks.trees import ROOT, env_for, header, interleaved, tree_at

__all__ = ["main"]

#: name -> (flood, rtf, robot watchdog (wall s), when the flood starts)
SCENARIOS = {
    "rival": ("rival", "1", "0.1", "mid"),
    "rival-rtf0": ("rival", "0", "0.1", "start"),
    "replay": ("replay", "1", "0", "mid"),
}

# The flooder: connects, captures the controller's left-arm command (replay), then on a line of
# stdin publishes N copies of its payload and prints how long that took.
FLOODER = r"""
import sys, time
import zenoh
from archery.mesh.netflags import NetConfig
from archery.mesh.node import Node
from archery.protocol.codec import encode
from archery.protocol.messages import JointCommand, JointState

endpoint, robot, kind, count = sys.argv[1], sys.argv[2], sys.argv[3], int(sys.argv[4])
with Node(None, NetConfig(connect=(endpoint,), robot=robot)) as node:
    keys = node.keys
    state = node.subscribe(keys.state("left_arm"), JointState)
    captured = []
    commands = node.subscribe(keys.command("left_arm"), JointCommand, callback=captured.append)
    pub = node.session.declare_publisher(
        keys.command("left_arm"), congestion_control=zenoh.CongestionControl.BLOCK
    )
    print("ready", flush=True)
    for line in sys.stdin:
        if kind == "rival":
            payload = encode(JointCommand(part="left_arm", position=list(state.latest().position)))
        else:
            payload = encode(captured[-1])
        commands.close()  # not to hear its own flood
        start = time.monotonic()
        for _ in range(count):
            pub.put(payload)
        print(time.monotonic() - start, flush=True)
"""

WORKLOAD = r"""
import json, subprocess, sys, threading, time
import numpy as np
from archery.mesh.netflags import NetConfig
from archery.mesh.node import Node
from archery.mesh.router import free_tcp_endpoint, spawn_router
from archery.protocol.messages import JointState
from archery.protocol.parts import PARTS
from archery.protocol.errors import RpcError
from tests.rpc import rpc_call

kind, rtf, watchdog, when, count, flooder_src = sys.argv[1:7]
THETA = [0.17, 0.03, -0.03]
TOL = 0.005  # rad: there
WATCH = 30.0  # s: the posture's timeout, and how long the arm is watched after the flood
endpoint = free_tcp_endpoint()
router = spawn_router(endpoint)
robot = "flood"
flags = ["--connect", endpoint, "--robot", robot]
cli = [sys.executable, "-m", "archery.apps.cli"]
procs = [
    subprocess.Popen(
        [*cli, "robot", "--rtf", rtf, "--watchdog", watchdog, *flags], stdin=subprocess.DEVNULL
    ),
    subprocess.Popen([*cli, "controller", "--traj-time", "2", *flags], stdin=subprocess.DEVNULL),
]
flooder = subprocess.Popen(
    [sys.executable, "-c", flooder_src, endpoint, robot, kind, count],
    stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
)
out = {}
try:
    with Node(None, NetConfig(connect=(endpoint,), robot=robot)) as node:
        keys = node.keys
        node.wait_alive(["robot", "controller"], 180)
        assert flooder.stdout.readline().startswith("ready")
        goal = [None]
        seen = []  # (arrival wall s, distance to the goal in rad)

        def on_state(msg):
            if goal[0] is not None:
                error = np.max(np.abs(np.asarray(msg.position) - goal[0]))
                seen.append((time.monotonic(), float(error)))

        node.subscribe(keys.state("left_arm"), JointState, callback=on_state)

        def posture(result):
            result["start"] = time.monotonic()
            try:
                result["reply"] = rpc_call(node, keys.cartesian_rpc("archery"), "posture",
                                           {"theta": THETA, "timeout": WATCH}, timeout=2 * WATCH)
            except RpcError as exc:
                result["reply"] = {"reached": False, "error": exc.code}
            result["s"] = time.monotonic() - result["start"]
            return result

        def progress(start, end):
            # (worst gap between states that bring the arm closer, from its first move; the
            # wall s from `start` until it is there, None if it never is)
            best, last, worst = float("inf"), None, 0.0
            for t, d in list(seen):
                if d < best - 1e-6:
                    if last is not None:
                        worst = max(worst, t - last)
                    best, last = d, t
                    if d <= TOL:
                        return worst, t - start
            return max(worst, end - (last or end)), None

        def home():
            rpc_call(node, keys.archery_rpc(), "reset", {"seed": 0}, timeout=30)
            seen.clear()

        home()
        q = posture({})["reply"]["q"]
        goal[0] = np.array([q[j] for j in PARTS["left_arm"]])
        home()
        plain = posture({})
        out["plain_s"] = plain["s"]
        out["plain_gap_s"], out["plain_arrival_s"] = progress(plain["start"], time.monotonic())
        home()
        result = {}
        thread = threading.Thread(target=posture, args=(result,))
        if when == "start":  # the flood and the posture's request at one moment
            flooder.stdin.write("go\n")
            flooder.stdin.flush()
            thread.start()
        else:  # the flood once the arm moves
            thread.start()
            deadline = time.monotonic() + 60
            while len(seen) < 2 or not any(d < seen[0][1] - 1e-3 for _, d in seen[1:]):
                if time.monotonic() > deadline:
                    raise RuntimeError("the arm never started to move")
                time.sleep(0.005)
            flooder.stdin.write("go\n")
            flooder.stdin.flush()
        flooded = time.monotonic()
        out["flood_s"] = float(flooder.stdout.readline())
        thread.join(3 * WATCH)
        out["flooded_s"] = result["s"]
        out["reached"] = bool(result["reply"]["reached"])
        out["error"] = result["reply"].get("error", "")
        while progress(result["start"], time.monotonic())[1] is None:
            if time.monotonic() > flooded + WATCH:
                break  # an arm not there yet is watched until WATCH s after the flood
            time.sleep(0.05)
        end = time.monotonic()
        out["gap_s"], out["arrival_s"] = progress(result["start"], end)
        late = (out["arrival_s"] if out["arrival_s"] is not None else end - result["start"])
        out["late_s"] = late - out["plain_arrival_s"]
        out["stall_s"] = max(out["gap_s"], out["late_s"])
        counters = rpc_call(node, keys.part_rpc("left_arm"), "counters", timeout=30)
        out["counters"] = {k: counters[k] for k in ("accepted", "rejected", "undecodable")}
        out["by_reason"] = {k: v for k, v in counters["rejected_by_reason"].items() if v}
finally:
    flooder.stdin.close()
    for proc in [flooder, *procs]:
        proc.terminate()
    for proc in [flooder, *procs]:
        try:
            proc.wait(20)
        except subprocess.TimeoutExpired:
            proc.kill()
    router.terminate()
    router.wait(10)
print(json.dumps(out))
"""


def _workload(tree: Path, scenario: str, count: int) -> dict[str, Any]:
    run = subprocess.run(
        [sys.executable, "-c", WORKLOAD, *SCENARIOS[scenario], str(count), FLOODER],
        cwd=tree,
        env=env_for(tree),
        capture_output=True,
        text=True,
        timeout=900,
    )
    if run.returncode != 0:
        raise RuntimeError(f"the workload failed in {tree}: {run.stderr[-3000:]}")
    result: dict[str, Any] = json.loads(run.stdout.strip().splitlines()[-1])
    return result


def _summary(scenario: str, name: str, results: list[dict[str, Any]], count: int) -> str:
    def spread(key: str, spec: str = ".3f") -> str:
        return median_spread([float(r[key]) for r in results], spec, " s")

    reached = sum(bool(r["reached"]) for r in results)
    errors = sorted({r["error"] for r in results if r["error"]})
    return (
        f"- {scenario}, {count:,} commands, {name}: stall {spread('stall_s')} (worst progress "
        f"gap {spread('gap_s')}, arrival later by {spread('late_s')}; unflooded gap "
        f"{spread('plain_gap_s')}); posture reply {spread('flooded_s', '.2f')} flooded, "
        f"{spread('plain_s', '.2f')} unflooded; reached {reached}/{len(results)}"
        + (f" (errors: {', '.join(errors)})" if errors else "")
        + f"; flood sent in {spread('flood_s', '.2f')}; the robot counted (last repeat) "
        f"{results[-1]['counters']} {results[-1]['by_reason']}"
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="bench_flood", description=__doc__)
    parser.add_argument("--repeats", type=int, default=5, help="interleaved repeats (≥ 5)")
    parser.add_argument("--count", type=int, default=50_000, help="commands in the flood")
    parser.add_argument("--before", default="3dac023", help="the commit before ownership")
    parser.add_argument(
        "--scenarios", default=",".join(SCENARIOS), help=f"among {', '.join(SCENARIOS)}"
    )
    parser.add_argument("--after-only", action="store_true", help="skip the code before")
    parser.add_argument(
        "--smoke",
        action="store_true",
        help="smallest budget: 1 repeat of every scenario, 500 commands, this tree only "
        "(overrides the flags above)",
    )
    args = parser.parse_args(argv)
    if args.smoke:
        args.repeats, args.count, args.before, args.after_only = 1, 500, "HEAD", True
        args.scenarios = ",".join(SCENARIOS)
    scenarios = [s for s in args.scenarios.split(",") if s]
    if args.repeats < 5 and not args.smoke:
        parser.error("--repeats must be at least 5")
    if not set(scenarios) <= set(SCENARIOS):
        parser.error(f"--scenarios must be among {', '.join(SCENARIOS)}")
    header()
    with tempfile.TemporaryDirectory() as tmp:
        before = tree_at(args.before, Path(tmp))
        trees = [("after", ROOT)] if args.after_only else [("before", before), ("after", ROOT)]
        for scenario in scenarios:
            got: dict[str, list[dict[str, Any]]] = {name: [] for name, _ in trees}
            for k, name, tree in interleaved(args.repeats, trees):
                result = _workload(tree, scenario, args.count)
                got[name].append(result)
                print(f"  {scenario} {k + 1} {name}: {result}", file=sys.stderr, flush=True)
            for name, results in got.items():
                print(_summary(scenario, name, results, args.count), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
