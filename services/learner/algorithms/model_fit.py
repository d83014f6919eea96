"""The physical parameters of a `PhysicalModel` that best explain where the arrows landed."""

from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares

from archery.services.learner.algorithms.impact_model import PhysicalModel

__all__ = ["fit_parameters"]

# A model that cannot shoot a θ with trial parameters is told it missed by this much (in
# noise stds per component), so the fit steps back from those parameters.
_UNSHOOTABLE = 1e6
_DIFF_STEP = 1e-6  # relative finite-difference step of the fit's Jacobian


def fit_parameters(
    model: PhysicalModel,
    thetas: np.ndarray,
    rewards: np.ndarray,
    weights: np.ndarray,
    *,
    noise_std: float,
    mean: np.ndarray,
    start: np.ndarray,
) -> np.ndarray:
    """The maximum a posteriori p of `model`: the least squares of the weighted misses
    (rewards − model.impacts_at(thetas, p)) / noise_std and of (p − mean) / the model's prior
    std, within the model's bounds (a bounded trust-region fit, scipy's `least_squares`).

    Parameters with a prior std of 0 stay at `mean`. The fit starts from `start` (the previous
    fit), at least a tenth of a prior std inside each bound: at a bound of 0 drag the wind,
    which acts only through the drag, would show no gradient.

    Args:
        model: the model whose parameters are fitted.
        thetas: (n, d) θ of the rollouts (m).
        rewards: (n, 2) where they landed, r (m).
        weights: (n,) weight of each rollout (≥ 0).
        noise_std: std of the observation noise on r (m).
        mean: the prior mean of p.
        start: where the fit starts.

    Returns:
        p, the prior mean where no rollout is given.
    """
    std = model.parameter_std()
    free = std > 0
    if not np.any(free) or len(thetas) == 0:
        return np.array(mean, dtype=float)
    low, high = (bound[free] for bound in model.parameter_bounds())
    scale = np.sqrt(np.asarray(weights, dtype=float))[:, None] / noise_std
    params = np.array(mean, dtype=float)

    def residuals(q: np.ndarray) -> np.ndarray:
        params[free] = q
        try:
            misses = (rewards - model.impacts_at(thetas, params)) * scale
        except ValueError:
            misses = np.full(rewards.shape, _UNSHOOTABLE)
        return np.concatenate([misses.ravel(), (q - mean[free]) / std[free]])

    margin = np.minimum(0.1 * std[free], 0.5 * (high - low))
    x0 = np.clip(np.asarray(start, dtype=float)[free], low + margin, high - margin)
    solution = least_squares(
        residuals, x0, bounds=(low, high), x_scale=std[free], diff_step=_DIFF_STEP
    )
    fitted = np.array(mean, dtype=float)
    fitted[free] = solution.x
    return fitted
