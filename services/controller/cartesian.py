"""The cartesian controller's geometry of requests and replies, iKin style; pure (no Zenoh).

The request and reply types themselves, with their ranges, are in `protocol.verbs.controller`.

Positions are metres in `root_link`; orientations travel as iKin's axis-angle 4-vectors
[ax, ay, az, angle] (unit axis in root axes, angle in rad) and are turned into the rotation
vectors (axis × angle) that `ik.IkSolver` takes. Trajectory time T (s of simulated time) becomes
per-joint reference speeds |Δq|/T, so every joint of a move arrives together.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import numpy as np
import pinocchio as pin

from archery.protocol.robotspec import MAX_REFERENCE_SPEED
from archery.protocol.vectors import finite_vector
from archery.services.controller.errors import TargetError
from archery.services.controller.ik_types import IkResult

__all__ = ["MIN_REFERENCE_SPEED", "axis_angle", "ik_reply", "reference_speeds", "rotation_vector"]

MIN_REFERENCE_SPEED = 0.01  # rad/s, for joints that barely move


def rotation_vector(value: Any, name: str = "od") -> np.ndarray:
    """The rotation vector (rad) of an iKin axis-angle [ax, ay, az, angle] from a request.

    Raises:
        TargetError: not 4 finite numbers, or a zero axis with a non-zero angle.
    """
    vec = finite_vector(name, value, TargetError, size=4, unit="unit axis, then angle in rad")
    axis, angle = vec[:3], float(vec[3])
    norm = float(np.linalg.norm(axis))
    if norm < 1e-9:
        if angle == 0.0:
            return np.zeros(3)
        raise TargetError(f"{name} has a zero axis {axis.tolist()} with angle {angle} rad")
    return axis / norm * angle


def axis_angle(rotation: np.ndarray) -> list[float]:
    """iKin's [ax, ay, az, angle] (unit axis, angle in [0, π] rad) of a rotation matrix or a
    rotation vector (rad); the axis is +z for the identity."""
    rot = np.asarray(rotation, dtype=float)
    vec = np.asarray(pin.log3(rot)) if rot.shape == (3, 3) else rot
    angle = float(np.linalg.norm(vec))
    if angle < 1e-12:
        return [0.0, 0.0, 1.0, 0.0]
    return [*(vec / angle).tolist(), angle]


def reference_speeds(delta: np.ndarray, traj_time: float) -> np.ndarray:
    """Per-joint reference speeds (rad/s) that cover |Δq| (rad) in `traj_time` (s), kept in
    [MIN_REFERENCE_SPEED, MAX_REFERENCE_SPEED] (a move too large for T takes longer)."""
    speeds = np.abs(np.asarray(delta, dtype=float)) / traj_time
    result: np.ndarray = np.clip(speeds, MIN_REFERENCE_SPEED, MAX_REFERENCE_SPEED)
    return result


def ik_reply(result: IkResult, joints: Iterable[str]) -> dict[str, Any]:
    """The askForPose reply: q of the chain's joints (rad), x (m), o (axis-angle), errors."""
    return {
        "q": {name: float(result.q[name]) for name in joints},
        "x": result.x.tolist(),
        "o": axis_angle(result.orientation),
        "position_error_m": float(result.position_error_m),
        "orientation_error_rad": float(result.orientation_error_rad),
        "reachable": bool(result.reachable),
        "iterations": int(result.iterations),
    }
