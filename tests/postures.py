"""A small numerical IK on the MuJoCo scene, to find archery postures for tests and benchmarks.

The controller service owns the real IK (the paper's Eq. 9 with Pinocchio); this helper only
finds joint angles that put the hand sites at given positions (m, root frame), with the bow hand
oriented as `sim.scene` expects (grip vertical, back of the hand toward the string hand), by
bounded least squares over the 14 arm joints within the world's software limits, torso fixed.
"""

from __future__ import annotations

import mujoco
import numpy as np
from scipy.optimize import least_squares

from archery.protocol.robotspec import (
    BOW_ARM,
    BOW_HAND_FRAME,
    STRING_ARM,
    STRING_HAND_FRAME,
    home_of,
)
from archery.sim.errors import CommandError
from archery.sim.scene import ScenePhysics

__all__ = ["archery_posture"]

_ARMS = (BOW_ARM, STRING_ARM)


def archery_posture(
    model: mujoco.MjModel,
    bow_hand: np.ndarray,
    string_hand: np.ndarray,
    *,
    torso: np.ndarray | None = None,
    orientation_weight: float = 0.02,
    rest_weight: float = 0.01,
    tolerance: float = 1e-3,
) -> dict[str, np.ndarray]:
    """Joint angles (rad, per part) that put the hands at `bow_hand` and `string_hand` (m).

    Args:
        model: a scene from `sim.scene.build_scene`.
        bow_hand, string_hand: wanted `l_hand_dh_frame` / `r_hand_dh_frame` positions (m).
        torso: fixed torso angles (rad, YARP order); the home torso if None.
        orientation_weight: weight (per unit of axis error) of the bow-hand orientation terms.
        rest_weight: weight (per rad) pulling the arms toward the home posture.
        tolerance: largest accepted hand position error (m).

    Raises:
        CommandError: the positions are not finite 3-vectors or cannot be reached within
            `tolerance`; the message gives the residual error.
    """
    bow_hand = np.asarray(bow_hand, dtype=float)
    string_hand = np.asarray(string_hand, dtype=float)
    for name, value in (("bow_hand", bow_hand), ("string_hand", string_hand)):
        if value.shape != (3,) or not np.all(np.isfinite(value)):
            raise CommandError(f"{name} must be a finite 3-vector in metres, got {value!r}")
    physics = ScenePhysics(model)
    torso_q = np.asarray(home_of("torso") if torso is None else torso, dtype=float)
    physics.set_joint_positions("torso", torso_q)
    home = np.concatenate([home_of(p) for p in _ARMS])
    # The world's software limits: URDF limits shrunk by the joint stops' margin.
    margin = np.concatenate([physics.joint_margins(p) for p in _ARMS])
    lower = np.concatenate([physics.joint_limits(p)[0] for p in _ARMS]) + margin
    upper = np.concatenate([physics.joint_limits(p)[1] for p in _ARMS]) - margin
    theta = string_hand - bow_hand
    back_of_hand = theta / max(float(np.linalg.norm(theta)), 1e-9)  # bow hand +z → string hand
    down = np.array([0.0, 0.0, -1.0])  # bow hand +y: grip axis, thumb (−y) up

    def residual(q: np.ndarray) -> np.ndarray:
        physics.set_joint_positions(BOW_ARM, q[:7])
        physics.set_joint_positions(STRING_ARM, q[7:])
        physics.kinematics()
        rot = physics.site_rotation(BOW_HAND_FRAME)
        return np.concatenate(
            [
                physics.site_position(BOW_HAND_FRAME) - bow_hand,
                physics.site_position(STRING_HAND_FRAME) - string_hand,
                orientation_weight * (rot[:, 1] - down),
                orientation_weight * (rot[:, 2] - back_of_hand),
                rest_weight * (q - home),
            ]
        )

    start = np.clip(home, lower + 1e-6, upper - 1e-6)
    solution = least_squares(residual, start, bounds=(lower, upper), xtol=1e-12, ftol=1e-12)
    error = np.linalg.norm(residual(solution.x)[:6].reshape(2, 3), axis=1)
    if np.max(error) > tolerance:
        raise CommandError(
            f"hands cannot reach bow {bow_hand.round(3)} / string {string_hand.round(3)} m: "
            f"position errors {error.round(4)} m exceed {tolerance} m"
        )
    return {"torso": torso_q, BOW_ARM: solution.x[:7].copy(), STRING_ARM: solution.x[7:].copy()}
