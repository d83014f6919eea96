"""Expectation–maximisation for a full-covariance Gaussian mixture in the UV plane (2-D).

What `GaussianMixture(covariance_type="full", reg_covar=…, n_init=…)` of scikit-learn does for
the calibration sets of a colour model (tens to thousands of points), in plain numpy: k-means++
seeding and a few Lloyd steps per start, EM until the mean log-likelihood per point gains less
than `tol`, the best of `n_init` starts, and the Bayesian Information Criterion. Calibration
then needs no scikit-learn import (most of a one-photo `archery calibrate`'s time).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["Mixture", "fit_mixture"]

_LOG_2PI = math.log(2 * math.pi)


@dataclass(frozen=True)
class Mixture:
    """A fitted mixture: priors (K,), means (K, 2), covariances (K, 2, 2) and the total
    log-likelihood of the data it was fitted to."""

    weights: np.ndarray
    means: np.ndarray
    covariances: np.ndarray
    log_likelihood: float

    @property
    def n_components(self) -> int:
        """K."""
        return len(self.weights)

    def bic(self, count: int) -> float:
        """−2 log L + p ln N, with p = 6K − 1 free parameters in 2-D."""
        return -2.0 * self.log_likelihood + (6 * self.n_components - 1) * math.log(count)


def _log_densities(points: np.ndarray, means: np.ndarray, covariances: np.ndarray) -> np.ndarray:
    """log N(x; μ_k, Σ_k) for every point and component: (N, K)."""
    a, b, d = covariances[:, 0, 0], covariances[:, 0, 1], covariances[:, 1, 1]
    det = a * d - b * b
    dx = points[:, None, 0] - means[None, :, 0]
    dy = points[:, None, 1] - means[None, :, 1]
    mahal = (d * dx * dx - 2 * b * dx * dy + a * dy * dy) / det
    densities: np.ndarray = -0.5 * (mahal + np.log(det)) - _LOG_2PI
    return densities


def _seed_labels(points: np.ndarray, k: int, rng: np.random.Generator) -> np.ndarray:
    """k-means++ centres refined by Lloyd steps; the label of each point."""
    centres = [points[rng.integers(len(points))]]
    for _ in range(1, k):
        gaps = np.min(((points[:, None, :] - np.array(centres)[None]) ** 2).sum(-1), axis=1)
        total = float(gaps.sum())
        pick = rng.integers(len(points)) if total <= 0 else rng.choice(len(points), p=gaps / total)
        centres.append(points[pick])
    centre = np.array(centres, dtype=np.float64)
    labels = np.zeros(len(points), dtype=np.int64)
    for _ in range(20):
        labels = np.argmin(((points[:, None, :] - centre[None]) ** 2).sum(-1), axis=1)
        moved = centre.copy()
        for j in range(k):
            members = points[labels == j]
            if len(members):
                moved[j] = members.mean(axis=0)
        if np.allclose(moved, centre):
            break
        centre = moved
    return labels


def _m_step(
    points: np.ndarray, resp: np.ndarray, reg: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    counts = resp.sum(axis=0) + 10 * np.finfo(float).eps
    means = resp.T @ points / counts[:, None]
    covariances = np.empty((resp.shape[1], 2, 2))
    for j in range(resp.shape[1]):
        diff = points - means[j]
        covariances[j] = (resp[:, j, None] * diff).T @ diff / counts[j] + reg * np.eye(2)
    return counts / len(points), means, covariances


def fit_mixture(
    points: np.ndarray,
    k: int,
    *,
    reg: float,
    seed: int = 0,
    n_init: int = 2,
    tol: float = 1e-3,
    max_iter: int = 100,
) -> Mixture:
    """The best of `n_init` EM runs of a K-component full-covariance mixture on (N, 2) points;
    `reg` (units²) is added to every covariance's diagonal."""
    points = np.asarray(points, dtype=np.float64)
    rng = np.random.default_rng(seed)
    best: Mixture | None = None
    for _ in range(n_init):
        labels = _seed_labels(points, k, rng)
        resp = np.zeros((len(points), k))
        resp[np.arange(len(points)), labels] = 1.0
        previous = -math.inf
        total = -math.inf
        for _ in range(max_iter):
            weights, means, covariances = _m_step(points, resp, reg)
            log_p = _log_densities(points, means, covariances) + np.log(weights)[None]
            top = log_p.max(axis=1, keepdims=True)
            log_sum = top[:, 0] + np.log(np.exp(log_p - top).sum(axis=1))
            resp = np.exp(log_p - log_sum[:, None])
            total = float(log_sum.sum())
            if abs(total - previous) / len(points) < tol:
                break
            previous = total
        weights, means, covariances = _m_step(points, resp, reg)
        log_p = _log_densities(points, means, covariances) + np.log(weights)[None]
        top = log_p.max(axis=1, keepdims=True)
        total = float((top[:, 0] + np.log(np.exp(log_p - top).sum(axis=1))).sum())
        if best is None or total > best.log_likelihood:
            best = Mixture(weights, means, covariances, total)
    if best is None:
        raise ValueError(f"n_init must be ≥ 1, got {n_init}")
    return best
