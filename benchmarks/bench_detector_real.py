"""The detector on the development set and the real photographs, against a baseline revision.

The baseline (default: the `main` branch) is exported from git into a temporary folder, and
its detector (its whole detection core, as a package of its own) and CLI run in the same
process and the same run as this tree's, interleaved:
- the development set (`tests.devset`): per kind of change, the fraction of the
  visible cases whose centre is within 5 % of the blue ring's diameter, wrong centres reported
  with confidence ≥ 0.5, and faces mostly outside the image reported as seen;
- the four shared photographs (when beside the clone): same-photo calibration (each photo
  calibrated on itself) and cross-photo (calibrated on one, detecting on each other one);
- detection time per 1280×720 frame (every 1280×720 case of the set, ≥ 5 interleaved
  repeats; median and spread of the repeats' medians);
- wall and CPU time of `archery calibrate` / `archery detect` on one photo and of `archery
  detect` on a missing file (child processes, interleaved).

    MUJOCO_GL=egl .venv/bin/python -m benchmarks.bench_detector_real [--baseline main]
        [--repeats 5] [--json FILE] [--smoke]

`--smoke` runs the same path at its smallest budget: the baseline is `git archive HEAD` (this
tree's last commit: a `main` branch need not exist in the checkout), the development set is its
smallest drawn scene (every kind of change; the timing's model is still calibrated on the second
scene), the photographs' same- and cross-photo figures when they are beside the clone, one
timing repeat over the first 4 frames, the CLI commands once per tree; the goals are printed but
not judged (the exit status is 0 unless something fails to run).
"""

from __future__ import annotations

import argparse
import collections
import importlib
import json
import math
import os
import platform
import re
import resource
import shutil
import statistics
import subprocess
import sys
import tarfile
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

from archery.services.detector.colour_model import ColourModel
from archery.services.detector.detect import Detector, DetectorSettings
from benchmarks.machine import cpu_model
from benchmarks.spread import median_spread
from tests import devset
from tests.devset import Case, Scene

ROOT = Path(__file__).resolve().parents[1]
PHOTOS = ROOT.parent / "shared" / "data" / "real-targets"
TIME_GOAL_MS = 10.0
CLI_GOAL_S = 1.5
SMOKE_SCENES = 1  # scenes of the development set in a smoke run (the smallest comes first)
SMOKE_FRAMES = 4  # frames timed in a smoke run

Find = Callable[[np.ndarray], tuple[tuple[float, float] | None, float]]


def export_baseline(ref: str, into: Path) -> Path:
    """The baseline revision's `protocol`, `services` and `sim` packages under `into`.

    Raises:
        SystemExit: git cannot export `ref`.
    """
    archive = into / "baseline.tar"
    done = subprocess.run(
        ["git", "-C", str(ROOT), "archive", "--format=tar", "-o", str(archive), ref,
         "protocol", "services", "sim"],
        capture_output=True, text=True, check=False,
    )  # fmt: skip
    if done.returncode != 0:
        raise SystemExit(f"cannot export the baseline {ref!r} from git: {done.stderr.strip()}")
    tree = into / "tree"
    with tarfile.open(archive) as tar:
        tar.extractall(tree, filter="data")
    return tree


def load_baseline(tree: Path) -> ModuleType:
    """The baseline's detection core as a package of its own, `baseline_detector` beside the
    exported tree (its modules import each other, never this tree's), and its `detect` module.
    """
    package = tree.parent / "baseline_detector"
    shutil.copytree(tree / "services" / "detector", package)
    for path in package.glob("*.py"):  # a tree of before the one import name `archery` too
        text = path.read_text().replace("archery.services.detector.", "baseline_detector.")
        text = text.replace("archery.services.detector.", "baseline_detector.")
        path.write_text(
            re.sub(r"^(\s*)from (protocol|sim)\.", r"\1from archery.\2.", text, flags=re.M)
        )
    sys.path.insert(0, str(tree.parent))
    return importlib.import_module("baseline_detector.detect")


def finders(model: ColourModel, legacy: ModuleType) -> dict[str, Find]:
    """centre and confidence from this tree's detector and the baseline's, one model."""
    ours, theirs = Detector(model), legacy.Detector(model)

    def run(detector: Any) -> Find:
        def find(rgb: np.ndarray) -> tuple[tuple[float, float] | None, float]:
            target = detector.detect(rgb).target
            return (None, 0.0) if target is None else (tuple(target.px), target.confidence)

        return find

    return {"baseline": run(theirs), "this": run(ours)}


def devset_figures(
    scenes: list[Scene], legacy: ModuleType
) -> tuple[dict[str, dict[str, collections.Counter[str]]], list[Case]]:
    """Per detector and kind of change: counts of right / wrong / unsure (visible cases),
    hidden cases seen; under "confidence", this detector's candidates without a threshold
    ("right" or "off" > 5 %) per confidence quarter; and the 1280×720 cases (for timing)."""
    counts: dict[str, dict[str, collections.Counter[str]]] = {
        "baseline": collections.defaultdict(collections.Counter),
        "this": collections.defaultdict(collections.Counter),
        "confidence": collections.defaultdict(collections.Counter),
    }
    timing = []
    for scene in scenes:
        model = devset.calibrate(scene)
        find = finders(model, legacy)
        raw = Detector(model, DetectorSettings(min_target_confidence=0.0))
        for case in devset.cases(scene):
            if case.rgb.shape[:2] == (720, 1280):
                timing.append(case)
            target = raw.detect(case.rgb).target  # every candidate, with its confidence
            if target is not None:
                off = math.dist(target.px, case.centre) > devset.TOLERANCE * case.diameter
                band = min(3, int(target.confidence * 4))
                counts["confidence"]["off" if off else "right"][f"{band}"] += 1
            for name, detect in find.items():
                px, confidence = detect(case.rgb)
                verdict = devset.judge(case, px, confidence)
                tally = counts[name][case.kind]
                if verdict == "wrong":
                    tally["wrong"] += 1
                if case.expect == "visible":
                    tally["visible"] += 1
                    tally["right"] += verdict == "right"
                elif case.expect == "hidden":
                    tally["hidden"] += 1
                    tally["hidden seen"] += px is not None
    return counts, timing


def photo_figures(legacy: ModuleType) -> dict[str, dict[str, list[float]]]:
    """Same-photo and cross-photo errors (fraction of the blue diameter; inf: not seen) and
    confidences per detector."""
    scenes = devset.photo_scenes(PHOTOS)
    out: dict[str, dict[str, list[float]]] = collections.defaultdict(
        lambda: collections.defaultdict(list)
    )
    for source in scenes:
        find = finders(devset.calibrate(source), legacy)
        for scene in scenes:
            setting = "same" if scene is source else "cross"
            for name, detect in find.items():
                px, confidence = detect(scene.rgb)
                error = math.inf if px is None else math.dist(px, scene.centre) / scene.diameter
                out[name][f"{setting} error"].append(error)
                out[name][f"{setting} confidence"].append(confidence)
    return out


def time_detection(
    frames: list[Case], legacy: ModuleType, model: ColourModel, repeats: int
) -> dict[str, list[float]]:
    """Per repeat, the median ms per frame over `frames`, detectors interleaved; under
    "NAME p90" and "NAME max", those of every frame of every repeat."""
    find = finders(model, legacy)
    medians: dict[str, list[float]] = {name: [] for name in find}
    every: dict[str, list[float]] = {name: [] for name in find}
    for detect in find.values():  # warm-up
        detect(frames[0].rgb)
    for _ in range(repeats):
        for name, detect in find.items():
            times = []
            for case in frames:
                start = time.perf_counter()
                detect(case.rgb)
                times.append(1e3 * (time.perf_counter() - start))
            medians[name].append(statistics.median(times))
            every[name] += times
    for name, times in every.items():  # the slow frames: hard cases try more corrections
        medians[f"{name} p90"] = [float(np.quantile(times, 0.9))]
        medians[f"{name} max"] = [max(times)]
    return medians


def _child_times(command: list[str], cwd: Path, env: dict[str, str]) -> tuple[float, float, int]:
    """Wall s, CPU s (user + system) and exit status of one child process."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    done = subprocess.run(command, cwd=cwd, env=env, capture_output=True, check=False)
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return wall, cpu, done.returncode


def time_cli(
    baseline: Path, work: Path, repeats: int
) -> dict[str, dict[str, list[tuple[float, float]]]]:
    """Wall and CPU seconds of the CLI commands, per tree, interleaved."""
    photo, pixels = PHOTOS / "target-2.jpg", PHOTOS / "target-2.json"
    trees = {"baseline": baseline, "this": ROOT}
    out: dict[str, dict[str, list[tuple[float, float]]]] = {t: {} for t in trees}
    for _ in range(repeats):
        for name, tree in trees.items():
            env = {**os.environ, "PYTHONPATH": str(tree)}
            model = work / f"{name}.json"
            cli = [sys.executable, "-m", "archery.apps.cli"]
            commands = {
                "calibrate one photo": [
                    *cli, "calibrate", str(photo), "--pixels", str(pixels), "--out", str(model)
                ],
                "detect one photo": [*cli, "detect", str(photo), "--model", str(model)],
                "detect a missing file": [
                    *cli, "detect", str(work / "missing.jpg"), "--model", str(model)
                ],
            }  # fmt: skip
            model.unlink(missing_ok=True)  # calibrate refuses to replace it (no --force)
            for label, command in commands.items():
                wall, cpu, status = _child_times(command, tree, env)
                expected = 2 if "missing" in label else 0
                if status != expected:
                    raise SystemExit(f"{name}: `{' '.join(command)}` exited {status}")
                out[name].setdefault(label, []).append((wall, cpu))
    return out


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark and print its tables (markdown); exit 1 if a goal is missed."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--baseline", default="main", help="git revision to compare against")
    parser.add_argument("--repeats", type=int, default=5, help="interleaved timing repeats")
    parser.add_argument("--json", help="also write the figures to this file")
    parser.add_argument(
        "--smoke",
        action="store_true",
        help=f"smallest budget: baseline HEAD, {SMOKE_SCENES} drawn scene, 1 repeat over "
        f"{SMOKE_FRAMES} frames, goals not judged (overrides --baseline, --repeats)",
    )
    args = parser.parse_args(argv)
    if args.smoke:
        args.baseline, args.repeats = "HEAD", 1
    elif args.repeats < 5:
        parser.error("--repeats must be ≥ 5")
    print(f"machine: {os.cpu_count()} CPUs, {cpu_model()}; python {platform.python_version()}")
    print(f"load average at start: {os.getloadavg()[0]:.2f}")
    goals: list[tuple[str, bool]] = []
    with tempfile.TemporaryDirectory() as folder:
        tree = export_baseline(args.baseline, Path(folder))
        legacy = load_baseline(tree)
        scenes = devset.drawn_scenes() + (devset.photo_scenes(PHOTOS) if PHOTOS.is_dir() else [])
        measured = scenes[:SMOKE_SCENES] if args.smoke else scenes
        counts, frames = devset_figures(measured, legacy)
        if args.smoke:
            frames = frames[:SMOKE_FRAMES]
        print(f"\n### Development set ({len(measured)} scenes; baseline {args.baseline!r})\n")
        print(
            "| change | visible cases | within 5 %: baseline | within 5 %: this | wrong with "
            "confidence ≥ 0.5: baseline / this | mostly outside, seen: baseline / this |"
        )
        print("|---|---|---|---|---|---|")
        total: dict[str, collections.Counter[str]] = collections.defaultdict(collections.Counter)
        for kind in counts["this"]:
            old, new = counts["baseline"][kind], counts["this"][kind]
            for name, tally in (("baseline", old), ("this", new)):
                total[name].update(tally)
            hidden = (
                f"{old['hidden seen']} / {new['hidden seen']} of {new['hidden']}"
                if new["hidden"] else "–"
            )  # fmt: skip
            print(f"| {kind} | {new['visible']} | {old['right'] / new['visible']:.0%} | "
                  f"{new['right'] / new['visible']:.0%} | {old['wrong']} / {new['wrong']} | "
                  f"{hidden} |")  # fmt: skip
        old, new = total["baseline"], total["this"]
        print(f"| **all** | {new['visible']} | {old['right'] / new['visible']:.0%} | "
              f"{new['right'] / new['visible']:.0%} | {old['wrong']} / {new['wrong']} | "
              f"{old['hidden seen']} / {new['hidden seen']} of {new['hidden']} |")  # fmt: skip
        goals.append(("no wrong answer with confidence ≥ 0.5 on the set", new["wrong"] == 0))
        bands = counts["confidence"]
        print("\nThis detector's candidates with no confidence threshold, per confidence:\n")
        print("| confidence | centre within 5 % | centre off by > 5 % |")
        print("|---|---|---|")
        for band, label in enumerate(("0–0.25", "0.25–0.5", "0.5–0.75", "0.75–1")):
            print(f"| {label} | {bands['right'][str(band)]} | {bands['off'][str(band)]} |")

        if PHOTOS.is_dir():
            photos = photo_figures(legacy)
            print("\n### The four shared photographs\n")
            print("| calibration | detector | within 5 % | wrong with confidence ≥ 0.5 | "
                  "error (% of the blue diameter): median, max |")  # fmt: skip
            print("|---|---|---|---|---|")
            for setting in ("same", "cross"):
                for name in ("baseline", "this"):
                    errors = photos[name][f"{setting} error"]
                    confidences = photos[name][f"{setting} confidence"]
                    right = sum(e <= 0.05 for e in errors)
                    wrong = sum(
                        e > 0.05 and c >= 0.5 for e, c in zip(errors, confidences, strict=True)
                    )
                    finite = [100 * e for e in errors if math.isfinite(e)]
                    text = f"{statistics.median(finite):.2f}, {max(finite):.2f}" if finite else "–"
                    unseen = len(errors) - len(finite)
                    text += f" ({unseen} not seen)" if unseen else ""
                    print(
                        f"| {setting}-photo | {name} | {right}/{len(errors)} | {wrong} | {text} |"
                    )
                    if name == "this":
                        goals.append(
                            (f"{setting}-photo: all within 5 %, none confidently wrong",
                             right == len(errors) and wrong == 0)
                        )  # fmt: skip

        model = devset.calibrate(scenes[1])
        ms = time_detection(frames, legacy, model, args.repeats)
        ratio = [b / t for b, t in zip(ms["baseline"], ms["this"], strict=True)]
        print(f"\n### Detection time per 1280×720 frame ({len(frames)} frames of the set, "
              f"{args.repeats} interleaved repeats)\n")  # fmt: skip
        print("| detector | median ms per frame: median [min, max] of the repeats | p90 | max |")
        print("|---|---|---|---|")
        for name in ("baseline", "this"):
            print(f"| {name} | {median_spread(ms[name])} | {ms[f'{name} p90'][0]:.2f} | "
                  f"{ms[f'{name} max'][0]:.2f} |")  # fmt: skip
        print(f"| ratio baseline / this | {median_spread(ratio)} | | |")
        goals.append(
            (f"detection ≤ {TIME_GOAL_MS:g} ms", statistics.median(ms["this"]) <= TIME_GOAL_MS)
        )

        if PHOTOS.is_dir():
            cli = time_cli(tree, Path(folder), args.repeats)
            print(f"\n### CLI on one 960×1280 photo ({args.repeats} interleaved repeats; "
                  "wall s and CPU s: median [min, max])\n")  # fmt: skip
            print("| command | baseline wall | this wall | this / baseline (wall) | "
                  "baseline CPU | this CPU |")  # fmt: skip
            print("|---|---|---|---|---|---|")
            for label in cli["this"]:
                old_t, new_t = cli["baseline"][label], cli["this"][label]
                walls = [n[0] / o[0] for n, o in zip(new_t, old_t, strict=True)]
                print(
                    f"| `archery {label.split()[0]}` {' '.join(label.split()[1:])} | "
                    f"{median_spread([t[0] for t in old_t])} | "
                    f"{median_spread([t[0] for t in new_t])} | "
                    f"{median_spread(walls)} | {median_spread([t[1] for t in old_t])} | "
                    f"{median_spread([t[1] for t in new_t])} |"
                )
                goals.append(
                    (f"{label} ≤ {CLI_GOAL_S:g} s wall",
                     statistics.median(t[0] for t in new_t) <= CLI_GOAL_S)
                )  # fmt: skip
    print(f"\nload average at the end: {os.getloadavg()[0]:.2f}\n")
    for text, met in goals:
        judged = " (not judged in a smoke run)" if args.smoke else ""
        print(f"goal: {text}: {'met' if met else 'NOT MET'}{judged}")
    if args.json:
        Path(args.json).write_text(json.dumps({"goals": dict(goals)}, indent=1) + "\n")
    return 0 if all(met for _, met in goals) or args.smoke else 1


if __name__ == "__main__":
    raise SystemExit(main())
