"""PoWER with importance sampling over the σ best rollouts (the paper's Section III-A, Eq. 2-4)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from archery.protocol.text import shown
from archery.protocol.theta import THETA_BOX, ThetaBox
from archery.services.learner.algorithms.base import (
    MAX_STD,
    Learner,
    RestoreError,
    _count_option,
    _finite_option,
    _std_option,
    in_range,
)

__all__ = ["DEFAULT_RETURN_SCALE", "Power"]

# s (m) in R = exp(−‖r‖/s), PoWER's importance weights: why 5 cm, see `Power`.
DEFAULT_RETURN_SCALE = 0.05


class Power(Learner):
    """Policy learning by Weighting Exploration with the Returns (Kober and Peters).

    Each rollout explores around the current policy mean θ_n with Gaussian noise; after each
    rollout θ_n is replaced by the return-weighted mean of the σ best rollouts of the whole
    history (Eq. 2 with the importance sampler of Eq. 3-4), and the exploration variance is
    multiplied by `decay`.

    Args:
        theta0: initial policy mean θ (m).
        rng: the random generator for exploration.
        bounds: θ box (m).
        n_best: σ, how many of the best past rollouts the importance sampler uses (Eq. 3).
        explore_std: initial exploration standard deviation (m), one for all θ components or
            one per component.
        decay: factor applied to the exploration variance after each rollout (0, 1].
        return_scale: the length s (m) that ‖r‖ is measured in for the importance weights,
            R = exp(−‖r‖/s). Default 5 cm, the radius of the innermost ring.

    The paper writes R = exp(−‖r‖) (Eq. 1) without saying in which unit ‖r‖ enters it. The
    unit matters only to PoWER: its update (Eq. 2) weights the σ best rollouts by R, so with ‖r‖
    in metres arrows 5 and 20 cm from the centre weigh almost the same (e^−0.05 vs e^−0.2) and
    the mean moves slowly; ARCHER and the baselines use R only to rank rollouts, which no scale
    changes. Sweeping s on the paper's ballistic scenario (40 sessions × 60 rollouts, five
    master seeds; `benchmarks/bench_power_scale.py`, table in benchmarks/RESULTS.md): with
    s = 1 m PoWER needs a median of 26 rollouts to hit (25.5 over the seeds) against the
    paper's 19; every s from 10 cm down to 5 mm lands within 19 ± 3. The default is 5 cm, in
    the middle of that range, because it is the task's own length: R = e^−1 on the 5 cm ring
    that counts as a hit (median 18 with seed 0, 20 over the seeds, each seed 18-20.5; 3 cm
    lands on 19 over the seeds but is no length of the task). Other scales stay selectable
    (`power-metre` for 1 m; `archery experiment --power-scale S`, `archery learn --option
    return_scale=S`).
    """

    algorithm = "power"

    def __init__(
        self,
        theta0: np.ndarray,
        *,
        rng: np.random.Generator,
        bounds: ThetaBox = THETA_BOX,
        n_best: int = 3,
        explore_std: float | Sequence[float] = 0.01,
        decay: float = 0.965,
        return_scale: float = DEFAULT_RETURN_SCALE,
    ) -> None:
        super().__init__(theta0, rng=rng, bounds=bounds)
        self.n_best = _count_option("n_best (σ)", n_best, low=1)
        self.explore_std = _std_option("explore_std (m)", explore_std, self.theta0.size)
        self.decay = _finite_option("decay", decay, low=1e-6, high=1.0)
        self.return_scale = _finite_option("return_scale (m)", return_scale, low=1e-6)
        self.mean = self.theta0.copy()
        self.variance = self.explore_std**2

    def options(self) -> dict[str, Any]:
        """Constructor options as plain values."""
        return {
            "n_best": self.n_best,
            "explore_std": self.explore_std.tolist(),
            "decay": self.decay,
            "return_scale": self.return_scale,
        }

    def _propose(self) -> np.ndarray:
        # Exploration: θ_k = θ_n + ε, ε ~ N(0, diag(variance)).
        result: np.ndarray = self.mean + np.sqrt(self.variance) * self.rng.standard_normal(
            self.mean.size
        )
        return result

    def _update(self, theta: np.ndarray, r: np.ndarray, big_return: float) -> None:
        # Eq. 4: ind(k), the k-th best of all past rollouts by return; keep the σ best.
        top = self.ranked()[: self.n_best]
        thetas = self.thetas[top]
        # Returns R(τ) = exp(−‖r‖) (Eq. 1, r in units of return_scale), rescaled by
        # exp(min‖r‖) so that they cannot all underflow to 0; the factor cancels in Eq. 2.
        distances = np.linalg.norm(self.rewards[top], axis=1) / self.return_scale
        weights = np.exp(-(distances - distances.min()))
        # Eq. 2 with the importance sampler of Eq. 3:
        # θ_{n+1} = θ_n + Σ_k (θ_ind(k) − θ_n) R_ind(k) / Σ_k R_ind(k).
        self.mean = self.mean + weights @ (thetas - self.mean) / weights.sum()
        # Exploration decay, per rollout.
        self.variance = self.variance * self.decay

    def _extra_state(self) -> dict[str, Any]:
        return {"mean": self.mean.tolist(), "variance": self.variance.tolist()}

    def _load_extra_state(self, extra: dict[str, Any]) -> None:
        try:
            mean = np.array(extra["mean"], dtype=float)
            variance = np.array(extra["variance"], dtype=float)
        except (KeyError, TypeError, ValueError) as exc:
            raise RestoreError(f"PoWER state needs 'mean' and 'variance' vectors: {exc}") from exc
        if mean.shape != self.theta0.shape or variance.shape != self.theta0.shape:
            raise RestoreError(f"PoWER state vectors must have {self.theta0.size} components")
        if not self.bounds.contains(mean):
            raise RestoreError(f"PoWER {self.bounds.outside('mean', mean)}")
        if not in_range(variance, 0.0, MAX_STD**2):
            raise RestoreError(
                f"PoWER variance {shown(extra['variance'])} m² is outside [0, {MAX_STD**2}]"
            )
        self.mean, self.variance = mean, variance
