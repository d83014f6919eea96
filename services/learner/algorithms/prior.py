"""ARCHER with a physics prior: a model of the shot aims, the rollouts correct it."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from archery.protocol.text import shown
from archery.protocol.theta import THETA_BOX, ThetaBox
from archery.services.learner.algorithms.base import (
    MAX_STD,
    Learner,
    LearnerConfigError,
    RestoreError,
    _finite_option,
)
from archery.services.learner.algorithms.impact_model import ImpactModel, PhysicalModel
from archery.services.learner.algorithms.model_fit import fit_parameters

__all__ = ["ArcherPrior"]

_JACOBIAN_STEP = 1e-5  # m, finite-difference step of the model's Jacobian dr/dθ
_NEWTON_ITERATIONS = 12
# Std (m, and m/m) added in quadrature to a transferred posterior: a prior on c about 4 noise
# stds wide, so that one rollout of the new world outweighs it ~16:1.
TRANSFER_OFFSET_STD = 0.02
TRANSFER_GAIN_STD = 0.5


class ArcherPrior(Learner):
    """Aim with a physics model, and learn from every rollout where it is wrong.

    The prediction of where θ puts the arrow is the model plus a learned linear residual,

        r̂(θ) = r_model(θ) + c + D (θ − θ0),

    with r_model the injected `model` (`impact_model.ImpactModel`; the registry's default is
    the ballistic model of `sim.ballistic` with nominal parameters, `BallisticModel`, built
    from the options `model_distance`, `model_stiffness`, `model_drag` and the prior stds
    `model_*_std`, which the learner's `options` include, so that a saved state restores it),
    c (m) an offset and D (m of r per m of θ) a correction of the model's Jacobian.

    A model of physical parameters p (`impact_model.PhysicalModel`; the ballistic model's are
    the range, the drag, a side wind and the bow's stiffness) is first fitted to the rollouts:
    `params` is the maximum a posteriori p under the model's prior (`model_fit.fit_parameters`),
    refitted after every rollout that did not land where the learner predicted. So a miss is
    explained by the physics that would cause it, and the next aim uses the Jacobian of that
    world: a linear residual learned from one rollout cannot change the Jacobian, and the
    nominal model's (2.2 m, no air) is too weak on a far target (with drag and a side wind it
    left the second arrow 7-70 cm off from 3 m on).

    (c, D) then takes what the fitted physics leaves: it has a Gaussian prior centred on 0
    (trust the model: std `prior_offset_std` for c, `prior_gain_std` for each entry of D) and a
    Bayesian linear regression on the residuals r_i − r_model(θ_i) of the rollouts (observation
    noise std `noise_std`, each rollout weighted 2^(−age/half_life) when `half_life` > 0) gives
    its posterior mean; the data override the prior wherever they disagree with the model.

    Each proposal is a Gauss-Newton solve of r̂(θ) = 0 from the best rollout so far (θ0 before
    the first): the step is the least-norm solution in the metric diag(draw_weight, 1, 1), which
    prefers changing the aim over the draw (the launch speed is the most nonlinear input), with
    the model's Jacobian by finite differences. So the first θ is the model's own aim and, with
    the offset c learned from the first rollout, the second corrects the model's error there.

    Safeguards, as in `Archer`: the total step is limited to a trust radius Δ (m) that doubles
    after a rollout that beats the best so far and halves (down to `min_step`) after one that
    does not; a nearly singular Jacobian J_model + D (σ_min < σ_max/max_cond) uses only its
    well-determined directions and, like a trust radius at its minimum, adds an exploratory step
    N(0, s²) with s = min(fallback_std, ‖r_best‖/σ_max(J)).

    A changing world: a rollout is a surprise when its residual lies further from the
    prediction than max(change_threshold, 4·noise_std) + change_gain·(its distance to the nearest
    earlier θ; 0 for the first). A surprise right after a rollout that was not one means the world
    changed (the model had been right, and a small step cannot explain a large miss): the
    rollouts before it are forgotten, and the trust radius starts afresh. While the model is still
    wrong (surprise after surprise) the data correct it instead. `change_threshold` = 0 turns the
    detection off.

    Transfer (`seed_from` a session in another world): the source's fitted p becomes the prior
    mean of p, and its posterior of (c, D), moved to this learner's θ0
    (c' = c + D(θ0' − θ0_source)), becomes the prior of (c, D), its covariance widened by
    `TRANSFER_OFFSET_STD` (c) and `TRANSFER_GAIN_STD` (each entry of D) in quadrature: the
    first proposal aims with the world and the residual learned there, and a few rollouts here
    override them wherever this world differs.

    Args:
        theta0: the θ (m) the Gauss-Newton solve of the first rollout starts from.
        rng: the random generator for the exploratory steps.
        model: where the model says θ puts the arrow (r in m).
        bounds: θ box (m).
        prior_offset_std: prior std of the offset c (m).
        prior_gain_std: prior std of each entry of the Jacobian correction D (m/m).
        noise_std: std of the observation noise on r assumed by the regression (m).
        half_life: age (rollouts) at which a rollout's weight halves; 0 keeps every weight 1.
        draw_weight: cost of changing the draw θ_x relative to the aim θ_y, θ_z (>= 1).
        change_threshold: smallest surprise (m) that signals a changed world; 0 disables it.
        change_gain: surprise (m of r) allowed per m of distance to the nearest earlier θ.
        trust_radius: initial trust radius Δ (m).
        min_step: smallest trust radius (m).
        max_step: largest trust radius (m).
        fallback_std: largest std of the exploratory step (m).
        max_cond: largest accepted condition number of J_model + D.
    """

    algorithm = "archer-prior"
    exploration_rollouts = 0

    def __init__(
        self,
        theta0: np.ndarray,
        *,
        rng: np.random.Generator,
        model: ImpactModel,
        bounds: ThetaBox = THETA_BOX,
        prior_offset_std: float = 0.5,
        prior_gain_std: float = 3.0,
        noise_std: float = 0.005,
        half_life: float = 0.0,
        draw_weight: float = 4.0,
        change_threshold: float = 0.03,
        change_gain: float = 5.0,
        trust_radius: float = 0.05,
        min_step: float = 0.001,
        max_step: float = 0.1,
        fallback_std: float = 0.004,
        max_cond: float = 50.0,
    ) -> None:
        super().__init__(theta0, rng=rng, bounds=bounds)
        self.model = model
        self.prior_offset_std = _finite_option("prior_offset_std (m)", prior_offset_std, low=1e-9)
        self.prior_gain_std = _finite_option("prior_gain_std", prior_gain_std, low=1e-9)
        self.noise_std = _finite_option("noise_std (m)", noise_std, low=1e-9)
        self.half_life = _finite_option("half_life (rollouts)", half_life, low=0.0)
        self.draw_weight = _finite_option("draw_weight", draw_weight, low=1.0)
        self.change_threshold = _finite_option("change_threshold (m)", change_threshold, low=0.0)
        self.change_gain = _finite_option("change_gain", change_gain, low=0.0)
        self.min_step = _finite_option("min_step (m)", min_step, low=0.0)
        self.max_step = _finite_option(
            "max_step (m)", max_step, low=max(self.min_step, 1e-9), high=MAX_STD
        )
        self.trust_radius = _finite_option(
            "trust_radius (m)", trust_radius, low=max(self.min_step, 1e-9), high=self.max_step
        )
        self.fallback_std = _finite_option("fallback_std (m)", fallback_std, low=0.0, high=MAX_STD)
        self.max_cond = _finite_option("max_cond", max_cond, low=1.0)
        self._radius0 = self.trust_radius
        self._metric = np.ones(self.theta0.size)
        self._metric[0] = self.draw_weight
        self._residuals: list[np.ndarray | None] = []
        self.forget_before = 0  # rollouts before this index are forgotten (a changed world)
        self.changes: list[int] = []  # 0-based indices of the rollouts that revealed a change
        self.settled = False  # the last rollout landed where the learner predicted
        # Prior of (c, D) as rows [c; Dᵀ] (mean (d+1, 2), covariance (d+1, d+1)); a transfer sets
        # it, else it is centred on 0 with the prior stds.
        self._prior: tuple[np.ndarray, np.ndarray] | None = None
        # The physical parameters p: their prior mean (the model's nominal ones, or a transferred
        # fit) and the current fit; None for a model without them.
        self.params_mean: np.ndarray | None = None
        self.params: np.ndarray | None = None
        if isinstance(model, PhysicalModel):
            self.params_mean = np.asarray(model.nominal(), dtype=float)
            self.params = self.params_mean.copy()

    def options(self) -> dict[str, Any]:
        """Constructor options as plain values, the model's (`ImpactModel.options`) first."""
        return self.model.options() | {
            "prior_offset_std": self.prior_offset_std,
            "prior_gain_std": self.prior_gain_std,
            "noise_std": self.noise_std,
            "half_life": self.half_life,
            "draw_weight": self.draw_weight,
            "change_threshold": self.change_threshold,
            "change_gain": self.change_gain,
            "trust_radius": self._radius0,
            "min_step": self.min_step,
            "max_step": self.max_step,
            "fallback_std": self.fallback_std,
            "max_cond": self.max_cond,
        }

    # -- the model ------------------------------------------------------------------------------

    def model_impacts(self, thetas: np.ndarray) -> np.ndarray:
        """r_model (m) of the θ rows (m): the model with the fitted parameters `params`.

        Raises:
            ValueError: the model cannot shoot a θ.
        """
        if self.params is not None and isinstance(self.model, PhysicalModel):
            return np.asarray(self.model.impacts_at(thetas, self.params), dtype=float)
        return np.asarray(self.model.impacts(thetas), dtype=float)

    def model_jacobian(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """(r_model(θ), dr_model/dθ) of the model (m, m/m); None where it cannot shoot."""
        d = theta.size
        batch = np.vstack([theta, theta + _JACOBIAN_STEP * np.eye(d)])
        try:
            r = self.model_impacts(batch)
        except ValueError:
            return None
        return r[0], (r[1:] - r[0]).T / _JACOBIAN_STEP

    def _model_residual(self, theta: np.ndarray, r: np.ndarray) -> np.ndarray | None:
        try:
            result: np.ndarray | None = r - self.model_impacts(theta.reshape(1, -1))[0]
            return result
        except ValueError:
            return None

    def posterior(self, upto: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Posterior (mean, covariance) of the residual model's rows [c; Dᵀ] ((d+1, 2) and
        (d+1, d+1), the same covariance for both components of r), from the remembered rollouts
        before index `upto` (all by default)."""
        n = self.n_rollouts if upto is None else upto
        d = self.theta0.size
        if self._prior is None:
            precision = np.diag([self.prior_offset_std**-2] + [self.prior_gain_std**-2] * d)
            moment = np.zeros((d + 1, 2))
        else:
            precision = np.linalg.inv(self._prior[1])
            moment = precision @ self._prior[0]
        for i in range(self.forget_before, n):
            residual = self._residuals[i]
            if residual is None:
                continue
            weight = self._weight(i, n)
            phi = np.concatenate([[1.0], self._thetas[i] - self.theta0])
            precision += weight * np.outer(phi, phi) / self.noise_std**2
            moment += weight * np.outer(phi, residual) / self.noise_std**2
        covariance = np.linalg.inv(precision)
        return covariance @ moment, covariance

    def _weight(self, i: int, n: int) -> float:
        """The weight of rollout i among the first n: 2^(−age/half_life), or 1."""
        return 1.0 if self.half_life == 0 else 2.0 ** (-(n - 1 - i) / self.half_life)

    def correction(self, upto: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Posterior mean (c, D) of the residual r − r_model ≈ c + D(θ − θ0), from the remembered
        rollouts before index `upto` (all by default)."""
        mean = self.posterior(upto)[0]
        return mean[0], mean[1:].T

    def predict(self, theta: np.ndarray) -> np.ndarray | None:
        """r̂(θ) = r_model(θ) + c + D(θ − θ0) (m) with the current posterior mean."""
        theta = np.asarray(theta, dtype=float)
        evaluated = self.model_jacobian(theta)
        if evaluated is None:
            return None
        c, dmat = self.correction()
        result: np.ndarray | None = evaluated[0] + c + dmat @ (theta - self.theta0)
        return result

    # -- the algorithm --------------------------------------------------------------------------

    def _best_remembered(self) -> int | None:
        """Index of the best rollout not forgotten; None before any."""
        if self.n_rollouts <= self.forget_before:
            return None
        return self.forget_before + int(np.argmax(self.returns[self.forget_before :]))

    def _propose(self) -> np.ndarray:
        d = self.theta0.size
        best = self._best_remembered()
        centre = self.theta0 if best is None else self._thetas[best]
        c, dmat = self.correction()
        theta = centre.copy()
        scale = 1.0 / np.sqrt(self._metric)  # θ = centre + scale ⊙ u, least-norm in u
        ill = False
        gain = 0.0
        for _ in range(_NEWTON_ITERATIONS):
            evaluated = self.model_jacobian(theta)
            if evaluated is None:
                ill = True
                break
            r_model, jac = evaluated
            f = r_model + c + dmat @ (theta - self.theta0)
            jac_u = (jac + dmat) * scale
            u_mat, sing, vt = np.linalg.svd(jac_u, full_matrices=False)
            gain = float(sing[0] / scale.max()) if sing.size else 0.0
            keep = sing > sing[0] / self.max_cond if sing[0] > 1e-12 else np.zeros_like(sing, bool)
            ill = ill or not bool(np.all(keep))
            step_u = -(vt[keep].T / sing[keep]) @ (u_mat[:, keep].T @ f)
            target = theta + scale * step_u
            offset = target - centre
            norm = float(np.linalg.norm(offset))
            if norm > self.trust_radius:
                target = centre + offset * (self.trust_radius / norm)
            moved = float(np.linalg.norm(target - theta))
            theta = self.bounds.clip(target)
            if moved < 1e-10:
                break
        if ill or self.trust_radius <= self.min_step:
            # The model gives no direction, or keeps failing: explore on the scale of the θ
            # change the local gain says is still needed.
            needed = self.fallback_std
            if best is not None and gain > 1e-12:
                needed = float(np.linalg.norm(self._rewards[best])) / gain
            theta = theta + min(self.fallback_std, needed) * self.rng.standard_normal(d)
        return theta

    def _update(self, theta: np.ndarray, r: np.ndarray, big_return: float) -> None:
        self._judge(theta, r, big_return)
        if self.params is not None and not self.settled:
            self._refit()

    def _refit(self) -> None:
        """Fit p to the remembered rollouts (from the last fit), then recompute every residual
        against the model of the new p."""
        assert isinstance(self.model, PhysicalModel) and self.params is not None
        assert self.params_mean is not None
        n = self.n_rollouts
        kept = range(self.forget_before, n)
        self.params = fit_parameters(
            self.model,
            np.array([self._thetas[i] for i in kept]),
            np.array([self._rewards[i] for i in kept]),
            np.array([self._weight(i, n) for i in kept]),
            noise_std=self.noise_std,
            mean=self.params_mean,
            start=self.params,
        )
        self._residuals = [
            self._model_residual(t, r) for t, r in zip(self._thetas, self._rewards, strict=True)
        ]

    def _judge(self, theta: np.ndarray, r: np.ndarray, big_return: float) -> None:
        """Whether the rollout was a surprise (a changed world: forget the earlier ones), and the
        trust radius after it."""
        self._residuals.append(self._model_residual(theta, r))
        n = self.n_rollouts
        earlier = range(self.forget_before, n - 1)
        was_settled, self.settled = self.settled, False
        if self.change_threshold > 0 and self._residuals[-1] is not None:
            c, dmat = self.correction(upto=n - 1)
            surprise = float(np.linalg.norm(self._residuals[-1] - c - dmat @ (theta - self.theta0)))
            nearest = min(
                (float(np.linalg.norm(theta - self._thetas[i])) for i in earlier), default=0.0
            )
            allowed = max(self.change_threshold, 4.0 * self.noise_std) + self.change_gain * nearest
            self.settled = surprise <= allowed
            if not self.settled and was_settled and earlier:
                self.forget_before = n - 1
                self.changes.append(n - 1)
                self.trust_radius = self._radius0
                return
        if not earlier:
            return
        # Trust radius: grow after a rollout that improved on the best, shrink otherwise.
        if big_return > max(self._returns[self.forget_before : n - 1]):
            self.trust_radius = min(2.0 * self.trust_radius, self.max_step)
        else:
            self.trust_radius = max(0.5 * self.trust_radius, self.min_step)

    def _seed_from(self, source: Learner) -> None:
        assert isinstance(source, ArcherPrior)
        mean, covariance = source.posterior()
        d = self.theta0.size
        shift = np.eye(d + 1)  # [c'; D'ᵀ] = shift @ [c; Dᵀ] with c' = c + D(θ0' − θ0)
        shift[0, 1:] = self.theta0 - source.theta0
        widen = np.diag([TRANSFER_OFFSET_STD**2] + [TRANSFER_GAIN_STD**2] * d)
        self._prior = (shift @ mean, shift @ covariance @ shift.T + widen)
        if self.params is not None and source.params is not None:
            if source.params.shape != self.params.shape:
                raise LearnerConfigError(
                    f"the source's model has {source.params.size} physical parameters, this "
                    f"one's {self.params.size}"
                )
            self.params_mean = source.params.copy()
            self.params = source.params.copy()

    def _extra_state(self) -> dict[str, Any]:
        prior = None
        if self._prior is not None:
            prior = {"mean": self._prior[0].tolist(), "covariance": self._prior[1].tolist()}
        return {
            "trust_radius": self.trust_radius,
            "forget_before": self.forget_before,
            "changes": list(self.changes),
            "settled": self.settled,
            "prior": prior,
            "params": None if self.params is None else self.params.tolist(),
            "params_mean": None if self.params_mean is None else self.params_mean.tolist(),
        }

    def _load_extra_state(self, extra: dict[str, Any]) -> None:
        try:
            radius = float(extra["trust_radius"])
            forget = int(extra["forget_before"])
            changes = [int(i) for i in extra["changes"]]
            settled = extra["settled"]
        except (KeyError, TypeError, ValueError) as exc:
            raise RestoreError(
                "archer-prior state needs 'trust_radius', 'forget_before', 'changes', "
                f"'settled': {exc}"
            ) from exc
        if not math.isfinite(radius) or not self.min_step <= radius <= self.max_step:
            raise RestoreError(
                f"archer-prior trust_radius {radius!r} m is outside "
                f"[{self.min_step}, {self.max_step}]"
            )
        if not 0 <= forget <= max(self.n_rollouts - 1, 0):
            raise RestoreError(f"archer-prior forget_before {forget} is outside the history")
        self.trust_radius = radius
        self.forget_before = forget
        if not isinstance(settled, bool):
            raise RestoreError(f"archer-prior 'settled' must be true or false, got {settled!r}")
        self.changes = changes
        self.settled = settled
        self._prior = _prior_of(extra.get("prior"), self.theta0.size)
        if self.params is not None and self.params_mean is not None:
            # A state saved before the parameters were fitted keeps the nominal ones.
            self.params_mean = _params_of(extra.get("params_mean"), self.params_mean)
            self.params = _params_of(extra.get("params"), self.params)
        # The residuals are a function of the history and the model: recompute them.
        self._residuals = [
            self._model_residual(t, r) for t, r in zip(self._thetas, self._rewards, strict=True)
        ]


def _prior_of(saved: Any, d: int) -> tuple[np.ndarray, np.ndarray] | None:
    """A saved transferred prior (mean, covariance) of [c; Dᵀ], checked; None if there is none."""
    if saved is None:
        return None
    try:
        mean = np.array(saved["mean"], dtype=float)
        covariance = np.array(saved["covariance"], dtype=float)
    except (KeyError, TypeError, ValueError) as exc:
        raise RestoreError(f"archer-prior prior needs 'mean' and 'covariance': {exc}") from exc
    if mean.shape != (d + 1, 2) or covariance.shape != (d + 1, d + 1):
        raise RestoreError(
            f"archer-prior prior must be a ({d + 1}, 2) mean and a ({d + 1}, {d + 1}) covariance"
        )
    if not (np.all(np.isfinite(mean)) and np.all(np.isfinite(covariance))):
        raise RestoreError("archer-prior prior holds a non-finite value")
    if not np.allclose(covariance, covariance.T) or np.linalg.eigvalsh(covariance).min() <= 0:
        raise RestoreError("archer-prior prior covariance must be symmetric positive definite")
    return mean, covariance


def _params_of(saved: Any, default: np.ndarray) -> np.ndarray:
    """Saved physical parameters, checked against the model's count; `default` if none."""
    if saved is None:
        return default
    try:
        params = np.array(saved, dtype=float)
    except (TypeError, ValueError) as exc:
        raise RestoreError(f"archer-prior physical parameters are not numbers: {exc}") from exc
    if params.shape != default.shape or not np.all(np.isfinite(params)):
        raise RestoreError(
            f"archer-prior physical parameters must be {default.size} finite numbers, "
            f"got {shown(saved)}"
        )
    return params
