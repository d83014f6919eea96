"""Least privilege per verb (issue 25) against the code before it, in secure mode: what the
per-verb keys and access-control rules cost.

The code before is a `git archive` of --before (default 3dac023, the last commit before the
issue: one key per `rpc:i` port, access granted per port), run with this interpreter and
environment; the code after is this working tree. Per repeat and tree, alternating which goes
first:

1. **Secure RPC**: a mutual-TLS router with the deployment's access control, the robot's
   identity serving a part's verbs, the controller's identity calling `getLimits` (median of
   --calls round trips), in a fresh process.
2. **A secure session**: `archery up --secure` (router and five services, each its identity)
   and `archery learn --secure --rollouts N --no-until-hit`; the wall time per rollout from the
   journal (first to last done record, over N − 1 rollouts).

Figures: the medians and after/before ratios per repeat (goal ≤ 1.05× for both).

    MUJOCO_GL=egl .venv/bin/python -m benchmarks.bench_acl [--repeats 5] [--calls 2000]
        [--rollouts 12] [--before COMMIT] [--smoke]

`--smoke` runs the same path at its smallest budget: one repeat per tree, 50 timed round trips
(after the workload's 200 unmeasured ones), a secure session of 4 rollouts, the code before
being `git archive HEAD` (this tree's last commit, so that the comparison runs without the
history of a shallow clone); the session's hit is not filmed (`archery learn --no-film`), the
rendering backend is left to the product (`MUJOCO_GL` is passed on only when set).
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
from pathlib import Path

from archery.mesh.router import free_tcp_endpoint, wait_for_endpoint
from benchmarks.spread import median_spread
from benchmarks.trees import ROOT, env_for, header, interleaved, tree_at

RPC_WORKLOAD = r"""
import json, statistics, subprocess, sys, tempfile, time
from pathlib import Path
from archery.mesh.credentials import init_deployment
from archery.mesh.netflags import NetConfig
from archery.mesh.node import Node
from archery.mesh.router import free_tcp_endpoint, spawn_router
from archery.protocol.verbs.robot import GET_LIMITS
from archery.protocol.verbs.robot import PART_VERBS, LimitsReply

calls = int(sys.argv[1])
robot = "aclbench"
with tempfile.TemporaryDirectory() as tmp:
    deployment = init_deployment(Path(tmp) / "deploy", robot=robot)
    endpoint = free_tcp_endpoint().replace("tcp/", "tls/")
    router = spawn_router(endpoint, secure=str(deployment))
    try:
        def net(identity):
            return NetConfig(
                connect=(endpoint,), robot=robot, secure=str(deployment), identity=identity
            )

        limits = LimitsReply(names=["a"], min=[-1.0], max=[1.0], tolerance=0.01)

        def refuse(_):
            raise RuntimeError("not served here")

        handlers = {name: refuse for name in PART_VERBS.names()}
        handlers["getLimits"] = lambda _: limits
        with Node("robot", net("robot")) as server, Node("controller", net("controller")) as client:
            key = server.keys.part_rpc("left_arm")
            server.serve(key, PART_VERBS.bind_names(handlers))
            server.ready()
            client.wait_alive(["robot"], 30)
            verb = GET_LIMITS
            deadline = time.monotonic() + 30
            while True:  # the queryable has reached the router
                try:
                    client.call_typed(key, verb, timeout=2)
                    break
                except Exception:
                    if time.monotonic() > deadline:
                        raise
            for _ in range(200):
                client.call_typed(key, verb)
            times = []
            for _ in range(calls):
                t0 = time.perf_counter()
                client.call_typed(key, verb)
                times.append(time.perf_counter() - t0)
    finally:
        router.terminate()
        try:
            router.wait(10)
        except subprocess.TimeoutExpired:  # a router slow to stop is not what is measured
            router.kill()
            router.wait(10)
print(json.dumps({"rpc_ms": 1e3 * statistics.median(times)}))
"""


def _rpc(tree: Path, calls: int) -> float:
    run = subprocess.run(
        [sys.executable, "-c", RPC_WORKLOAD, str(calls)],
        cwd=tree,
        env=env_for(tree),
        capture_output=True,
        text=True,
        timeout=600,
    )
    if run.returncode != 0:
        raise RuntimeError(f"the RPC workload failed in {tree}: {run.stderr[-3000:]}")
    return float(json.loads(run.stdout.strip().splitlines()[-1])["rpc_ms"])


UP_FLAGS = ("--restart", "never")
LEARN_FLAGS = ("--no-until-hit", "--quiet", "--wait", "120")


def _cli(*argv: str) -> list[str]:
    return [sys.executable, "-m", "archery.apps.cli", *argv]


def _session(tree: Path, work: Path, rollouts: int, seed: int, smoke: bool = False) -> float:
    """Wall time per rollout (s) of a secure session on a fresh `archery up --secure`. `smoke`:
    the rendering backend left to the product (else MUJOCO_GL is egl when unset), the hit not
    filmed."""
    if smoke:
        env, film = env_for(tree), ["--no-film"]
    else:
        env, film = env_for(tree, MUJOCO_GL=os.environ.get("MUJOCO_GL", "egl")), []
    deploy, runs = work / "deploy", work / "runs"
    subprocess.run(
        _cli("keys", "init", str(deploy)), cwd=tree, env=env, check=True, capture_output=True
    )
    endpoint = free_tcp_endpoint().replace("tcp/", "tls/")
    secure = ["--secure", str(deploy)]
    with open(work / "up.log", "wb") as log:
        up = subprocess.Popen(
            [
                *_cli("up", *secure, "--listen", endpoint, *UP_FLAGS, "--logs", str(work / "logs")),
                "--runs",
                str(runs),
            ],
            cwd=tree,
            env=env,
            stdout=log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
    try:
        wait_for_endpoint(endpoint, 120)
        learn = subprocess.run(
            [
                *_cli("learn", *secure, "--connect", endpoint, "--rollouts", str(rollouts)),
                "--seed",
                str(seed),
                *LEARN_FLAGS,
                *film,
            ],
            cwd=tree,
            env=env,
            capture_output=True,
            text=True,
            timeout=900,
        )
        if learn.returncode != 0:
            raise RuntimeError(f"learn failed in {tree}: {learn.stderr[-2000:]}")
        journal = Path(json.loads(learn.stdout.strip().splitlines()[-1])["journal"])
    finally:
        os.killpg(up.pid, signal.SIGTERM)
        up.wait(120)
    times = [
        record["t"]
        for record in map(json.loads, journal.read_text().splitlines())
        if record.get("record") == "done"
    ]
    return (times[-1] - times[0]) / (len(times) - 1)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="bench_acl", description=__doc__)
    parser.add_argument("--repeats", type=int, default=5, help="interleaved repeats (≥ 5)")
    parser.add_argument("--calls", type=int, default=2000, help="RPC round trips per repeat")
    parser.add_argument("--rollouts", type=int, default=12, help="rollouts per session")
    parser.add_argument("--before", default="3dac023", help="the commit before per-verb access")
    parser.add_argument(
        "--smoke",
        action="store_true",
        help="smallest budget: 1 repeat, 50 calls, 4 rollouts, before = HEAD (overrides the "
        "flags above)",
    )
    args = parser.parse_args(argv)
    if args.smoke:
        args.repeats, args.calls, args.rollouts, args.before = 1, 50, 4, "HEAD"
    elif args.repeats < 5:
        parser.error("--repeats must be at least 5")
    header()
    rpc: dict[str, list[float]] = {"before": [], "after": []}
    rollout: dict[str, list[float]] = {"before": [], "after": []}
    with tempfile.TemporaryDirectory() as tmp:
        before = tree_at(args.before, Path(tmp))
        trees = [("before", before), ("after", ROOT)]
        for k, name, tree in interleaved(args.repeats, trees):
            rpc[name].append(_rpc(tree, args.calls))
            with tempfile.TemporaryDirectory() as work:
                session = _session(tree, Path(work), args.rollouts, k, args.smoke)
                rollout[name].append(session)
            print(
                f"  repeat {k + 1} {name}: rpc {rpc[name][-1]:.3f} ms, "
                f"{1e3 * rollout[name][-1]:.0f} ms per rollout",
                file=sys.stderr,
                flush=True,
            )
    rpc_ratio = [a / b for a, b in zip(rpc["after"], rpc["before"], strict=True)]
    roll_ratio = [a / b for a, b in zip(rollout["after"], rollout["before"], strict=True)]
    ms = {n: [1e3 * v for v in values] for n, values in rollout.items()}
    print(
        f"- Secure RPC round trip (getLimits, controller → robot), median of {args.calls}, "
        f"{args.repeats} interleaved repeats: before {median_spread(rpc['before'], '.3f', ' ms')}"
        f", after {median_spread(rpc['after'], '.3f', ' ms')}; after/before "
        f"{median_spread(rpc_ratio, '.3f', '×')} (goal ≤ 1.05×)"
    )
    print(
        f"- Secure session, wall time per rollout ({args.rollouts} rollouts, ARCHER, the whole "
        f"budget): before {median_spread(ms['before'], '.0f', ' ms')}, after "
        f"{median_spread(ms['after'], '.0f', ' ms')}; after/before "
        f"{median_spread(roll_ratio, '.3f', '×')} (goal ≤ 1.05×)"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
