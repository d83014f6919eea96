"""ARCHER, Augmented Reward CHainEd Regression (Section III-B, Eq. 5-6), with safeguards."""

from __future__ import annotations

from collections.abc import Sequence
from itertools import combinations
from typing import Any

import numpy as np

from archery.protocol.text import shown
from archery.protocol.theta import THETA_BOX, ThetaBox
from archery.services.learner.algorithms.base import (
    MAX_STD,
    Learner,
    LearnerConfigError,
    RestoreError,
    _count_option,
    _finite_option,
    _std_option,
)

__all__ = ["Archer"]

_SEED_POOL = 8  # a transfer picks ARCHER's seeds among the source's this many best rollouts


def _largest_singular(matrix: np.ndarray) -> float:
    return float(np.linalg.svd(matrix, compute_uv=False)[0])


class Archer(Learner):
    """ARCHER: regress the goal r_T = 0 on the N best reward vectors, map the weights to θ.

    The first `n_explore` rollouts explore at random around θ0 (std `explore_std`). After that,
    with the rollouts sorted by return (best first), r_1 closest to the centre:

    - Eq. 5: r_{1,T} = Σ_i w_i r_{1,i+1}, solved as W = r_{1,T} U^† (least norm; with `ridge` > 0
      the footnote's ridge regression W = r_{1,T} Uᵀ(UUᵀ + λI)⁻¹);
    - Eq. 6: θ_next = θ_1 + Σ_i w_i θ_{1,i+1}.

    With `safeguard=False` this is the paper's algorithm. With `safeguard=True` (the default)
    two guards keep a session from running away when the linear model is not to be trusted:

    - an ill-conditioned U (the N best results nearly collinear: σ_min(U) < σ_max(U)/max_cond)
      uses the truncated pseudo-inverse (only the well-determined direction) and adds an
      exploratory step N(0, s²) to gather the missing information, with
      s = min(fallback_std, ‖r_1‖/g) and g = σ_max(U)/σ_max(Θ) the local gain (m of r per m of
      θ), so that the exploration shrinks as the arrows close in on the centre;
    - every regression step is limited to a trust radius Δ (m) that doubles after an aimed
      rollout that beats the best so far and halves (down to `min_step`) after one that does not,
      so a failed extrapolation is followed by a shorter one instead of the same one again; at
      `min_step` the exploratory step above is added too.

    Transfer (`seed_from` a session in another world): the source's best rollout and the N − 1 of
    its next best that span the best-conditioned U become the seeds, kept apart from the history
    as data of another world. The first rollout runs the
    source's best θ instead of the random exploration; until N rollouts of this world exist, each
    step is Eq. 5-6 with U and Θ from the seeds' differences (their local gain, which carries over
    between worlds) and r_{1,T} = −r of the best rollout of this world (their own r, from the
    other world, never enters), under the same trust radius and exploratory fallback. From N
    rollouts of this world on, the seeds are no longer used.

    With `window` > 0 the N best are chosen among the `window` most recent rollouts only (and the
    trust radius compares a rollout with those), so rollouts of a world that has since changed
    (a new wind) stop steering the regression after `window` rollouts.

    Args:
        theta0: initial θ (m), the centre of the exploratory rollouts.
        rng: the random generator for exploration.
        bounds: θ box (m).
        n_best: N, how many best rollouts the regression uses (>= 2; 3 in the paper).
        n_explore: number of initial random rollouts (>= n_best; 3 in the paper).
        explore_std: std of the initial exploration (m), one number or one per θ component.
            The default explores the draw (θ_x, string hand behind the bow hand) 5 mm and the
            aim (θ_y, θ_z) 20 mm: the launch speed, set by the draw, is the most nonlinear
            input of the shot, and a wide draw spread spoils the linear model of Eq. 5-6.
        ridge: λ of the footnote's ridge regression (m²); 0 gives the pseudo-inverse.
        safeguard: enable the ill-conditioning fallback and the trust radius.
        max_cond: largest accepted condition number σ_max/σ_min of U.
        fallback_std: largest std of the exploratory step of the safeguards (m).
        trust_radius: initial trust radius Δ (m).
        min_step: smallest trust radius (m).
        max_step: largest trust radius (m).
        window: choose the N best among this many most recent rollouts (>= n_best); 0: all.
    """

    algorithm = "archer"

    def __init__(
        self,
        theta0: np.ndarray,
        *,
        rng: np.random.Generator,
        bounds: ThetaBox = THETA_BOX,
        n_best: int = 3,
        n_explore: int = 3,
        explore_std: float | Sequence[float] = (0.005, 0.02, 0.02),
        ridge: float = 0.0,
        safeguard: bool = True,
        max_cond: float = 20.0,
        fallback_std: float = 0.004,
        trust_radius: float = 0.06,
        min_step: float = 0.002,
        max_step: float = 0.1,
        window: int = 0,
    ) -> None:
        super().__init__(theta0, rng=rng, bounds=bounds)
        self.n_best = _count_option("n_best (N)", n_best, low=2)
        self.n_explore = _count_option("n_explore", n_explore, low=self.n_best)
        self.explore_std = _std_option("explore_std (m)", explore_std, self.theta0.size)
        self.ridge = _finite_option("ridge (m²)", ridge, low=0.0)
        if not isinstance(safeguard, bool):
            raise LearnerConfigError(f"safeguard must be True or False, got {shown(safeguard)}")
        self.safeguard = safeguard
        self.max_cond = _finite_option("max_cond", max_cond, low=1.0)
        self.fallback_std = _finite_option("fallback_std (m)", fallback_std, low=0.0, high=MAX_STD)
        self.min_step = _finite_option("min_step (m)", min_step, low=0.0)
        self.max_step = _finite_option("max_step (m)", max_step, low=self.min_step, high=MAX_STD)
        self.trust_radius = _finite_option(
            "trust_radius (m)", trust_radius, low=self.min_step, high=self.max_step
        )
        self._radius0 = self.trust_radius
        self.window = _count_option("window", window, low=0)
        if 0 < self.window < self.n_best:
            raise LearnerConfigError(
                f"window must be 0 (all rollouts) or >= n_best ({self.n_best}), got {shown(window)}"
            )
        self.exploration_rollouts = self.n_explore
        self._seeds: tuple[np.ndarray, np.ndarray] | None = None  # (θ, r) of another world

    def options(self) -> dict[str, Any]:
        """Constructor options as plain values."""
        return {
            "n_best": self.n_best,
            "n_explore": self.n_explore,
            "explore_std": self.explore_std.tolist(),
            "ridge": self.ridge,
            "safeguard": self.safeguard,
            "max_cond": self.max_cond,
            "fallback_std": self.fallback_std,
            "trust_radius": self._radius0,
            "min_step": self.min_step,
            "max_step": self.max_step,
            "window": self.window,
        }

    def _propose(self) -> np.ndarray:
        d = self.theta0.size
        n = self.n_rollouts
        if self._seeds is not None and n < self.n_best:
            seed_thetas, seed_rewards = self._seeds
            if n == 0:
                result: np.ndarray = seed_thetas[0].copy()  # the other world's best θ
                return result
            # Seeds of another world: only their differences (the local gain) carry over.
            top = int(self._recent_ranked(n)[0])
            return self._step(
                self._thetas[top],
                -self._rewards[top],
                seed_rewards[1:] - seed_rewards[0],
                seed_thetas[1:] - seed_thetas[0],
            )
        if n < self.n_explore:
            # Initial phase: large random exploration around θ0.
            return self.theta0 + self.explore_std * self.rng.standard_normal(d)
        # Sort the rollouts by return, best first (R(τ_i) >= R(τ_i+1)); keep the N best.
        best = self._recent_ranked(n)[: self.n_best]
        thetas, rewards = self.thetas[best], self.rewards[best]
        # r_{1,T} = r_T − r_1 with r_T = (0, 0); U's rows are r_{1,i} = r_i − r_1, i = 2..N.
        return self._step(thetas[0], -rewards[0], rewards[1:] - rewards[0], thetas[1:] - thetas[0])

    def _step(
        self, theta_1: np.ndarray, r_1t: np.ndarray, u: np.ndarray, theta_1i: np.ndarray
    ) -> np.ndarray:
        """θ_next from θ_1 (Eq. 5-6, and the safeguards) for r_{1,T}, U and Θ = θ_{1,i}."""
        # Eq. 5: weights W with r_{1,T} = W U.
        weights, ill_conditioned = self._weights(u, r_1t)
        # Eq. 6: θ̂_{1,T} = Σ_i w_i θ_{1,i+1}.
        step: np.ndarray = weights @ theta_1i
        if not self.safeguard:
            unguarded: np.ndarray = theta_1 + step
            return unguarded
        # Safeguard 1: limit the extrapolation to the trust radius.
        norm = float(np.linalg.norm(step))
        if norm > self.trust_radius:
            step = step * (self.trust_radius / norm)
        # Safeguard 2: an ill-conditioned U leaves a direction unknown, and a trust radius shrunk
        # to its minimum means the model keeps failing; explore, on the scale of the θ change
        # that the local gain (m of r per m of θ) says is still needed.
        if ill_conditioned or self.trust_radius <= self.min_step:
            gain = _largest_singular(u) / max(_largest_singular(theta_1i), 1e-12)
            needed = float(np.linalg.norm(r_1t)) / gain if gain > 0 else self.fallback_std
            step = step + min(self.fallback_std, needed) * self.rng.standard_normal(theta_1.size)
        guarded: np.ndarray = theta_1 + step
        return guarded

    def _recent_ranked(self, end: int) -> np.ndarray:
        """Indices of the rollouts before `end` that the window keeps, best first."""
        start = max(0, end - self.window) if self.window else 0
        returns = self.returns[start:end]
        return start + np.argsort(-returns, kind="stable")

    def _weights(self, u: np.ndarray, r_1t: np.ndarray) -> tuple[np.ndarray, bool]:
        """W solving r_{1,T} = W U (Eq. 5), and whether U was ill-conditioned."""
        # U must have rank 2 (the reward's dimension) for the linear model to reach the goal.
        singular = np.linalg.svd(u, compute_uv=False)
        s_max = float(singular[0])
        ill = singular.size < u.shape[1] or s_max <= 1e-12 or singular[-1] * self.max_cond < s_max
        if self.ridge > 0.0:
            # The footnote's ridge regression: W = r_{1,T} Uᵀ (U Uᵀ + λI)⁻¹.
            gram = u @ u.T + self.ridge * np.eye(u.shape[0])
            return np.linalg.solve(gram, u @ r_1t), ill
        if self.safeguard and ill:
            if s_max <= 1e-12:
                return np.zeros(u.shape[0]), True
            # Truncated pseudo-inverse: only the directions U determines well.
            return r_1t @ np.linalg.pinv(u, rcond=1.0 / self.max_cond), True
        # The paper's least-norm solution W = r_{1,T} U^†.
        return r_1t @ np.linalg.pinv(u), ill

    def _update(self, theta: np.ndarray, r: np.ndarray, big_return: float) -> None:
        if not self.safeguard or self.n_rollouts <= self.exploration_rollouts:
            return
        # Trust radius: grow after an aimed rollout that improved on the best, shrink otherwise.
        previous = self._recent_ranked(self.n_rollouts - 1)[0]
        if big_return > self._returns[previous]:
            self.trust_radius = min(2.0 * self.trust_radius, self.max_step)
        else:
            self.trust_radius = max(0.5 * self.trust_radius, self.min_step)

    def _seed_from(self, source: Learner) -> None:
        # The source's best rollout, and the N − 1 of its next best that span the best-conditioned
        # U (a converged session's N best lie too close together to show the gain).
        ranked = source.ranked()[:_SEED_POOL]
        if ranked.size < self.n_best:
            raise LearnerConfigError(
                f"the source session has {ranked.size} rollouts; ARCHER's seeds need N = "
                f"{self.n_best}"
            )
        rewards = source.rewards
        best, pool = int(ranked[0]), [int(i) for i in ranked[1:]]

        def conditioning(others: tuple[int, ...]) -> float:
            u = rewards[list(others)] - rewards[best]
            singular = np.linalg.svd(u, compute_uv=False)
            return float(singular[-1]) if singular.size == u.shape[1] else 0.0

        others = max(combinations(pool, self.n_best - 1), key=conditioning)
        chosen = [best, *others]
        self._set_seeds(source.thetas[chosen], rewards[chosen])

    def _set_seeds(self, thetas: np.ndarray, rewards: np.ndarray) -> None:
        self._seeds = (self.bounds.clip(thetas), rewards.copy())
        self.exploration_rollouts = 1

    def _extra_state(self) -> dict[str, Any]:
        seeds = None
        if self._seeds is not None:
            seeds = {"thetas": self._seeds[0].tolist(), "rewards": self._seeds[1].tolist()}
        return {"trust_radius": self.trust_radius, "seeds": seeds}

    def _load_extra_state(self, extra: dict[str, Any]) -> None:
        try:
            radius = float(extra["trust_radius"])
        except (KeyError, TypeError, ValueError) as exc:
            raise RestoreError(f"ARCHER state needs a 'trust_radius' (m): {exc}") from exc
        if not np.isfinite(radius) or not self.min_step <= radius <= self.max_step:
            raise RestoreError(
                f"ARCHER trust_radius {radius!r} m is outside [{self.min_step}, {self.max_step}]"
            )
        self.trust_radius = radius
        seeds = extra.get("seeds")
        if seeds is None:
            return
        try:
            thetas = np.array(seeds["thetas"], dtype=float)
            rewards = np.array(seeds["rewards"], dtype=float)
        except (KeyError, TypeError, ValueError) as exc:
            raise RestoreError(f"ARCHER seeds need 'thetas' and 'rewards' (m): {exc}") from exc
        shape = (self.n_best, self.theta0.size)
        if thetas.shape != shape or rewards.shape != (self.n_best, 2):
            raise RestoreError(
                f"ARCHER seeds must be {self.n_best} θ {self.theta0.size}-vectors and "
                f"{self.n_best} r 2-vectors"
            )
        if not (np.all(np.isfinite(thetas)) and np.all(np.isfinite(rewards))):
            raise RestoreError("ARCHER seeds hold a number that is not finite")
        self._set_seeds(thetas, rewards)
