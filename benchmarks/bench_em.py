"""Benchmark of the colour model's EM (`services/detector/em.py`) against scikit-learn's
`GaussianMixture`: why calibration fits its mixtures with a numpy EM.

For the calibration pixels of every scene of the development set (drawn faces, and the shared
photographs when they are beside the clone), both fit K = 1..5 full-covariance mixtures with the
same regularisation and number of starts, and each picks K by BIC. Reported, with ≥ 5
interleaved repeats (median [min, max]):

- fit time of the K sweep (ms) for each, and the ratio scikit-learn / numpy EM;
- the import time of `sklearn.mixture` in a fresh interpreter (s), which a one-photo
  `archery calibrate` would pay on top;
- the quality: mean log-likelihood per pixel of the chosen fit (nats) for each and K chosen.

Run: `.venv/bin/python -m benchmarks.bench_em [--repeats N] [--smoke]`

`--smoke` runs the same sweeps (both fits, K = 1..5, BIC, the import timing) once, on the
smallest calibration set of the drawn scenes alone (no photographs): a check that the benchmark
still runs, whose figures mean nothing.
"""

from __future__ import annotations

import argparse
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from sklearn.mixture import GaussianMixture

from archery.services.detector.calibration import sample_pixels
from archery.services.detector.colour_model import _REG_COVAR, rgb_to_uv
from archery.services.detector.em import fit_mixture
from benchmarks.machine import cpu_model
from benchmarks.spread import median_spread
from tests.devset import Scene, drawn_scenes, photo_scenes

PHOTOS = Path(__file__).resolve().parents[2] / "shared" / "data" / "real-targets"
KS = range(1, 6)


def _em_sweep(uv: np.ndarray) -> tuple[int, float]:
    """(K by BIC, mean log-likelihood per pixel) of the numpy EM's sweep."""
    fits = [fit_mixture(uv, k, reg=_REG_COVAR, seed=0, n_init=2) for k in KS]
    best = min(fits, key=lambda m: m.bic(len(uv)))
    return best.n_components, best.log_likelihood / len(uv)


def _sk_sweep(uv: np.ndarray) -> tuple[int, float]:
    """(K by BIC, mean log-likelihood per pixel) of scikit-learn's sweep."""
    fits = [
        GaussianMixture(
            k, covariance_type="full", reg_covar=_REG_COVAR, n_init=2, random_state=0
        ).fit(uv)
        for k in KS
    ]
    best = min(fits, key=lambda m: m.bic(uv))
    return best.n_components, float(best.score(uv))


def _import_seconds() -> float:
    """Wall seconds of `import sklearn.mixture` in a fresh interpreter."""
    code = "import time; t = time.perf_counter(); import sklearn.mixture; "
    code += "print(time.perf_counter() - t)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return float(out.stdout.strip())


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark and print its tables; exit status 0."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=7, help="interleaved repeats (≥ 5)")
    parser.add_argument(
        "--smoke",
        action="store_true",
        help="smallest budget: one repeat on the smallest drawn set (overrides --repeats)",
    )
    args = parser.parse_args(argv)
    scenes: list[Scene] = drawn_scenes() + ([] if args.smoke else photo_scenes(PHOTOS))
    sets = {
        s.name: rgb_to_uv(sample_pixels(s.rgb, s.marks["target"], "target")).astype(np.float64)
        for s in scenes
    }
    if args.smoke:
        args.repeats = 1
        smallest = min(sets, key=lambda name: len(sets[name]))
        sets = {smallest: sets[smallest]}
    started = time.strftime("%a %b %d %H:%M UTC %Y", time.gmtime())
    print(f"{started}; {os.cpu_count()} CPUs, {cpu_model()}; python {platform.python_version()}")
    print(
        f"{len(sets)} calibration sets: " + ", ".join(f"{n} ({len(u)} px)" for n, u in sets.items())
    )
    em_ms: list[float] = []
    sk_ms: list[float] = []
    imports: list[float] = []
    quality: dict[str, tuple[tuple[int, float], tuple[int, float]]] = {}
    for repeat in range(args.repeats):
        imports.append(_import_seconds())
        order = (_em_sweep, _sk_sweep) if repeat % 2 == 0 else (_sk_sweep, _em_sweep)
        totals = {_em_sweep: 0.0, _sk_sweep: 0.0}
        for name, uv in sets.items():
            results = {}
            for fit in order:
                start = time.perf_counter()
                results[fit] = fit(uv)
                totals[fit] += time.perf_counter() - start
            quality[name] = (results[_em_sweep], results[_sk_sweep])
        em_ms.append(totals[_em_sweep] * 1000 / len(sets))
        sk_ms.append(totals[_sk_sweep] * 1000 / len(sets))
        print(f"repeat {repeat + 1}/{args.repeats} done", file=sys.stderr)
    ratios = [s / e for s, e in zip(sk_ms, em_ms, strict=True)]
    print("\n| figure | numpy EM | scikit-learn | scikit-learn / EM |")
    print("|---|---|---|---|")
    print(
        f"| K = 1..5 sweep per set (ms) | {median_spread(em_ms, '.3g')} | "
        f"{median_spread(sk_ms, '.3g')} | {median_spread(ratios, '.3g', '×')} |"
    )
    print(f"| import `sklearn.mixture` (s) | 0 | {median_spread(imports, '.3g')} | |")
    print("\n| set | EM: K, mean log-lik/px | scikit-learn: K, mean log-lik/px | Δ log-lik/px |")
    print("|---|---|---|---|")
    for name, ((k_em, ll_em), (k_sk, ll_sk)) in quality.items():
        print(f"| {name} | {k_em}, {ll_em:.3f} | {k_sk}, {ll_sk:.3f} | {ll_em - ll_sk:+.3f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
