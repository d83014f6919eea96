"""Analytic derivatives the Eq. 9 IK needs beyond Pinocchio's Jacobians: the orientation
residual eₙ = log(R̂·Rᵀ) with its Jacobian, and the curvature of a hand position (for the
constraint term ν·∂²x/∂q² of the SQP's Lagrangian Hessian).
"""

from __future__ import annotations

import functools

import numpy as np
import pinocchio as pin

__all__ = [
    "orientation_residual",
    "orientation_residual_jacobian",
    "position_hessian_contraction",
]


def orientation_residual(target: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """eₙ = log(R̂·Rᵀ): axis-angle (rad, root axes) turning `rotation` R into `target` R̂."""
    return np.asarray(pin.log3(target @ rotation.T))


def orientation_residual_jacobian(
    target: np.ndarray, rotation: np.ndarray, angular_jacobian: np.ndarray
) -> np.ndarray:
    """∂eₙ/∂q = −Jlog(R̂Rᵀ)·J_ω, for J_ω the hand's angular Jacobian in root axes (3×n)."""
    result: np.ndarray = -np.asarray(pin.Jlog3(target @ rotation.T)) @ angular_jacobian
    return result


def position_hessian_contraction(weights: np.ndarray, jacobian: np.ndarray) -> np.ndarray:
    """Σₖ wₖ·∂²xₖ/∂q² for a frame on a revolute chain, from its 6×n Jacobian (LOCAL_WORLD_ALIGNED).

    Columns must be in ancestor-first order (Pinocchio's). For joints a ≤ b the second
    derivative of the frame position is z_a × v_b (z: joint axis, v: linear Jacobian column), so
    the contraction with w is (w × z_a)·v_b. Units: m per rad² times the units of w.
    """
    wx = np.array(
        [
            [0.0, -weights[2], weights[1]],
            [weights[2], 0.0, -weights[0]],
            [-weights[1], weights[0], 0.0],
        ]
    )
    pairs = (wx @ jacobian[3:]).T @ jacobian[:3]
    result: np.ndarray = np.where(_upper_mask(pairs.shape[0]), pairs, pairs.T)
    return result


@functools.lru_cache(maxsize=8)
def _upper_mask(n: int) -> np.ndarray:
    """Read-only boolean n×n mask of the upper triangle (diagonal included)."""
    mask = np.triu(np.ones((n, n), dtype=bool))
    mask.setflags(write=False)
    return mask
