"""Benchmark of `archery ros2`: what the node on the ROS 2 graph costs a session, and what an
rmw_zenoh subscriber that is not ours (zenoh-ros2-sdk) receives of it.

Run `python -m benchmarks.bench_ros2 [--repeats 5] [--rollouts-rtf1 8] [--rollouts-rtf0 30]`.
For each real-time factor (1 and 0) a whole mesh (`archery up`'s Launcher) runs ARCHER sessions
of one seed per repeat under two conditions, interleaved (the order alternating): nothing else,
and `archery ros2` with a zenoh-ros2-sdk subscriber to its joint states and its camera image.
It prints, per rtf: the rollouts of the two sessions of a repeat compared (θ and r), the wall
time per rollout and its ratio with/without (goal ≤ 1.05× at rtf 1), the node's CPU per
rollout and its share of a core, and the joint states and frames the subscriber received per
second against the rates the mesh's publishers report (their own counts).

`--smoke`: 1 repeat of 2-rollout sessions at rtf 0 only.
"""

from __future__ import annotations

import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

from zenoh_ros2_sdk import ROS2Subscriber, ZenohSession

from archery.apps.port_rates import stream_counts
from archery.apps.ros2 import typestore
from archery.apps.ros2.command import READY
from archery.mesh.instances import describe_all
from archery.mesh.node import Node
from archery.protocol.parts import PARTS
from benchmarks.bench_foxglove import _rollouts
from benchmarks.bench_record import _per_rollout
from benchmarks.observers import cpu_seconds
from benchmarks.paced_runs import paced_mesh, run_paced
from benchmarks.spread import median_spread
from tests.ros2_sdk import sdk_session

__all__ = ["main"]

ROBOT = "benchros"
#: what the subscriber counts: (topic under the namespace, ROS 2 type)
COUNTED = (
    ("joint_states", "sensor_msgs/msg/JointState"),
    ("camera/image_raw", "sensor_msgs/msg/Image"),
)


class WithNode:
    """`archery ros2` on the mesh and a zenoh-ros2-sdk subscriber counting what it receives."""

    def __init__(self, endpoint: str, net: Any) -> None:
        self.proc = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "archery.apps.cli",
                "ros2",
                "--connect",
                endpoint,
                "--robot",
                ROBOT,
            ],
            stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL,
            text=True,
        )
        assert self.proc.stdout is not None
        line = self.proc.stdout.readline()
        if not line.startswith(READY):
            self.proc.kill()
            raise RuntimeError(f"the node did not start: {line!r}")
        self.sdk = sdk_session(net)
        host, port = endpoint.split("/", 1)[1].rsplit(":", 1)
        self.counts = dict.fromkeys((topic for topic, _ in COUNTED), 0)
        self._lock = threading.Lock()
        self.subs = []
        for topic, ros_type in COUNTED:

            def count(_: Any, topic: str = topic) -> None:
                with self._lock:
                    self.counts[topic] += 1

            definition = typestore.messages().generate_msgdef(ros_type, ros_version=2)[0]
            subscriber = ROS2Subscriber(
                f"/{ROBOT}/{topic}", ros_type, count, msg_definition=definition,
                type_hash=typestore.type_hash(ros_type), domain_id=0, router_ip=host,
                router_port=int(port),
            )  # fmt: skip
            self.subs.append(subscriber)
        self.started = time.monotonic()

    def received(self) -> tuple[dict[str, int], float]:
        """{topic: messages received} and the seconds since the subscription began."""
        with self._lock:
            return dict(self.counts), time.monotonic() - self.started

    def close(self) -> None:
        for sub in self.subs:
            sub.close()
        self.sdk.session.close()
        ZenohSession._instance = None
        self.proc.send_signal(signal.SIGINT)
        self.proc.communicate(timeout=60)


def _published(node: Node) -> dict[str, int]:
    """Joint states (all parts) and camera frames published so far (the publishers' counts)."""
    counts = stream_counts(describe_all(node.session, node.keys, timeout=5))
    return {
        "joint_states": sum(counts.get(node.keys.state(part), 0) for part in PARTS),
        "camera/image_raw": counts.get(node.keys.cam_frames(), 0),
    }


def _one_rtf(rtf: float, repeats: int, rollouts: int, tmp: Path) -> dict[str, Any]:
    rows: list[dict[str, Any]] = []
    with paced_mesh(tmp, ROBOT, rtf) as paced:
        launcher, node, feed, mesh = paced.launcher, paced.node, paced.feed, paced.pids
        for i in range(repeats):
            row: dict[str, Any] = {}
            for condition in ("none", "node") if i % 2 == 0 else ("node", "none"):
                extra = WithNode(launcher.endpoint, launcher.net) if condition == "node" else None
                try:
                    pids = dict(mesh) | ({"node": extra.proc.pid} if extra else {})
                    sent0, cpu0, t0 = _published(node), cpu_seconds(pids), time.monotonic()
                    got0 = extra.received()[0] if extra else {}
                    per_rollout, journal = _per_rollout(node, feed, i, rollouts)
                    wall = time.monotonic() - t0
                    cpu1, sent1 = cpu_seconds(pids), _published(node)
                    got1 = extra.received()[0] if extra else {}
                finally:
                    if extra is not None:
                        extra.close()
                row[condition] = {
                    "per_rollout": per_rollout,
                    "rollouts": _rollouts(journal),
                    "sent": {k: (sent1[k] - sent0[k]) / wall for k in sent1},
                }
                if extra is not None:
                    row[condition]["got"] = {k: (got1[k] - got0[k]) / wall for k in got1}
                    row[condition]["cpu"] = (cpu1["node"] - cpu0["node"]) / rollouts
                    row[condition]["core"] = (cpu1["node"] - cpu0["node"]) / wall
            ratio = row["node"]["per_rollout"] / row["none"]["per_rollout"]
            same = row["node"]["rollouts"] == row["none"]["rollouts"]
            got, sent = row["node"]["got"], row["node"]["sent"]
            print(
                f"  rtf {rtf:g} repeat {i}: ×{ratio:.3f} wall per rollout, rollouts "
                f"{'identical' if same else 'DIFFER'}, joint states {got['joint_states']:.0f}/"
                f"{sent['joint_states']:.0f} per s, frames {got['camera/image_raw']:.1f}/"
                f"{sent['camera/image_raw']:.1f} per s",
                flush=True,
            )
            rows.append(row)
    return {"rtf": rtf, "rows": rows}


def _report(result: dict[str, Any], rollouts: int) -> None:
    rows, rtf = result["rows"], result["rtf"]
    ratios = [r["node"]["per_rollout"] / r["none"]["per_rollout"] for r in rows]
    same = sum(r["node"]["rollouts"] == r["none"]["rollouts"] for r in rows)
    print(f"rtf {rtf:g} ({len(rows)} interleaved repeats of {rollouts}-rollout ARCHER sessions):")
    print(f"  rollouts identical with the node and without (θ and r): {same}/{len(rows)}")
    none_ms = [r["none"]["per_rollout"] * 1e3 for r in rows]
    node_ms = [r["node"]["per_rollout"] * 1e3 for r in rows]
    print(
        f"  wall ms per rollout: without {median_spread(none_ms, '.0f')}, with "
        f"{median_spread(node_ms, '.0f')}; ratio per repeat ×{median_spread(ratios, '.3f')}"
    )
    cpu = [r["node"]["cpu"] * 1e3 for r in rows]
    core = [r["node"]["core"] for r in rows]
    print(
        f"  the node: {median_spread(cpu, '.1f')} ms CPU per rollout, "
        f"{median_spread(core, '.3f')} of a core"
    )
    for topic, _ in COUNTED:
        got = [r["node"]["got"][topic] for r in rows]
        sent = [r["node"]["sent"][topic] for r in rows]
        print(
            f"  {topic}: {median_spread(got, '.1f')}/s received against "
            f"{median_spread(sent, '.1f')}/s published"
        )


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark; exit status 0."""
    return run_paced("bench_ros2", __doc__, argv, _one_rtf, _report)


if __name__ == "__main__":
    sys.exit(main())
