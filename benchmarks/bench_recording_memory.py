"""Peak memory of `archery info` and `archery replay` reading a large recording, against a small
one: the reader holds one chunk at a time, so its peak RSS must not follow the file's size.

A recording of ~`--gib` GiB is synthesised in a temporary folder with the project's own
`Recorder` (1280 x 720 rgb8 camera frames of noise, so lz4 barely shrinks them and the file is
as big as what it decompresses to), with a small one (`--small-frames` frames) as the baseline.
Each repeat runs, in a rotating order, on both files:

* `archery info FILE` (the complete file: its summary only);
* `archery info CUT` (a copy cut 1 MiB short of its end: no summary, so every chunk is read
  and decompressed, one at a time);
* `archery replay FILE --keys NONE/**` to a router on loopback: every record is read,
  decompressed and decoded (frames included), and the key filter, which matches nothing,
  publishes none of them (so the figure is the reader's, not Zenoh's queues).

Each run's peak RSS is the command's own (`tests.peak_rss`: `ru_maxrss` from `os.wait4`, the
command forked from a small launcher, as Linux carries a parent's peak into its children).
Per command it prints the large file's peak and the small file's, each median [min, max] over
the repeats, their ratio (per repeat), and the large peak as a share of the large file's size.

    python -m benchmarks.bench_recording_memory [--gib 1] [--repeats 5]

`--smoke`: a 20-frame "large" file of 320 x 240 frames, 1 repeat, in a temporary folder
removed after (seconds; its figures are noise).
"""

from __future__ import annotations

import argparse
import os
import platform
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from archery.apps.topics.recording import Recorder
from archery.mesh.router import free_tcp_endpoint, spawn_router
from archery.protocol.codec import encode
from archery.protocol.messages import Image
from benchmarks.machine import cpu_model
from benchmarks.spread import median_spread
from tests.peak_rss import run_with_peak

__all__ = ["main"]

ROBOT = "bench"
KEY = f"{ROBOT}/cam/target:o"


def _synthesise(path: Path, frames: int, width: int, height: int) -> None:
    """A recording of `frames` rgb8 frames of noise (one new frame in 16, the others rolled
    copies of it, so making them stays cheap; lz4 finds no match within a frame either way)."""
    rng = np.random.default_rng(1)
    recorder = Recorder(path, ROBOT, [f"{ROBOT}/**"], writer_nice=0)
    start = time.time_ns()
    pixels = rng.integers(0, 256, (height, width, 3), np.uint8)
    for i in range(frames):
        if i % 16 == 0:
            pixels = rng.integers(0, 256, (height, width, 3), np.uint8)
        frame = np.roll(pixels, i, axis=1)
        image = Image.from_numpy(frame, frame=i, sim_time=i / 30, seq=i + 1, stamp=start / 1e9)
        recorder.put(KEY, encode(image), start + i * 33_333_333)
        while recorder.pending() > 8:  # the writer keeps up; memory stays at a few frames
            time.sleep(0.005)
    stats = recorder.close()
    assert stats.total == frames and not stats.overflow, stats


def _cut_copy(path: Path, cut: Path) -> None:
    """A copy of `path` without its last MiB (its summary and footer): a file cut short."""
    shutil.copyfile(path, cut)
    os.truncate(cut, max(len(b"\x89MCAP0\r\n"), path.stat().st_size - (1 << 20)))


def _peak_mib(args: list[str], expect: int) -> tuple[float, float]:
    """(peak RSS in MiB, wall s) of `archery ARGS` in a child that must end with `expect`."""
    start = time.perf_counter()
    done = run_with_peak(*args, timeout=1800.0)
    wall = time.perf_counter() - start
    if done.status != expect or "Traceback" in done.stderr:
        raise RuntimeError(f"archery {' '.join(args)} ended {done.status}: {done.stderr[-500:]}")
    return done.peak_mib, wall


def main(argv: list[str] | None = None) -> int:
    """Synthesise the recordings, run the commands interleaved and print the figures."""
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.bench_recording_memory", description=__doc__
    )
    parser.add_argument("--gib", type=float, default=1.0, help="the large file's size (GiB)")
    parser.add_argument("--small-frames", type=int, default=4, help="frames of the small file")
    parser.add_argument("--repeats", type=int, default=5, help="interleaved repeats (≥ 5)")
    parser.add_argument("--smoke", action="store_true", help="a tiny run: no figures")
    args = parser.parse_args(argv)
    width, height = (320, 240) if args.smoke else (1280, 720)
    frame_bytes = width * height * 3
    large_frames = 20 if args.smoke else max(1, round(args.gib * (1 << 30) / frame_bytes))
    if args.smoke:
        args.repeats, args.small_frames = 1, 2
    elif args.repeats < 5:
        parser.error("--repeats must be at least 5")
    endpoint = free_tcp_endpoint()
    router = spawn_router(endpoint)
    net = ["--connect", endpoint, "--robot", ROBOT]
    try:
        with tempfile.TemporaryDirectory(prefix="bench-recording-memory-") as tmp:
            folder = Path(tmp)
            files = {"large": folder / "large.mcap", "small": folder / "small.mcap"}
            t0 = time.perf_counter()
            _synthesise(files["large"], large_frames, width, height)
            _synthesise(files["small"], args.small_frames, width, height)
            cuts = {name: folder / f"{name}-cut.mcap" for name in files}
            for name, path in files.items():
                _cut_copy(path, cuts[name])
            made = time.perf_counter() - t0
            sizes = {name: path.stat().st_size for name, path in files.items()}
            commands = {
                "info (summary)": lambda f: ["info", str(files[f])],
                "info (cut: every chunk)": lambda f: ["info", str(cuts[f])],
                "replay (--keys NONE/**)": lambda f: [
                    "replay",
                    str(files[f]),
                    "--keys",
                    "none/**",
                    *net,
                ],
            }
            runs = [(command, f) for command in commands for f in files]
            peaks: dict[tuple[str, str], list[float]] = {run: [] for run in runs}
            walls: dict[tuple[str, str], list[float]] = {run: [] for run in runs}
            for r in range(args.repeats):
                order = runs[r % len(runs) :] + runs[: r % len(runs)]  # rotate the order
                for command, f in order:
                    expect = 2 if command.startswith("info (cut") else 0  # cut short: 2
                    peak, wall = _peak_mib(commands[command](f), expect)
                    peaks[(command, f)].append(peak)
                    walls[(command, f)].append(wall)
    finally:
        router.terminate()
        router.wait()
    print(
        f"machine: {cpu_model()}, {os.cpu_count()} cores, Python {platform.python_version()}; "
        f"files made in {made:.0f} s"
    )
    print(
        f"large: {sizes['large'] / (1 << 20):.0f} MiB ({large_frames} frames {width}x{height} "
        f"rgb8, lz4 chunks); small: {sizes['small'] / (1 << 20):.1f} MiB "
        f"({args.small_frames} frames); {args.repeats} interleaved repeats"
    )
    print("peak RSS of the child (MiB), median [min, max]; ratio = large / small per repeat")
    for command in commands:
        large, small = peaks[(command, "large")], peaks[(command, "small")]
        ratios = [a / b for a, b in zip(large, small, strict=True)]
        share = [a * (1 << 20) / sizes["large"] for a in large]
        print(
            f"  {command:<24} large {median_spread(large, '.0f')}  small "
            f"{median_spread(small, '.0f')}  ratio {median_spread(ratios, '.3f', '×')}  "
            f"peak/file {median_spread(share, '.3f')}  wall large "
            f"{median_spread(walls[(command, 'large')], '.1f', ' s')}"
        )
    if args.smoke:
        print("(--smoke: figures are noise)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
