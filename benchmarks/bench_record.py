"""Benchmark of `archery record`, `archery dashboard` and `archery replay`.

Run `python -m benchmarks.bench_record [--repeats 5] [--rollouts 30] [--rtf 0]`. It prints:

* the observers' cost: per-rollout wall time of learning sessions on one mesh (`archery up`'s
  Launcher, robot at rtf 0 by default, or 1: the wall-clock pace of a watched session) under
  four conditions, interleaved in a rotating order `--repeats` times (ARCHER sessions that do not
  stop at the hit: every session runs its `--rollouts`, and the median of their rollouts' wall
  times is the session's figure): nothing watching; a
  recorder of `ROBOT/**`; the dashboard with a client polling it as its page does (`/api/state`
  every 0.5 s, `/api/frame.png` whenever the frame's version changes); both. Per condition, the
  median over repeats of its ratio to the same repeat's unwatched session, and the spread (min,
  max);
  Also each session's CPU time per rollout, per process (the mesh's and the observers'; the
  polling client stands for the browser and is not counted): a figure that the load of other
  jobs on a shared machine disturbs far less than wall time;
* the recorder's throughput: 1280×720 rgb8 frames published at rising rates for `--seconds`
  s each, frames written against frames published (a drop is counted, never guessed); the
  highest rate with none lost;
* replay fidelity: the last recorded session replayed (camera frames, `--serve-grab`) into a
  fresh detector loaded with the mesh detector's colour model; every detection measured again
  (its frame found by sim time and stamp) and compared with the r the learner journaled; max
  |Δr|.

`--smoke`: every part at its smallest budget, its figures noise: 1 repeat (each condition
once) of 2-rollout sessions on the same whole mesh, 0.5 s per offered frame rate, and the
replay of the last recorded session; in a temporary directory, removed after.
"""

from __future__ import annotations

import argparse
import itertools
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from archery.apps.learn.follow import follow
from archery.apps.topics.recording import open_recording
from archery.apps.up.launch_config import SERVICES
from archery.apps.up.launcher import Launcher
from archery.mesh.netflags import NetConfig
from archery.mesh.node import Node
from archery.mesh.router import free_tcp_endpoint
from archery.protocol.journal_records import DoneRecord
from archery.protocol.messages import Detection, Image, Rollout
from archery.services.learner.journal import read_records
from benchmarks.observers import CONDITIONS, Observers, cpu_seconds, stop
from tests.rpc import rpc_call
from tests.spawn import spawn

__all__ = ["main", "mesh_launcher", "remeasure"]


def _per_rollout(node: Node, rollouts: Any, seed: int, budget: int) -> tuple[float, Path]:
    """One session of `budget` rollouts (it goes on after a hit): its median wall time per
    rollout (s) and journal."""
    request = {"algo": "archer", "seed": seed, "rollouts": budget, "until_hit": False}
    session = rpc_call(node, node.keys.learner_rpc(), "start", request, timeout=60)["session"]
    final = follow(node, session, rollouts, lambda m: None, poll=0.2)
    journal = Path(final["journal"])
    done = [r for r in read_records(journal)[0] if isinstance(r, DoneRecord)]
    return statistics.median(b.t - a.t for a, b in itertools.pairwise(done)), journal


def _frame(width: int = 1280, height: int = 720) -> np.ndarray:
    """A render-like frame: smooth gradients and a disc (compresses as a render does)."""
    y, x = np.mgrid[0:height, 0:width]
    rgb = np.stack([x * 255 // width, y * 255 // height, (x + y) * 255 // (width + height)], -1)
    rgb[(x - width // 2) ** 2 + (y - height // 2) ** 2 < (height // 4) ** 2] = (220, 30, 30)
    return rgb.astype(np.uint8)


def _throughput(endpoint: str, tmp: Path, seconds: float) -> list[tuple[float, int, int]]:
    net = NetConfig(connect=(endpoint,), robot="benchfps")
    pixels = _frame()
    results = []
    for rate in (10.0, 20.0, 30.0, 60.0):
        frames = int(rate * seconds)
        path = tmp / f"fps{rate:g}.mcap"
        recorder = spawn(
            "record",
            "--out",
            str(path),
            "--connect",
            endpoint,
            "--robot",
            net.robot,
            "--count",
            str(frames),
            "--no-transforms",  # the frames alone: no scene record counted among them
            ready="archery record: recording",
        )
        sent = 0
        with Node(None, net) as node:
            pub = node.publisher(node.keys.cam_frames(), Image)
            pub.wait_matched(10)
            start = time.monotonic()
            while sent < frames:
                pub.put(Image.from_numpy(pixels, frame=sent, sim_time=sent / rate))
                sent += 1
                time.sleep(max(0.0, start + sent / rate - time.monotonic()))
            # it ends by itself once it has every frame; late frames still count
            try:
                said, _ = recorder.communicate(timeout=10)
            except subprocess.TimeoutExpired:
                said = stop(recorder)
        written = open_recording(path).message_count or 0
        results.append((rate, sent, written))
        print(f"  {rate:4.0f} frames/s offered: {sent} published, {written} written", flush=True)
        print(f"    {said.strip().splitlines()[-1] if said.strip() else ''}", flush=True)
    return results


def remeasure(node: Node, hits: list[Detection]) -> tuple[float, int, int]:
    """Measure each recorded detection's frame again (`after_sim_time` its sim time,
    `after_stamp` its frame's stamp: every rollout resets the simulated clock, the stamp tells
    the rollouts apart) through the detector of `node`'s robot; the largest |Δr| (m) against
    the recorded r, and how many were measured on their very frame.

    The camera publishes its frames latest-wins, so the frame a detection measured (sent to the
    detector as a `grab` reply) may be missing from the recording on a loaded machine; then the
    next recorded frame of the same rollout and the same sim time stands for it: the camera
    sends the same world state's render again, re-stamped. When no frame of that world state
    was recorded (the recorder counts such a gap as missing by sequence number), the replay
    answers with a later world state's frame: that detection is counted as not recorded and
    left out of the largest |Δr|.

    Returns:
        The largest |Δr| (m), how many were measured on their very frame, how many had no
        recorded frame of their world state.

    Raises:
        AssertionError: a measurement that failed, or no detection's world state recorded.
    """
    worst, exact, absent = 0.0, 0, 0
    for hit in hits:
        again = rpc_call(
            node,
            node.keys.detector_rpc(),
            "measure",
            {"after_sim_time": hit.sim_time, "after_stamp": hit.frame_stamp, "timeout": 60},
            timeout=90,
        )
        if again["status"] != "ok":
            raise AssertionError(f"the replayed frame of sim time {hit.sim_time}: {again}")
        if again["sim_time"] != hit.sim_time:
            absent += 1
            continue
        exact += again["frame_stamp"] == hit.frame_stamp
        worst = max(worst, float(np.max(np.abs(np.subtract(again["r_m"], hit.r_m)))))
    if hits and absent == len(hits):
        raise AssertionError(f"none of {len(hits)} detections' world states was recorded")
    return worst, exact, absent


def _detections(path: Path) -> list[Detection]:
    """The recorded detections that measured an r."""
    return [
        m
        for k, m, _ in open_recording(path).messages()
        if isinstance(m, Detection) and k.endswith("detector/hit:o") and m.r_m is not None
    ]


def _fidelity(
    endpoint: str, path: Path, model: Path, journal: Path
) -> tuple[float, int, int, int, int]:
    """Replay `path` into a fresh detector and measure every recorded detection again: the
    largest |Δr| (m) against the r the learner journaled, the recorded detections, the
    rollouts journaled with an r, how many of those were measured on their very frame and
    how many had no recorded frame of their world state.

    Raises:
        AssertionError: a journaled r that no recorded detection holds, or a frame not found.
    """
    hits = _detections(path)
    journaled = [r.r_m for r in read_records(journal)[0] if isinstance(r, DoneRecord)]
    by_r = {tuple(h.r_m or ()): h for h in hits}
    missing = [r for r in journaled if tuple(r) not in by_r]
    if missing:
        raise AssertionError(f"journaled r without a recorded detection: {missing}")
    robot = "benchreplay"
    detector = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "archery.apps.cli",
            "detector",
            "--model",
            str(model),
            "--no-auto-calibrate",
            "--connect",
            endpoint,
            "--robot",
            robot,
        ],
        stdin=subprocess.DEVNULL,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    replay = spawn(
        "replay",
        str(path),
        "--keys",
        "bench/cam/target:o",
        "--serve-grab",
        "--rate",
        "4",
        "--robot",
        robot,
        "--connect",
        endpoint,
        ready="archery replay: serving grab",
    )
    try:
        with Node(None, NetConfig(connect=(endpoint,), robot=robot)) as node:
            node.wait_alive(["detector"], 60)
            worst, exact, absent = remeasure(node, [by_r[tuple(r)] for r in journaled])
    finally:
        stop(replay)
        detector.terminate()
        detector.wait(30)
    return worst, len(hits), len(journaled), exact, absent


def mesh_launcher(tmp: Path, robot: str, model: Path, rtf: float = 0.0) -> Launcher:
    """A whole mesh on a free port: logs and the learner's runs under `tmp`, the detector's
    colour model in `model`, the robot at real-time factor `rtf`."""
    return Launcher(
        free_tcp_endpoint(),
        robot,
        tmp / "logs",
        {
            "learner": ["--runs", str(tmp / "runs")],
            "detector": ["--model", str(model)],
            "robot": ["--rtf", f"{rtf:g}"],
        },
    )


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark; exit status 0."""
    os.environ.setdefault("MUJOCO_GL", "egl")
    parser = argparse.ArgumentParser(prog="python -m benchmarks.bench_record", description=__doc__)
    parser.add_argument("--repeats", type=int, default=5, help="pairs of sessions (≥ 5)")
    parser.add_argument("--rollouts", type=int, default=30, help="rollouts per session")
    parser.add_argument("--seconds", type=float, default=5.0, help="per offered frame rate")
    parser.add_argument(
        "--rtf",
        type=float,
        default=0.0,
        help="the robot's real-time factor: 0 = as fast as possible (default), 1 = wall-clock "
        "pace, as when a session is watched",
    )
    parser.add_argument(
        "--smoke",
        action="store_true",
        help="1 repeat of 2-rollout sessions, 0.5 s per rate, in a temporary directory",
    )
    args = parser.parse_args(argv)
    if args.smoke:
        args.repeats, args.rollouts, args.seconds = 1, 2, 0.5
        with tempfile.TemporaryDirectory(prefix="bench-record-") as tmp:
            return _run(args, Path(tmp))
    return _run(args, Path(tempfile.mkdtemp(prefix="bench-record-")))


def _run(args: argparse.Namespace, tmp: Path) -> int:
    """The benchmark at the budgets of `args`, its files under `tmp`; the report printed."""
    model = tmp / "model.json"
    launcher = mesh_launcher(tmp, "bench", model, args.rtf)
    launcher.up(180)
    endpoint = launcher.endpoint
    times: dict[str, list[float]] = {name: [] for name, *_ in CONDITIONS}
    cpu: dict[str, list[dict[str, float]]] = {name: [] for name, *_ in CONDITIONS}
    mesh = {name: c.proc.pid for name, c in launcher.children.items() if c.proc is not None}
    last, journal = tmp / "session.mcap", tmp / "none"
    try:
        with Node(None, launcher.net) as node:
            rollouts = node.subscribe(node.keys.learner_rollouts(), Rollout, mode="fifo")
            node.wait_alive(SERVICES, timeout=30)
            _per_rollout(node, rollouts, 1000, args.rollouts)  # warm-up (calibration): untimed
            for i in range(args.repeats):
                k = i % len(CONDITIONS)
                for name, recorder, dashboard, spinner in CONDITIONS[k:] + CONDITIONS[:k]:
                    with Observers(
                        endpoint,
                        "bench",
                        last,
                        recorder=recorder,
                        dashboard=dashboard,
                        spinner=spinner,
                    ) as observers:
                        pids = mesh | observers.pids()
                        before = cpu_seconds(pids)
                        per_rollout, session_journal = _per_rollout(
                            node, rollouts, i, args.rollouts
                        )
                        after = cpu_seconds(pids)
                    cpu[name].append({n: (after[n] - before[n]) / args.rollouts for n in pids})
                    if recorder:
                        journal = session_journal
                    times[name].append(per_rollout)
                    said = "; ".join(observers.said)
                    print(f"  repeat {i} {name}: {per_rollout * 1e3:.0f} ms/rollout {said}")
                base = times["none"][-1]
                print(
                    f"repeat {i}: "
                    + ", ".join(f"{n} ×{times[n][-1] / base:.3f}" for n, *_ in CONDITIONS[1:]),
                    flush=True,
                )
        print("recorder throughput (1280×720 rgb8, lz4):", flush=True)
        fps = _throughput(endpoint, tmp, args.seconds)
        worst, n_hits, n_journaled, exact, absent = _fidelity(endpoint, last, model, journal)
    finally:
        launcher.stop_all()
    kept = [rate for rate, sent, written in fps if written == sent]
    size = last.stat().st_size / 1e6
    print("\n--- bench_record")
    print(
        f"per-rollout wall time against no observer (robot at rtf {args.rtf:g}; {args.repeats} "
        f"interleaved repeats of {args.rollouts}-rollout sessions; median ms without: "
        f"{statistics.median(times['none']) * 1e3:.0f})"
    )
    for name, *_ in CONDITIONS[1:]:
        ratios = [a / b for a, b in zip(times[name], times["none"], strict=True)]
        print(
            f"  {name}: median ratio ×{statistics.median(ratios):.3f} "
            f"(spread ×{min(ratios):.3f}–×{max(ratios):.3f}; median "
            f"{statistics.median(times[name]) * 1e3:.0f} ms)"
        )
    print("CPU time per rollout (ms of CPU; median over repeats) of the mesh and the observers:")
    for name, *_ in CONDITIONS:
        parts = {n: statistics.median(run.get(n, 0.0) for run in cpu[name]) for n in cpu[name][0]}
        total = statistics.median(sum(run.values()) for run in cpu[name])
        shown = ", ".join(f"{n} {v * 1e3:.1f}" for n, v in parts.items())
        print(f"  {name}: total {total * 1e3:.1f} ({shown})")
    print(f"last recorded session: {size:.1f} MB")
    for rate, sent, written in fps:
        print(
            f"  offered {rate:g} frames/s: {sent} published, {written} written, "
            f"{sent - written} lost"
        )
    print(f"highest 1280×720 rate with no frame lost: {max(kept) if kept else 0:g} frames/s")
    print(
        f"replay fidelity: max |Δr| = {worst * 1e3:.4f} mm over {n_journaled - absent} of "
        f"{n_journaled} journaled r of the last recorded session ({n_hits} recorded "
        f"detections; {exact} measured again on their very frame, the others on the next "
        f"recorded frame of the same world state; {absent} whose world state has no recorded "
        f"frame, lost in transit)"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
