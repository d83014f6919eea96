"""Run every benchmark: each `benchmarks/bench_*.py` module and `drill_router` in turn.

`make bench` runs them at their recorded budgets; `make bench-smoke` (`--smoke`) runs each at
its smallest budget (seconds; no figures or results written), so that a benchmark that no longer
runs against today's code fails CI instead of waiting to be noticed. Each module's time is
printed, and the slowest at the end. A benchmark whose engine is missing here (Docker, YARP) is
skipped with one line naming what to install; CI, which installs both, runs every one.
"""

from __future__ import annotations

import argparse
import importlib.util
import subprocess
import sys
import time
from pathlib import Path

__all__ = ["MODULES", "main"]

HERE = Path(__file__).parent
MODULES = [*sorted(p.stem for p in HERE.glob("bench_*.py")), "drill_router"]


def _docker_problem() -> str | None:
    from tests.containers import engine_problem

    return engine_problem()


def _yarp_problem() -> str | None:
    if importlib.util.find_spec("yarp") is None:
        return "YARP's Python bindings are not installed (`make yarp` builds them, ~7 minutes)"
    return None


#: module -> the check of the engine it needs: None when it is here, else what to install
ENGINES = {
    "bench_containers": _docker_problem,
    "bench_yarp": _yarp_problem,
    "bench_yarp_body": _yarp_problem,
}


def main(argv: list[str] | None = None) -> int:
    """Run each benchmark module as `python -m benchmarks.NAME [--smoke]`; exit 1 if any fails."""
    parser = argparse.ArgumentParser(prog="python -m benchmarks.run", description=__doc__)
    parser.add_argument("--smoke", action="store_true", help="each at its smallest budget")
    parser.add_argument("only", nargs="*", help="run only these modules (default: all)")
    args = parser.parse_args(argv)
    unknown = sorted(set(args.only) - set(MODULES))
    if unknown:
        parser.error(f"no benchmark module {', '.join(unknown)}; they are: {', '.join(MODULES)}")
    failed: list[str] = []
    skipped: list[str] = []
    took: dict[str, float] = {}
    begin = time.monotonic()
    for name in args.only or MODULES:
        problem = ENGINES[name]() if name in ENGINES else None
        if problem is not None:
            print(f"\n=== {name}: skipped: {problem} ===", flush=True)
            skipped.append(name)
            continue
        print(f"\n=== {name}{' (smoke)' if args.smoke else ''} ===", flush=True)
        start = time.monotonic()
        argv_ = [sys.executable, "-m", f"benchmarks.{name}", *(["--smoke"] if args.smoke else [])]
        code = subprocess.run(argv_, stdin=subprocess.DEVNULL).returncode
        took[name] = time.monotonic() - start
        print(f"=== {name}: exit {code} in {took[name]:.1f} s ===", flush=True)
        if code != 0:
            failed.append(name)
    slowest = sorted(took, key=took.__getitem__, reverse=True)[:5]
    print(
        f"\n{len(took)} benchmark modules in {time.monotonic() - begin:.0f} s; slowest: "
        + ", ".join(f"{n} {took[n]:.0f} s" for n in slowest),
        flush=True,
    )
    if skipped:
        print(f"skipped (engine missing): {', '.join(skipped)}", flush=True)
    if failed:
        print(f"failed: {', '.join(failed)}", file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
