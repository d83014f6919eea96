"""A small dense QP: least squares in a joint step with linear equalities and box bounds."""

from __future__ import annotations

import numpy as np
import scipy.linalg.lapack

__all__ = ["solve_box_qp"]

_gesv = scipy.linalg.lapack.dgesv
_DIAG = np.arange(256)
_ROUNDING = 1e-13  # a full step this far past a bound (rad) is rounding, not a blocking bound


def solve_box_qp(
    hessian: np.ndarray,
    gradient: np.ndarray,
    eq_matrix: np.ndarray,
    eq_rhs: np.ndarray,
    eq_slack: np.ndarray,
    lower: np.ndarray,
    upper: np.ndarray,
    fixed_hint: np.ndarray | None = None,
    max_iterations: int = 40,
) -> tuple[np.ndarray, np.ndarray]:
    """Minimise ½·xᵀHx − gᵀx subject to C·x = c (regularised) and lower ≤ x ≤ upper.

    The equality is regularised as C·x − diag(s)·ν = c (a quasi-definite KKT system), i.e. a
    penalty of weight 1/sᵢ on row i: it stays solvable when the rows are rank-deficient or
    incompatible with the box, and is met to O(s) when feasible. A primal active-set method
    (feasible iterates from x = 0, step to the first blocking bound, release of the bound with
    the most wrongly signed multiplier) solves the box part. Units are the caller's (here rad).

    Args:
        hessian: H, n×n symmetric positive definite.
        gradient: g, n.
        eq_matrix: C, m×n (m may be 0).
        eq_rhs: c, m.
        eq_slack: s, m positive regularisation weights.
        lower, upper: n-vectors of bounds with lower ≤ 0 ≤ upper (x = 0 is the start).
        fixed_hint: optional boolean n-vector of variables expected at a bound whose value is
            0 (e.g. joints resting on a limit); they start fixed and are released if wrong.
        max_iterations: active-set changes allowed before the iterate is clipped and returned.

    Returns:
        (x, ν): x always within [lower, upper]; ν the multipliers of the equality rows, so that
        H·x − g + Cᵀ·ν vanishes on the variables not at a bound.
    """
    n = gradient.shape[0]
    m = eq_rhs.shape[0]
    kkt = np.empty((n + m, n + m))
    kkt[:n, :n] = hessian
    kkt[:n, n:] = eq_matrix.T
    kkt[n:, :n] = eq_matrix
    kkt[n:, n:] = 0.0
    kkt[_DIAG[n : n + m], _DIAG[n : n + m]] = -eq_slack
    rhs = np.concatenate((gradient, eq_rhs))
    if fixed_hint is None:
        fixed = np.zeros(n, dtype=bool)
        n_fixed = 0
    else:
        fixed = fixed_hint.copy()
        n_fixed = int(np.count_nonzero(fixed))
    # Which bound a fixed variable sits on: +1 upper, -1 lower (hinted ones: the bound at 0).
    side = np.where(upper <= 0.0, 1.0, -1.0)
    pinned = lower >= upper  # a zero-width box: never released
    x = np.zeros(n)
    for _ in range(max_iterations):
        # Minimiser with the fixed variables held at their current (bound) values: their KKT
        # rows become identity rows.
        if n_fixed:
            fix_idx = fixed.nonzero()[0]
            system = kkt.copy()
            system[fix_idx] = 0.0
            system[fix_idx, fix_idx] = 1.0
            sys_rhs = rhs.copy()
            sys_rhs[fix_idx] = x[fix_idx]
            _, _, sol, info = _gesv(system, sys_rhs, overwrite_a=1, overwrite_b=1)
            sol[fix_idx] = x[fix_idx]
        else:
            _, _, sol, info = _gesv(kkt, rhs)
        if info != 0:
            raise np.linalg.LinAlgError(f"singular KKT system in solve_box_qp (info={info})")
        target = sol[:n]
        # Free variables whose full step leaves the box: step to the first bound they meet.
        outside = (target < lower - _ROUNDING) | (target > upper + _ROUNDING)
        if outside.any():
            idx = outside.nonzero()[0]
            step = target[idx] - x[idx]
            bound = np.where(step < 0.0, lower[idx], upper[idx])
            ratios = (bound - x[idx]) / step
            k = int(ratios.argmin())
            block = int(idx[k])
            x = np.minimum(np.maximum(x + ratios[k] * (target - x), lower), upper)
            x[block] = bound[k]
            side[block] = 1.0 if step[k] > 0.0 else -1.0
            fixed[block] = True
            n_fixed += 1
            continue
        x = np.minimum(np.maximum(target, lower), upper)
        if not n_fixed:
            return x, sol[n:]
        # Multiplier of a fixed variable = its Lagrangian gradient (H·x − g + Cᵀν). Holding it
        # is right when that gradient pushes against the bound: ≥ 0 at lower, ≤ 0 at upper.
        grad = kkt[fix_idx] @ sol - gradient[fix_idx]
        wrong = np.where(pinned[fix_idx], -np.inf, side[fix_idx] * grad)
        worst = int(wrong.argmax())
        if wrong[worst] <= 1e-12:
            return x, sol[n:]
        fixed[fix_idx[worst]] = False
        n_fixed -= 1
    return np.minimum(np.maximum(x, lower), upper), sol[n:]
