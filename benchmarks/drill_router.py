"""Drill: kill the router of a supervised mesh and time how long the services take to be alive
again on the restarted router, without being restarted themselves.

Run `MUJOCO_GL=egl python -m benchmarks.drill_router [--outage 2 15] [--repeats N]`. For each
outage the mesh (a router and the five services, as `archery up` runs them) is started, the
router is SIGKILLed, `up`'s supervisor restarts it on the same endpoint after `outage` s (its
restart back-off), and a fresh node on the new router waits by liveliness until all five
services are alive. Prints one JSON line per run: the outage, the seconds from the new router
listening to all five alive, and whether every service kept its process.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import tempfile
import threading
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

from protocol.netflags import NetConfig
from protocol.node import Node
from protocol.router import free_tcp_endpoint, wait_for_endpoint
from services.launch_config import SERVICES, default_mesh
from services.launcher import Launcher
from services.restart_policy import RestartPolicy
from services.supervisor import Supervisor


def drill(outage: float, logs: Path) -> dict[str, object]:
    """One router outage of about `outage` s under supervision."""
    base = default_mesh(free_tcp_endpoint(), "drill", runs=str(logs / "runs"))
    router = dataclasses.replace(
        base.router, restart=RestartPolicy(backoff=outage, backoff_max=outage)
    )
    launcher = Launcher(logs=logs, mesh=dataclasses.replace(base, router=router))
    stop = threading.Event()
    with launcher:
        launcher.up(120)
        supervisor = Supervisor(launcher, report=lambda line: None)
        thread = threading.Thread(target=supervisor.run, args=(stop,), daemon=True)
        thread.start()
        pids = {n: c.proc.pid for n, c in launcher.children.items() if c.proc}
        launcher.kill("router")
        killed = time.monotonic()
        while launcher.children["router"].proc.pid == pids["router"]:  # type: ignore[union-attr]
            time.sleep(0.02)
        wait_for_endpoint(launcher.endpoint, 30)
        listening = time.monotonic()
        with Node(None, NetConfig(connect=(launcher.endpoint,), robot="drill")) as node:
            node.wait_alive(SERVICES, timeout=120)
        alive = time.monotonic()
        same = all(launcher.children[n].proc.pid == pids[n] for n in SERVICES)  # type: ignore[union-attr]
        stop.set()
        thread.join(30)
    return {
        "outage_s": round(listening - killed, 2),
        "alive_again_s": round(alive - listening, 2),
        "same_processes": same,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--outage", type=float, nargs="+", default=[2.0, 15.0])
    parser.add_argument("--repeats", type=int, default=1)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        for outage in args.outage:
            for _ in range(args.repeats):
                print(json.dumps(drill(outage, Path(tmp))), flush=True)


if __name__ == "__main__":
    main()
