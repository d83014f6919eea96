"""A small dense QP: least squares in a joint step with linear equalities and box bounds."""

from __future__ import annotations

import numpy as np
import scipy.linalg.lapack

__all__ = ["solve_box_qp"]

_gesv = scipy.linalg.lapack.dgesv
_DIAG = np.arange(256)


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
    fixed = np.zeros(n, dtype=bool) if fixed_hint is None else fixed_hint.copy()
    # Which bound a fixed variable sits on: +1 upper, -1 lower (hinted ones: the bound at 0).
    side = np.where(upper <= 0.0, 1.0, -1.0)
    pinned = lower >= upper  # a zero-width box: never released
    x = np.zeros(n)
    for _ in range(max_iterations):
        # Minimiser with the fixed variables held at their current (bound) values: their KKT
        # rows become identity rows.
        if fixed.any():
            fix_idx = np.flatnonzero(fixed)
            system = kkt.copy()
            system[fix_idx] = 0.0
            system[fix_idx, fix_idx] = 1.0
            sys_rhs = rhs.copy()
            sys_rhs[fix_idx] = x[fix_idx]
            _, _, sol, info = _gesv(system, sys_rhs)
            sol[fix_idx] = x[fix_idx]
        else:
            fix_idx = None
            _, _, sol, info = _gesv(kkt, rhs)
        if info != 0:
            raise np.linalg.LinAlgError(f"singular KKT system in solve_box_qp (info={info})")
        step = sol[:n] - x
        # Step to the first bound met by a free variable (ratio < 1 means it blocks).
        room = np.where(step < 0.0, lower - x, upper - x)
        size = np.abs(step)
        blocking = (size > np.abs(room)) & ~fixed
        if blocking.any():
            idx = np.flatnonzero(blocking)
            ratios = np.abs(room[idx]) / size[idx]
            k = int(np.argmin(ratios))
            block = int(idx[k])
            x = np.clip(x + ratios[k] * step, lower, upper)
            upward = step[block] > 0.0
            x[block] = upper[block] if upward else lower[block]
            side[block] = 1.0 if upward else -1.0
            fixed[block] = True
            continue
        x = np.clip(sol[:n], lower, upper)
        if fix_idx is None:
            return x, sol[n:]
        # Multiplier of a fixed variable = its Lagrangian gradient (H·x − g + Cᵀν). Holding it
        # is right when that gradient pushes against the bound: ≥ 0 at lower, ≤ 0 at upper.
        grad = kkt[fix_idx] @ sol - gradient[fix_idx]
        wrong = np.where(pinned[fix_idx], -np.inf, side[fix_idx] * grad)
        worst = int(np.argmax(wrong))
        if wrong[worst] <= 1e-12:
            return x, sol[n:]
        fixed[fix_idx[worst]] = False
    return x, sol[n:]
