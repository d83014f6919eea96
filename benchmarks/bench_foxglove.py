"""Benchmark of `archery foxglove`: what one client watching every channel costs a session.

Run `python -m benchmarks.bench_foxglove [--repeats 5] [--rollouts-rtf1 8] [--rollouts-rtf0 30]`.
For each real-time factor (1: the wall-clock pace of a watched session; 0: as fast as possible)
a whole mesh (`archery up`'s Launcher) runs ARCHER sessions of the same seed per repeat under two
conditions, interleaved (the order alternating): nothing watching, and `archery foxglove` with
Foxglove's own client (tests/foxglove_client, `--watch`) subscribed to every channel. It prints,
per rtf: the rollouts of the two sessions of a repeat compared (θ and r of every rollout), and
of two unwatched sessions of one seed (the control: whether the pace itself repeats); the
wall time per rollout (median of a session's rollouts) and its ratio watched/none per repeat
(goal ≤ 1.05× at rtf 1); the bridge's CPU per rollout and its share of a core; and the frames the
client received per second against the camera's published rate over the same session.

`--smoke`: 1 repeat of 2-rollout sessions at rtf 0 only, in a temporary directory.
"""

from __future__ import annotations

import json
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from archery.apps.port_rates import stream_counts
from archery.mesh.instances import describe_all
from archery.mesh.node import Node
from archery.protocol.journal_records import DoneRecord
from archery.services.learner.journal import read_records
from benchmarks.bench_record import _per_rollout
from benchmarks.observers import cpu_seconds
from benchmarks.paced_runs import paced_mesh, run_paced
from benchmarks.spread import median_spread

__all__ = ["main"]

CLIENT = Path(__file__).resolve().parent.parent / "tests" / "foxglove_client"


class Watched:
    """`archery foxglove` on a free port and Foxglove's client watching every channel."""

    def __init__(self, endpoint: str, robot: str) -> None:
        if not (CLIENT / "node_modules" / "@foxglove" / "ws-protocol").is_dir():
            subprocess.run(["npm", "ci", "--no-audit", "--no-fund"], cwd=CLIENT, check=True)
        self.bridge = subprocess.Popen(
            [sys.executable, "-m", "archery.apps.cli", "foxglove", "--connect", endpoint, "--robot",
             robot, "--port", "0"],
            stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL,
            text=True,
        )  # fmt: skip
        assert self.bridge.stdout is not None
        line = self.bridge.stdout.readline()
        if not line.startswith("archery foxglove: serving"):
            self.bridge.kill()
            raise RuntimeError(f"the bridge did not start: {line!r}")
        url = line.split(" on ", 1)[1].split()[0]
        self.client = subprocess.Popen(
            ["node", str(CLIENT / "client.mjs"), url, "--watch"],
            stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL,
            text=True,
        )
        assert self.client.stdout is not None
        first = json.loads(self.client.stdout.readline())
        if "watching" not in first:
            raise RuntimeError(f"the client did not subscribe: {first}")

    def counts(self) -> dict[str, Any]:
        """Stop the client; what it received: {"counts": {topic: [messages, bytes]}, "seconds"}."""
        self.client.send_signal(signal.SIGTERM)
        out, _ = self.client.communicate(timeout=60)
        lines = [json.loads(line) for line in out.splitlines() if line.strip()]
        return next(line for line in lines if "counts" in line)

    def close(self) -> None:
        if self.client.poll() is None:
            self.client.kill()
            self.client.wait()
        self.bridge.send_signal(signal.SIGINT)
        self.bridge.communicate(timeout=60)


def _rollouts(journal: Path) -> list[tuple[list[float], list[float]]]:
    """(θ, r) of each done rollout of a journal (m)."""
    done = [r for r in read_records(journal)[0] if isinstance(r, DoneRecord)]
    return [(list(r.theta), list(r.r_m)) for r in done]


def _frames_published(node: Node) -> int:
    """The camera's frames published so far (its publisher's own count)."""
    counts = stream_counts(describe_all(node.session, node.keys, timeout=5))
    return counts.get(node.keys.cam_frames(), 0)


def _one_rtf(rtf: float, repeats: int, rollouts: int, tmp: Path) -> dict[str, Any]:
    rows: list[dict[str, Any]] = []
    with paced_mesh(tmp, "benchfox", rtf) as paced:
        launcher, node, feed, mesh = paced.launcher, paced.node, paced.feed, paced.pids
        # the control: two unwatched sessions of one seed, whether this pace repeats itself
        control = [_rollouts(_per_rollout(node, feed, 999, rollouts)[1]) for _ in range(2)]
        print(
            f"  rtf {rtf:g} control: two unwatched sessions of one seed "
            f"{'identical' if control[0] == control[1] else 'DIFFER'}",
            flush=True,
        )
        for i in range(repeats):
            row: dict[str, Any] = {"repeat": i}
            order = ("none", "watched") if i % 2 == 0 else ("watched", "none")
            for condition in order:
                watched = Watched(launcher.endpoint, "benchfox") if condition == "watched" else None
                try:
                    pids = dict(mesh)
                    if watched is not None:
                        pids["bridge"] = watched.bridge.pid
                    frames0, cpu0, t0 = (
                        _frames_published(node),
                        cpu_seconds(pids),
                        time.monotonic(),
                    )
                    per_rollout, journal = _per_rollout(node, feed, i, rollouts)
                    wall = time.monotonic() - t0
                    cpu1, frames1 = cpu_seconds(pids), _frames_published(node)
                    got = watched.counts() if watched is not None else None
                finally:
                    if watched is not None:
                        watched.close()
                row[condition] = {
                    "per_rollout": per_rollout,
                    "rollouts": _rollouts(journal),
                    "cpu": {n: (cpu1[n] - cpu0[n]) / rollouts for n in pids},
                    "wall": wall,
                    "camera_fps": (frames1 - frames0) / wall,
                }
                if got is not None:
                    images = got["counts"].get("/camera/image", [0, 0])[0]
                    row[condition]["client_fps"] = images / got["seconds"]
                    row[condition]["bridge_core"] = (cpu1["bridge"] - cpu0["bridge"]) / wall
                    row[condition]["counts"] = got["counts"]
            ratio = row["watched"]["per_rollout"] / row["none"]["per_rollout"]
            same = row["watched"]["rollouts"] == row["none"]["rollouts"]
            print(
                f"  rtf {rtf:g} repeat {i}: ×{ratio:.3f} wall per rollout, rollouts "
                f"{'identical' if same else 'DIFFER'}, client "
                f"{row['watched']['client_fps']:.1f} frames/s (camera "
                f"{row['watched']['camera_fps']:.1f})",
                flush=True,
            )
            rows.append(row)
    return {"rtf": rtf, "rows": rows, "control": control[0] == control[1]}


def _report(result: dict[str, Any], rollouts: int) -> None:
    rows, rtf = result["rows"], result["rtf"]
    ratios = [r["watched"]["per_rollout"] / r["none"]["per_rollout"] for r in rows]
    same = sum(r["watched"]["rollouts"] == r["none"]["rollouts"] for r in rows)
    none_ms = [r["none"]["per_rollout"] * 1e3 for r in rows]
    watched_ms = [r["watched"]["per_rollout"] * 1e3 for r in rows]
    bridge_ms = [r["watched"]["cpu"]["bridge"] * 1e3 for r in rows]
    core = [r["watched"]["bridge_core"] for r in rows]
    client = [r["watched"]["client_fps"] for r in rows]
    camera = [r["watched"]["camera_fps"] for r in rows]
    print(f"rtf {rtf:g} ({len(rows)} interleaved repeats of {rollouts}-rollout ARCHER sessions):")
    print(f"  rollouts identical watched and not (θ and r, every rollout): {same}/{len(rows)}")
    control = "identical" if result["control"] else "NOT identical"
    print(f"  control, two unwatched sessions of one seed: {control}")
    print(
        f"  wall ms per rollout: none {median_spread(none_ms, '.0f')}, watched "
        f"{median_spread(watched_ms, '.0f')}; ratio per repeat ×{median_spread(ratios, '.3f')}"
    )
    print(
        f"  the bridge: {median_spread(bridge_ms, '.1f')} ms CPU per rollout, "
        f"{median_spread(core, '.3f')} of a core"
    )
    print(
        f"  frames to the client {median_spread(client, '.1f')}/s against the camera's "
        f"{median_spread(camera, '.1f')}/s"
    )


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark; exit status 0."""
    if shutil.which("node") is None:
        print(
            "bench_foxglove: Node is not installed (Foxglove's client runs on it)", file=sys.stderr
        )
        return 1
    return run_paced("bench_foxglove", __doc__, argv, _one_rtf, _report)


if __name__ == "__main__":
    sys.exit(main())
