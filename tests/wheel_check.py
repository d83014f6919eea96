"""`make wheel-check`: the package as a user installs it, checked end to end.

1. The wheel is built from the checkout (`pip wheel --no-deps`).
2. Every file of the five product packages that git tracks is inside it, under the one import
   name `archery` (a module or a page missing from the wheel would work in the checkout and
   fail for a user), and nothing else is at its top but its metadata.
3. It is installed with `[all]` into a fresh virtual environment outside the checkout, not
   editable.
4. From another folder, with only PATH, HOME and LANG in the environment, the installed
   distribution put only `archery` at the top of site-packages (`import protocol` fails), the
   installed `archery` imports from that environment (never the checkout) and `archery demo`
   runs to a hit, its JSON result line printed and the hit filmed.
5. With `--pythons 3.12,3.13`, the same wheel on each of those Pythons: a fresh venv, the
   install with `[all]`, `archery demo` to a hit from a bare shell, and a fast subset of the
   tests (FAST_TESTS) run by that Python (the full suite stays on the main Python).

Each step prints its time; the folder is removed afterwards unless a step failed (then its path
is printed). Exit status 0 when every step passes, 1 otherwise.

    python -m tests.wheel_check [--keep] [--pythons 3.12,3.13]
"""

from __future__ import annotations

import argparse
import glob
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
import zipfile
from pathlib import Path

CHECKOUT = Path(__file__).resolve().parents[1]
PACKAGES = ("protocol", "mesh", "services", "apps", "sim")
#: a fast subset of the suite for the other Pythons: every layer and each compiled dependency
#: (numpy, scipy, zenoh, MuJoCo, Pinocchio, OpenCV, msgspec), about two minutes
FAST_TESTS = (
    "test_ballistic.py",
    "test_messages.py",
    "test_vectors.py",
    "test_robotspec.py",
    "test_verbs.py",
    "test_netflags.py",
    "test_node.py",
    "test_journal.py",
    "test_learners.py",
    "test_ik.py",
    "test_movement_dmp.py",
    "test_world.py",
    "test_gmm.py",
    "test_detector_em.py",
    "test_output_paths.py",
)
#: what the fast subset needs beyond `[all]`
TEST_TOOLS = ("pytest>=8", "pytest-timeout>=2.2", "hypothesis>=6.100", "psutil>=5.9")


class CheckFailed(Exception):
    """A step of the check failed; the message says which and why."""


def _step(title: str, argv: list[str], *, timeout: float, **kwargs: object) -> str:
    """Run one step, print its time; its stdout. Raises CheckFailed with its output's end."""
    print(f"wheel-check: {title} …", flush=True)
    start = time.monotonic()
    try:
        proc = subprocess.run(
            argv,
            stdin=subprocess.DEVNULL,
            capture_output=True,
            text=True,
            timeout=timeout,
            **kwargs,  # type: ignore[arg-type]
        )
    except subprocess.TimeoutExpired as exc:
        raise CheckFailed(f"{title}: no end within {timeout:.0f} s") from exc
    took = time.monotonic() - start
    if proc.returncode != 0:
        tail = (proc.stdout[-3000:] + "\n" + proc.stderr[-3000:]).strip()
        raise CheckFailed(f"{title}: exit status {proc.returncode} after {took:.0f} s\n{tail}")
    print(f"wheel-check: {title}: ok in {took:.1f} s", flush=True)
    return proc.stdout


def _tracked_package_files() -> set[str]:
    """The files of the product packages that git tracks, as paths inside the wheel."""
    out = subprocess.run(
        ["git", "ls-files", *PACKAGES, "archery/__init__.py"],
        cwd=CHECKOUT,
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    return {
        line if line.startswith("archery/") else f"archery/{line}"
        for line in out.splitlines()
        if line.strip()
    }


def _check_top(names: set[str], where: str) -> None:
    """Only `archery` and the distribution's metadata at the top of `names` (paths)."""
    top = {name.split("/")[0] for name in names if not name.startswith("..")}
    extra = sorted(t for t in top if t != "archery" and not t.endswith(".dist-info"))
    if extra:
        raise CheckFailed(f"{where} puts more than `archery` at the top: {extra}")
    print(f"wheel-check: {where} puts only `archery` at the top of site-packages")


def _check_contents(wheel: Path) -> None:
    names = set(zipfile.ZipFile(wheel).namelist())
    missing = sorted(_tracked_package_files() - names)
    if missing:
        raise CheckFailed(
            f"{len(missing)} file(s) of the packages are not in {wheel.name}: "
            + ", ".join(missing[:20])
        )
    print(f"wheel-check: {wheel.name} holds every tracked package file ({len(names)} files)")
    _check_top(names, wheel.name)


def interpreter(version: str) -> str:
    """The path of a `pythonX.Y` for `version` ("3.12"): the one on PATH when it runs, else
    pyenv's (whose shim refuses a version that is not selected). Raises CheckFailed."""
    name = f"python{version}"
    found = shutil.which(name)
    if found and subprocess.run([found, "-c", ""], capture_output=True).returncode == 0:
        return found
    root = os.environ.get("PYENV_ROOT") or str(Path.home() / ".pyenv")
    for candidate in sorted(glob.glob(f"{root}/versions/{version}*/bin/{name}"), reverse=True):
        if subprocess.run([candidate, "-c", ""], capture_output=True).returncode == 0:
            return candidate
    raise CheckFailed(f"no {name} on PATH or under {root}/versions: install Python {version}")


def build(folder: Path) -> Path:
    """The wheel, built from the checkout into `folder`/dist and its contents checked."""
    dist = folder / "dist"
    _step(
        "build the wheel",
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(dist), str(CHECKOUT)],
        timeout=600,
    )
    wheels = sorted(dist.glob("archery-*.whl"))
    if len(wheels) != 1:
        raise CheckFailed(f"expected one archery wheel in {dist}, found {wheels}")
    _check_contents(wheels[0])
    return wheels[0]


def _installed(folder: Path, wheel: Path, python: str) -> tuple[Path, Path, dict[str, str]]:
    """A fresh venv of `python` in `folder` with `wheel[all]`: (venv, a folder outside the
    checkout to run from, the bare environment to run in)."""
    venv, home, elsewhere = (folder / n for n in ("venv", "home", "elsewhere"))
    for path in (home, elsewhere):
        path.mkdir(parents=True)
    _step("create a fresh virtual environment", [python, "-m", "venv", str(venv)], timeout=300)
    _step(
        "install the wheel with [all]",
        [str(venv / "bin" / "pip"), "install", "-q", f"{wheel}[all]"],
        timeout=1800,
    )
    env = {"PATH": f"{venv / 'bin'}:/usr/local/bin:/usr/bin:/bin", "HOME": str(home)}
    env["LANG"] = "C.UTF-8"
    return venv, elsewhere, env


def _demo(elsewhere: Path, env: dict[str, str], title: str, *args: str) -> dict[str, object]:
    """`archery demo ARGS` in `elsewhere` with `env`; its JSON result, checked for a filmed hit."""
    out = _step(title, ["archery", "demo", *args], timeout=900, cwd=elsewhere, env=env)
    try:
        result: dict[str, object] = json.loads(out.strip().splitlines()[-1])
    except (IndexError, ValueError):
        raise CheckFailed(f"the demo's last line is not its JSON result:\n{out[-2000:]}") from None
    video = elsewhere / str(result.get("video"))
    if result.get("hit_at") is None or not video.is_file() or video.stat().st_size == 0:
        raise CheckFailed(f"the demo did not hit, or its hit was not filmed: {result}")
    return result


def check_other_python(folder: Path, wheel: Path, version: str) -> None:
    """The wheel on Python `version`: installed with [all], the demo to a hit from a bare shell,
    the fast subset of the tests. Raises CheckFailed."""
    python = interpreter(version)
    print(f"wheel-check: Python {version} ({python})", flush=True)
    venv, elsewhere, env = _installed(folder, wheel, python)
    result = _demo(elsewhere, env, f"archery demo on Python {version} in a bare environment")
    print(f"wheel-check: Python {version}: the demo hit at rollout {result['hit_at']}, filmed")
    _step(
        f"install the test tools on Python {version}",
        [str(venv / "bin" / "pip"), "install", "-q", *TEST_TOOLS],
        timeout=600,
    )
    tests = [str(CHECKOUT / "tests" / name) for name in FAST_TESTS]
    out = _step(
        f"the fast subset of the tests on Python {version}",
        [str(venv / "bin" / "python"), "-m", "pytest", "-q", "-p", "no:cacheprovider", *tests],
        timeout=1200,
        cwd=CHECKOUT,
        env=env,
    )
    print(f"wheel-check: Python {version}: {out.strip().splitlines()[-1]}")


def check(folder: Path, wheel: Path) -> None:
    """The whole check of `wheel` on this Python in `folder` (outside the checkout). Raises
    CheckFailed."""
    venv, elsewhere, env = _installed(folder, wheel, sys.executable)
    installed = _step(
        "list the installed distribution's files",
        ["python", "-c", "import importlib.metadata as m; print(*m.files('archery'), sep='\\n')"],
        timeout=120,
        cwd=elsewhere,
        env=env,
    )
    _check_top(set(installed.split()), "the installed distribution")
    try:
        _step(
            "import protocol",
            ["python", "-c", "import protocol"],
            timeout=120,
            cwd=elsewhere,
            env=env,
        )
    except CheckFailed as exc:
        if "ModuleNotFoundError: No module named 'protocol'" not in str(exc):
            raise
        print("wheel-check: `import protocol` fails after the install, as it should")
    else:
        raise CheckFailed(
            "`import protocol` works after the install: an old import name is at the top"
        )
    where = _step(
        "import from the installed package",
        [
            "python",
            "-c",
            "import archery.apps, archery.sim; print(archery.apps.__file__, archery.sim.__file__)",
        ],
        timeout=120,
        cwd=elsewhere,
        env=env,
    )
    for line in where.split():
        if not Path(line).is_relative_to(venv) or Path(line).is_relative_to(CHECKOUT):
            raise CheckFailed(f"the package was imported from {line}, not from {venv}")
    result = _demo(elsewhere, env, "archery demo from another folder in a bare environment")
    print(
        f"wheel-check: the installed demo hit at rollout {result['hit_at']} "
        f"({result['rollouts']} rollouts), filmed into {Path(str(result['video'])).name}"
    )
    whole = _demo(
        elsewhere,
        env,
        "archery demo --shot whole (the shipped demonstration's DMPs) in a bare environment",
        *("--shot", "whole", "--seed", "4", "--rollouts", "20"),
    )
    print(f"wheel-check: the whole shot's demo hit at rollout {whole['hit_at']}, filmed")


def main(argv: list[str] | None = None) -> int:
    """Run the check; exit status 0 when every step passes."""
    parser = argparse.ArgumentParser(prog="python -m tests.wheel_check", description=__doc__)
    parser.add_argument("--keep", action="store_true", help="keep the folder afterwards")
    parser.add_argument(
        "--pythons",
        default="",
        metavar="X.Y,…",
        help="also check the wheel on these Pythons (e.g. 3.12,3.13): demo and fast tests",
    )
    args = parser.parse_args(argv)
    versions = [v for v in args.pythons.split(",") if v]
    for version in versions:
        if not re.fullmatch(r"3\.\d+", version):
            parser.error(f"--pythons: {version!r} is not a version like 3.12")
    folder = Path(tempfile.mkdtemp(prefix="archery-wheel-check-"))
    if folder.is_relative_to(CHECKOUT):
        print(f"wheel-check: {folder} is inside the checkout", file=sys.stderr)
        return 1
    start = time.monotonic()
    try:
        wheel = build(folder)
        check(folder / "main", wheel)
        for version in versions:
            check_other_python(folder / f"python{version}", wheel, version)
    except CheckFailed as exc:
        print(f"wheel-check: FAILED: {exc}\n(the folder is kept: {folder})", file=sys.stderr)
        return 1
    print(f"wheel-check: passed in {time.monotonic() - start:.0f} s")
    if args.keep:
        print(f"wheel-check: the folder is kept: {folder}")
    else:
        shutil.rmtree(folder, ignore_errors=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
