"""The spaces of the archery task as Gymnasium sees it, and the check of an action.

Action: θ, the string hand's position relative to the bow hand, a `Box` of shape (3,) in metres
(float64) built from the world's `protocol.theta.ThetaBox` (the controller's on the iCub; on the
analytic world `THETA_BOX` unless the environment is given another). `checked_action` is where
θ enters an environment: its check of an action.

Observation: a `Box` of shape (5,), float64, metres: `[r_y, r_z, θ_x, θ_y, θ_z]`, the last
measured r (the arrow's offset from the centre on the target plane: r[0] to the robot's right,
r[1] up; unbounded) and the last θ shot (inside the action box). After `reset`, before any shot,
r is (0, 0) and θ the episode's start θ (`info["shots"]` is 0 then). A bad action: `BadAction`.
"""

from __future__ import annotations

import math

import numpy as np
from gymnasium import spaces
from gymnasium.error import InvalidAction

from archery.protocol.text import shown
from archery.protocol.theta import ThetaBox

__all__ = [
    "OBSERVATION_FIELDS",
    "BadAction",
    "action_space",
    "checked_action",
    "observation",
    "observation_space",
]

#: What each component of an observation is (all in metres).
OBSERVATION_FIELDS = ("r_y", "r_z", "theta_x", "theta_y", "theta_z")


class BadAction(InvalidAction, ValueError):
    """An action that is not 3 finite numbers (θ, m): Gymnasium's `InvalidAction` for an action
    not in the space, and a ValueError; its message quotes the action cut (`protocol.text`)."""


def action_space(bounds: ThetaBox) -> spaces.Box:
    """θ's box (m) as a float64 `Box`."""
    return spaces.Box(
        low=np.array(bounds.low, dtype=np.float64),
        high=np.array(bounds.high, dtype=np.float64),
        dtype=np.float64,
    )


def observation_space(bounds: ThetaBox) -> spaces.Box:
    """The observation's `Box`: r (m) unbounded, θ (m) in `bounds`."""
    low = np.array([-math.inf, -math.inf, *bounds.low], dtype=np.float64)
    high = np.array([math.inf, math.inf, *bounds.high], dtype=np.float64)
    return spaces.Box(low=low, high=high, dtype=np.float64)


def observation(r: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """`[r_y, r_z, θ_x, θ_y, θ_z]` (m) from r (2,) and θ (3,)."""
    return np.concatenate([np.asarray(r, dtype=np.float64), np.asarray(theta, dtype=np.float64)])


def checked_action(action: object, space: spaces.Box) -> tuple[np.ndarray, bool]:
    """(θ to shoot, whether it was clipped) for an agent's action: a finite 3-vector in metres,
    clipped into `space` (Gymnasium's convention for continuous boxes) and never sent raw.

    Raises:
        BadAction: the action is not 3 numbers, or holds a NaN or an infinity (named), before
            anything moves.
    """
    size = _size(action)
    if size is not None and size > space.shape[0]:  # refused before a long one is copied
        raise BadAction(f"action must be 3 numbers (θ in m), got {size}: {shown(action)}")
    try:
        theta = np.array(action, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError, OverflowError):
        raise BadAction(f"action must be 3 numbers (θ in m), got {shown(action)}") from None
    if theta.shape != space.shape:
        raise BadAction(f"action must be 3 numbers (θ in m), got {theta.size}: {shown(action)}")
    bad = np.flatnonzero(~np.isfinite(theta))
    if bad.size:
        i = int(bad[0])
        raise BadAction(
            f"action {theta.tolist()} m holds {float(theta[i])!r} at index {i}: θ must be finite; "
            "nothing was moved"
        )
    clipped = np.clip(theta, space.low, space.high)
    return clipped, bool(np.any(clipped != theta))


def _size(action: object) -> int | None:
    """How many numbers an array holds, or items a list or tuple (at least its numbers' count
    when nested as (1, 3) or (3, 1)); None for anything else."""
    if isinstance(action, np.ndarray):
        return int(action.size)
    if isinstance(action, list | tuple):
        return len(action)
    return None
