"""The numpy EM behind calibration: it recovers a known mixture, BIC picks its size, and a
calibration never imports scikit-learn."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from archery.services.detector.em import fit_mixture


def _samples(seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    yellow = rng.multivariate_normal([60, 170], [[30, -10], [-10, 20]], 300)
    blue = rng.multivariate_normal([170, 60], [[15, 0], [0, 40]], 200)
    return np.concatenate([yellow, blue])


def test_a_known_mixture_is_recovered() -> None:
    fit = fit_mixture(_samples(), 2, reg=1e-6, seed=0)
    order = np.argsort(fit.means[:, 0])
    assert fit.means[order] == pytest.approx(np.array([[60, 170], [170, 60]]), abs=1.0)
    assert fit.weights[order] == pytest.approx([0.6, 0.4], abs=0.01)
    assert fit.covariances[order[0]] == pytest.approx(np.array([[30, -10], [-10, 20]]), abs=6)


def test_bic_prefers_the_true_number_of_components() -> None:
    points = _samples(1)
    bic = {k: fit_mixture(points, k, reg=4.0, seed=0).bic(len(points)) for k in (1, 2, 3, 4)}
    assert min(bic, key=bic.get) == 2


def test_the_same_seed_gives_the_same_fit() -> None:
    first, second = (fit_mixture(_samples(), 3, reg=4.0, seed=5) for _ in range(2))
    assert np.array_equal(first.means, second.means)
    with pytest.raises(ValueError, match="n_init"):
        fit_mixture(_samples(), 2, reg=4.0, n_init=0)


def test_calibrating_does_not_import_scikit_learn() -> None:
    code = (
        "import sys, numpy as np\n"
        "from services.detector.colour_model import ColourModel\n"
        "rng = np.random.default_rng(0)\n"
        "pixels = np.clip(rng.normal((250, 210, 30), 5, (80, 3)), 0, 255).astype(np.uint8)\n"
        "ColourModel.fit(pixels)\n"
        "print('sklearn' in sys.modules)\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert done.stdout.strip() == "False"
