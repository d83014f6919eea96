"""One benchmark on this tree and on an earlier one, run after run, alternating which goes first,
with one figure of each run's report taken out and summed up per tree.

Run `python -m benchmarks.alternate --before 0d1273b --repeats 5 --figure REGEX MODULE
[ARGS...]`: `python -m benchmarks.MODULE ARGS...` runs `--repeats` times on each tree,
interleaved (the earlier one a `git archive`; each run in its tree's folder, which `python -m`
puts first on the path, and with its code first on PYTHONPATH: `benchmarks.trees`). REGEX (one
group, a number) picks the figure out of each run's output. Prints each run's matching line,
then per tree the figure's median [min, max] and the ratio of the medians (this tree / the
earlier one); every run's whole output goes to `--out`.
"""

from __future__ import annotations

import argparse
import re
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from benchmarks.spread import median_spread
from benchmarks.trees import ROOT, env_for, header, interleaved, tree_at

__all__ = ["main"]


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark on both trees; exit status 0 (1 when a run failed or had no figure)."""
    parser = argparse.ArgumentParser(prog="python -m benchmarks.alternate", description=__doc__)
    parser.add_argument("--before", default="0d1273b", help="the earlier tree's commit")
    parser.add_argument("--repeats", type=int, default=5, help="runs per tree (≥ 5)")
    parser.add_argument("--figure", required=True, help="regex with one group: the figure")
    parser.add_argument("--out", default="runs/alternate", help="where each run's output goes")
    parser.add_argument("module", help="a benchmark module, e.g. bench_idle")
    parser.add_argument("args", nargs=argparse.REMAINDER, help="its arguments")
    args = parser.parse_args(argv)
    figure = re.compile(args.figure)
    out = Path(args.out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    values: dict[str, list[float]] = {"before": [], "after": []}
    header()
    print(f"- `python -m benchmarks.{args.module} {' '.join(args.args)}`, {args.repeats} × 2 runs")
    with tempfile.TemporaryDirectory(prefix="alternate-") as tmp:
        trees = [("before", tree_at(args.before, Path(tmp))), ("after", ROOT)]
        for k, name, tree in interleaved(args.repeats, trees):
            run = subprocess.run(
                [sys.executable, "-m", f"benchmarks.{args.module}", *args.args],
                env=env_for(tree),
                cwd=tree,
                capture_output=True,
                text=True,
            )
            (out / f"{args.module}-{name}-{k + 1}.txt").write_text(run.stdout + run.stderr)
            found = [m for m in map(figure.search, run.stdout.splitlines()) if m]
            if not found:
                print(f"run {k + 1} {name}: no figure (exit {run.returncode})", file=sys.stderr)
                return 1
            values[name].append(float(found[-1].group(1)))
            print(f"run {k + 1} {name}: {found[-1].string.strip()}", flush=True)
    for name, got in values.items():
        print(f"{name}: {median_spread(got, '.3f')}")
    ratio = statistics.median(values["after"]) / statistics.median(values["before"])
    print(f"after / before (medians): ×{ratio:.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
