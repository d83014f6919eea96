"""A fresh machine's `make demo`, install included, against the goal of 3 minutes; the demo's
hit on each supported Python.

Run `python -m benchmarks.bench_first_run [--repeats 5] [--pythons 3.12,3.13]`. Each repeat
clones the committed tree into a new folder and runs `make demo` there as a new user would: not
root (as `nobody` when the benchmark runs as root), with no C or C++ compiler on PATH, a new
HOME (so no pip cache and no YARP cache) and the machine's Python 3.11 (`/usr/bin/python3`).
The figure is the wall time from `make demo` to its exit (the demo's JSON line must show a
hit), with the install's share (until `.venv/.installed` is written). Then `archery demo` (seed
0) on each of `--pythons`, installed from the clone with `[all]` into a fresh venv: the rollout
of the hit and the final distance beside 3.11's. `--smoke`: `make -n demo` in a fresh clone
(no YARP, no `[dev]`, no apt in the plan), no figures.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from datetime import UTC, datetime
from pathlib import Path

from benchmarks.machine import cpu_model
from benchmarks.spread import median_spread

ROOT = Path(__file__).resolve().parents[1]
GOAL_S = 180.0
NOBODY = 65534
#: names a build of a C extension would call: hidden from PATH, as on a machine without them
COMPILERS = ("cc", "gcc", "g++", "c++", "cpp", "clang", "clang++", "ld", "as")
SYSTEM_PYTHON = "/usr/bin/python3"


def _bin_without_compilers(folder: Path) -> Path:
    """A folder of links to every program on the system PATH but the compilers."""
    out = folder / "bin"
    out.mkdir()
    for place in ("/usr/local/bin", "/usr/bin", "/bin"):
        for program in Path(place).iterdir():
            name = program.name
            hidden = name in COMPILERS or any(
                name.endswith(f"-{c}") or name.startswith(f"{c}-") for c in COMPILERS
            )
            if not hidden and not (out / name).exists():
                (out / name).symlink_to(program)
    return out


def _as_user(argv: list[str]) -> list[str]:
    """`argv` run as `nobody` when this process is root, else as it is."""
    if os.geteuid() != 0:
        return argv
    return ["setpriv", f"--reuid={NOBODY}", f"--regid={NOBODY}", "--clear-groups", *argv]


def _own(path: Path) -> None:
    if os.geteuid() == 0:
        subprocess.run(["chown", "-R", f"{NOBODY}:{NOBODY}", str(path)], check=True)


def _clone(folder: Path) -> Path:
    clone = folder / "archery"
    subprocess.run(["git", "clone", "-q", str(ROOT), str(clone)], check=True)
    return clone


def first_run(folder: Path) -> tuple[float, float, dict[str, object], Path]:
    """One fresh `make demo` in `folder`: (wall s, install s, the demo's result, the clone)."""
    folder.chmod(0o755)
    clone = _clone(folder)
    home = folder / "home"
    home.mkdir()
    path = _bin_without_compilers(folder)
    _own(folder)
    env = {"PATH": str(path), "HOME": str(home), "LANG": "C.UTF-8"}
    argv = _as_user(["make", "demo", f"PYTHON={SYSTEM_PYTHON}"])
    start = time.time()
    done = subprocess.run(argv, cwd=clone, env=env, capture_output=True, text=True, timeout=1800)
    wall = time.time() - start
    if done.returncode != 0:
        raise RuntimeError(f"make demo failed ({done.returncode}):\n{done.stderr[-3000:]}")
    result = _demo_result(done.stdout)
    if result.get("hit_at") is None:
        raise RuntimeError(f"the demo did not hit: {result}")
    install = (clone / ".venv" / ".installed").stat().st_mtime - start
    return wall, install, result, clone


def _demo_result(stdout: str) -> dict[str, object]:
    for line in reversed(stdout.strip().splitlines()):
        if line.startswith("{"):
            return dict(json.loads(line))
    raise RuntimeError(f"no JSON result in the demo's output:\n{stdout[-2000:]}")


def other_python(version: str, clone: Path, folder: Path) -> dict[str, object]:
    """`archery demo` (seed 0) on Python `version`, installed from `clone` with [all]."""
    from tests.wheel_check import interpreter

    venv = folder / f"venv{version}"
    subprocess.run([interpreter(version), "-m", "venv", str(venv)], check=True)
    subprocess.run(
        [str(venv / "bin" / "pip"), "install", "-q", f"{clone}[all]"],
        check=True,
        capture_output=True,
    )
    run = folder / f"run{version}"
    run.mkdir()
    env = {"PATH": f"{venv / 'bin'}:/usr/bin:/bin", "HOME": str(folder), "LANG": "C.UTF-8"}
    done = subprocess.run(
        ["archery", "demo", "--seed", "0"], cwd=run, env=env, capture_output=True, text=True
    )
    if done.returncode != 0:
        raise RuntimeError(f"archery demo on {version} failed:\n{done.stderr[-2000:]}")
    return _demo_result(done.stdout)


def smoke() -> int:
    """`make -n demo` in a fresh clone: the plan installs [all] and builds no YARP."""
    with tempfile.TemporaryDirectory() as tmp:
        clone = _clone(Path(tmp))
        plan = subprocess.run(
            ["make", "-n", "demo"], cwd=clone, capture_output=True, text=True, check=True
        ).stdout
    bad = [word for word in ("yarp_wheel", "apt-get", "[dev]") if word in plan]
    print(plan)
    if bad or ".[all]" not in plan:
        print(f"bench_first_run: make demo's plan holds {bad or 'no [all] install'}")
        return 1
    print("bench_first_run: make demo installs [all] and builds no YARP (smoke: no figures)")
    return 0


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark; print its RESULTS.md lines."""
    parser = argparse.ArgumentParser(prog="python -m benchmarks.bench_first_run")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--pythons", default="3.12,3.13")
    parser.add_argument("--smoke", action="store_true")
    args = parser.parse_args(argv)
    if args.smoke:
        return smoke()
    if subprocess.run(["git", "status", "--porcelain"], cwd=ROOT, capture_output=True,
                      text=True).stdout.strip():  # fmt: skip
        print("bench_first_run: the clone takes the committed tree (uncommitted changes here)")
    commit = subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True
    ).stdout.strip()
    walls: list[float] = []
    installs: list[float] = []
    results: list[dict[str, object]] = []
    with tempfile.TemporaryDirectory() as tmp:
        Path(tmp).chmod(0o755)  # the unprivileged user walks into it
        clone = None
        for i in range(args.repeats):
            folder = Path(tmp, f"fresh{i}")
            folder.mkdir()
            wall, install, result, clone = first_run(folder)
            walls.append(wall)
            installs.append(install)
            results.append(result)
            print(
                f"repeat {i + 1}/{args.repeats}: make demo {wall:.0f} s (install {install:.0f} s), "
                f"hit at rollout {result['hit_at']}",
                file=sys.stderr,
                flush=True,
            )
            if i < args.repeats - 1:
                shutil.rmtree(folder, ignore_errors=True)
        others: dict[str, dict[str, object]] = {}
        if clone is not None:
            for version in [v for v in args.pythons.split(",") if v]:
                others[version] = other_python(version, clone, Path(tmp))
    first = results[0]
    print(f"- Date: {datetime.now(UTC):%Y-%m-%d %H:%M} UTC; commit {commit}")
    print(f"- Machine: {os.cpu_count()} cores, {cpu_model()}")
    print(
        f"- `make demo` on a fresh clone, install included, {args.repeats} repeats, not root, no "
        f"compiler, new HOME: {median_spread(walls, '.0f', ' s')}, "
        f"×{statistics.median(walls) / GOAL_S:.2f} of the 3-minute goal; the install "
        f"{median_spread(installs, '.0f', ' s')}"
    )
    print(
        f"- The demo's hit (seed 0): Python 3.11 rollout {first['hit_at']}, "
        f"{float(str(first['final_distance_m'])) * 100:.4f} cm"
        + "".join(
            f"; {v} rollout {r['hit_at']}, {float(str(r['final_distance_m'])) * 100:.4f} cm"
            for v, r in others.items()
        )
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
