"""Start-order drills (`order-K`): the router and the five services are started one by one in
an order with the router in position K (0: first … 5: last), the services rotated by K so each
of them comes first once, under supervision from the first start.

A service started before the router cannot open its Zenoh session and exits (status 1); the
supervisor restarts it (on-failure, back-off ≤ 1 s) until the router listens. The next process
is started once the one before is alive, or, while there is no router yet, `STAGGER` s later
(deliberately: time enough to fail). Judged: the whole mesh ends up alive and a 3-rollout
session started then finishes. Time to recover: from the last start to the session's first
done rollout; no fault is detected.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path

from archery.apps.drills.faults import finish
from archery.apps.drills.mesh import DrillMesh
from archery.apps.drills.verdict import DrillResult
from archery.apps.up.launch_config import SERVICES

__all__ = ["STAGGER", "start_order", "start_order_drill"]

STAGGER = 1.0  # s between two starts while no router listens


def start_order(position: int) -> list[str]:
    """The start order of drill `order-{position}`: the services rotated, the router inserted."""
    services = list(SERVICES[position:] + SERVICES[:position])
    return [*services[:position], "router", *services[position:]]


def start_order_drill(workdir: Path, position: int, seed: int) -> DrillResult:
    """Start a whole mesh in the order `start_order(position)`; a session must complete."""
    order = start_order(position)
    pause = threading.Event()
    with DrillMesh(workdir / f"order{position}", f"order{position}", start=False) as mesh:
        mesh.supervise()
        router_up = False
        for name in order:
            if name == "router":
                mesh.launcher.start_router()
                mesh.observe()
                router_up = True
            else:
                mesh.launcher.start(name)
                if router_up:
                    mesh.wait_alive([name])
                else:
                    pause.wait(STAGGER)
        last = time.time()
        alive = mesh.wait_alive()
        run = mesh.start_session(seed, rollouts=3)
        first = mesh.until(lambda: mesh.done_after(run, last), "a rollout done")[0].t
        restarts = {n: len(t) for n, t in mesh.supervisor.restarts.items() if t}
        listed = ", ".join(f"{n} {c}" for n, c in restarts.items()) or "none"
        return finish(
            f"order-{position}",
            mesh,
            [run],
            [],
            expect="finished",
            recover_s=first - last,
            notes=[
                f"order {' → '.join(order)}; all alive {alive - last:.1f} s after the last "
                f"start; restarts: {listed}"
            ],
            details={"order": order, "restarts": restarts, "alive_s": alive - last},
        )
