"""The arrow's direction for θ = p_string − p_bow (m): a = −θ/‖θ‖
(the controller's hand orientations, the bow's launch velocity, the MuJoCo arrow's launch)."""

from __future__ import annotations

import numpy as np

from archery.protocol.errors import ArcheryError

__all__ = ["MIN_THETA_NORM", "NoArrowDirection", "arrow_direction"]

MIN_THETA_NORM = 1e-9  # m: a shorter θ puts the string hand on the bow hand


class NoArrowDirection(ArcheryError, ValueError):
    """θ gives no arrow direction: the string hand is on the bow hand (‖θ‖ ≈ 0)."""

    code = "bad_state"


def arrow_direction(theta: np.ndarray) -> np.ndarray:
    """Unit arrow direction −θ/‖θ‖ (θ's frame) for θ = p_string − p_bow, a finite 3-vector (m).

    Raises:
        NoArrowDirection: ‖θ‖ < `MIN_THETA_NORM` (the hands coincide).
    """
    theta = np.asarray(theta, dtype=float)
    norm = float(np.linalg.norm(theta))
    if norm < MIN_THETA_NORM:
        raise NoArrowDirection(
            f"θ = {theta.tolist()} m puts the string hand on the bow hand: no arrow direction"
        )
    direction: np.ndarray = -theta / norm
    return direction
