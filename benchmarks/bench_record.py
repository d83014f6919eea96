"""Benchmark of `archery record` and `archery replay`.

Run `python -m benchmarks.bench_record [--repeats 5] [--rollouts 8]`. It prints:

* the recorder's cost: per-rollout wall time of learning sessions on one mesh (`archery up`'s
  Launcher, robot at rtf 0) with a recorder of `ROBOT/**` running against without, the two
  interleaved `--repeats` times; median of each pair's ratio and its spread (min, max);
* the recorder's throughput: 1280×720 rgb8 frames published at rising rates for `--seconds`
  s each, frames written against frames published (a drop is counted, never guessed); the
  highest rate with none lost;
* replay fidelity: one session's recording replayed (camera frames, `--serve-grab`) into a
  fresh detector loaded with the mesh detector's colour model; max |Δr| over every recorded
  detection.
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from protocol.messages import Detection, Image, Rollout
from protocol.netflags import NetConfig
from protocol.node import Node
from protocol.recording import open_recording
from protocol.router import free_tcp_endpoint
from services.cli import spawn
from services.launcher import SERVICES, Launcher
from services.learner.journal import read_records
from services.learner.tools.learn import follow

__all__ = ["main", "mesh_launcher", "remeasure"]


def _stop(proc: subprocess.Popen[str]) -> str:
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=120)
    if proc.returncode != 0:
        raise RuntimeError(f"exit {proc.returncode}: {err}")
    return out


def _per_rollout(node: Node, rollouts: Any, seed: int, budget: int) -> float:
    request = {"algo": "archer", "seed": seed, "rollouts": budget}
    session = node.call(node.keys.learner_rpc(), "start", request, timeout=60)["session"]
    final = follow(node, session, rollouts, lambda m: None, poll=0.2)
    done = [r for r in read_records(Path(final["journal"]))[0] if r["record"] == "done"]
    return statistics.median(b["t"] - a["t"] for a, b in itertools.pairwise(done))


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
            with contextlib.suppress(subprocess.TimeoutExpired):
                recorder.wait(10)
        if recorder.returncode is None:
            _stop(recorder)
        written = open_recording(path).message_count or 0
        results.append((rate, sent, written))
        print(f"  {rate:4.0f} frames/s offered: {sent} published, {written} written", flush=True)
    return results


def remeasure(node: Node, hits: list[Detection]) -> float:
    """Measure each recorded detection's frame again (`after_sim_time` its sim time) through
    the detector of `node`'s robot; the largest |Δr| (m) against the recorded r."""
    worst = 0.0
    for hit in hits:
        again = node.call(
            node.keys.detector_rpc(),
            "measure",
            {"after_sim_time": hit.sim_time, "timeout": 60},
            timeout=90,
        )
        if again["status"] != "ok" or again["sim_time"] != hit.sim_time:
            raise AssertionError(f"the replayed frame of sim time {hit.sim_time}: {again}")
        worst = max(worst, float(np.max(np.abs(np.subtract(again["r_m"], hit.r_m)))))
    return worst


def _unambiguous(path: Path) -> tuple[list[Detection], int]:
    """The recorded detections whose frame a replayed `grab {after_sim_time}` finds again, and
    how many there were in all. Every rollout resets the simulated clock, so a grab for sim
    time t is answered with the first replayed frame at or after t, which is the measured frame
    only when no frame played before it (an earlier rollout's) already reached t."""
    frames = [
        m.sim_time
        for k, m, _ in open_recording(path).messages()
        if k.endswith("cam/target:o") and m.sim_time is not None
    ]
    hits = [
        m
        for k, m, _ in open_recording(path).messages()
        if k.endswith("detector/hit:o") and m.r_m is not None
    ]
    found = [h for h in hits if next((t for t in frames if t >= h.sim_time), None) == h.sim_time]
    return found, len(hits)


def _fidelity(endpoint: str, path: Path, model: Path) -> tuple[float, int, int]:
    hits, recorded = _unambiguous(path)
    robot = "benchreplay"
    detector = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "services.cli",
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
    worst = 0.0
    try:
        with Node(None, NetConfig(connect=(endpoint,), robot=robot)) as node:
            node.wait_alive(["detector"], 60)
            worst = remeasure(node, hits)
    finally:
        _stop(replay)
        detector.terminate()
        detector.wait(30)
    return worst, len(hits), recorded


def mesh_launcher(tmp: Path, robot: str, model: Path) -> Launcher:
    """A whole mesh on a free port: logs and the learner's runs under `tmp`, the detector's
    colour model in `model`."""
    return Launcher(
        free_tcp_endpoint(),
        robot,
        tmp / "logs",
        {"learner": ["--runs", str(tmp / "runs")], "detector": ["--model", str(model)]},
    )


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark; exit status 0."""
    os.environ.setdefault("MUJOCO_GL", "egl")
    parser = argparse.ArgumentParser(prog="python -m benchmarks.bench_record", description=__doc__)
    parser.add_argument("--repeats", type=int, default=5, help="pairs of sessions (≥ 5)")
    parser.add_argument("--rollouts", type=int, default=8, help="rollouts per session")
    parser.add_argument("--seconds", type=float, default=5.0, help="per offered frame rate")
    args = parser.parse_args(argv)
    tmp = Path(tempfile.mkdtemp(prefix="bench-record-"))
    model = tmp / "model.json"
    launcher = mesh_launcher(tmp, "bench", model)
    launcher.up(180)
    endpoint = launcher.endpoint
    ratios, plain, recorded = [], [], []
    last = tmp / "session.mcap"
    try:
        with Node(None, launcher.net) as node:
            rollouts = node.subscribe(node.keys.learner_rollouts(), Rollout, mode="fifo")
            node.wait_alive(SERVICES, timeout=30)
            for i in range(args.repeats):
                order = (False, True) if i % 2 == 0 else (True, False)
                pair = {}
                for with_recorder in order:
                    recorder = None
                    if with_recorder:
                        recorder = spawn(
                            "record",
                            "--out",
                            str(last),
                            "--connect",
                            endpoint,
                            "--robot",
                            "bench",
                            ready="archery record: recording",
                        )
                    pair[with_recorder] = _per_rollout(node, rollouts, i, args.rollouts)
                    if recorder is not None:
                        said = _stop(recorder).strip().splitlines()
                        print(f"  {said[-1] if said else ''}", flush=True)
                ratios.append(pair[True] / pair[False])
                plain.append(pair[False])
                recorded.append(pair[True])
                print(
                    f"repeat {i}: {pair[False] * 1e3:.0f} ms/rollout without, "
                    f"{pair[True] * 1e3:.0f} ms with the recorder (×{ratios[-1]:.3f})",
                    flush=True,
                )
        print("recorder throughput (1280×720 rgb8, zstd):", flush=True)
        fps = _throughput(endpoint, tmp, args.seconds)
        worst, n, n_hits = _fidelity(endpoint, last, model)
    finally:
        launcher.stop_all()
    kept = [rate for rate, sent, written in fps if written == sent]
    size = last.stat().st_size / 1e6
    print("\n--- bench_record")
    print(
        "per-rollout wall time, with/without the recorder: median ratio "
        f"×{statistics.median(ratios):.3f}"
        f" (spread ×{min(ratios):.3f}–×{max(ratios):.3f}; {args.repeats} interleaved pairs of "
        f"{args.rollouts}-rollout sessions; medians {statistics.median(plain) * 1e3:.0f} ms "
        f"without, {statistics.median(recorded) * 1e3:.0f} ms with)"
    )
    print(f"last session's recording: {size:.1f} MB")
    for rate, sent, written in fps:
        print(
            f"  offered {rate:g} frames/s: {sent} published, {written} written, "
            f"{sent - written} lost"
        )
    print(f"highest 1280×720 rate with no frame lost: {max(kept) if kept else 0:g} frames/s")
    print(
        f"replay fidelity: max |Δr| = {worst * 1e3:.4f} mm over the {n} of {n_hits} recorded "
        "detections whose frame a replayed grab finds by sim time"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
