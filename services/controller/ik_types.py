"""Value types of the Eq. 9 IK (`services.controller.ik`): its settings, the targets callers
pass, the results it returns and the resolved tasks the solver iterates on.

Units: positions in metres (root_link frame: x backward, y to the robot's right, z up),
angles in radians, orientations as axis-angle 3-vectors (rad, root axes) or 3×3 rotations.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any

import numpy as np
import pinocchio as pin

from archery.protocol.errors import ConfigError
from archery.services.controller.errors import TargetError
from archery.services.controller.model import check_arm

__all__ = [
    "FrameJacobian",
    "IkResult",
    "IkSettings",
    "OrientationTarget",
    "OrientationTask",
    "PositionTarget",
    "PositionTask",
    "RestTask",
    "TargetsResult",
    "as_rotation",
]


def _matrix3(value: Any, name: str) -> np.ndarray:
    """A symmetric positive semi-definite 3×3 matrix (read-only), or ConfigError."""
    mat = np.array(value, dtype=float)
    if mat.shape != (3, 3) or not np.all(np.isfinite(mat)):
        raise ConfigError(f"{name} must be a finite 3×3 matrix, got {value!r}")
    if not np.allclose(mat, mat.T, atol=1e-12):
        raise ConfigError(f"{name} must be symmetric, got {value!r}")
    if np.linalg.eigvalsh(mat).min() < -1e-12:
        raise ConfigError(f"{name} must be positive semi-definite, got {value!r}")
    mat.setflags(write=False)
    return mat


@dataclass(frozen=True)
class IkSettings:
    """Weights and tolerances of the Eq. 9 problem (the paper used identity covariances).

    Attributes:
        orientation_weight: w1 (per rad²), ≥ 0.
        rest_weight: w2 (per rad²), ≥ 0.
        sigma_x: Σx, 3×3 PSD weighting of the position error in the constraint.
        sigma_n: Σn, 3×3 PSD weighting of the orientation error (rad) in the cost.
        sigma_q: Σq as per-joint diagonal weights {joint: weight ≥ 0}; unnamed joints weigh 1.
        position_tolerance: the constraint holds when (x̂−x)ᵀΣx(x̂−x) < position_tolerance²,
            i.e. ε = position_tolerance² (m²); must be > 0.
        max_iterations: Gauss–Newton iterations (each one Jacobian evaluation), ≥ 1.
        max_step: per-joint trust region of one iteration (rad), > 0.
        step_tolerance: converged when the constraint holds and no joint moved more than
            this in the last iteration (rad), ≥ 0.
        cost_tolerance: ... or when the cost fell by less than this (rad²), ≥ 0.
        damping: initial Levenberg–Marquardt damping (per rad²), > 0.
        restarts: when the constraint is not met from the start posture, retry from this many
            random in-limit postures of the moving joints, ≥ 0.
        seed: seed of those restart postures (the same call always gives the same result).
        limit_margin: every joint's URDF range shrinks by this much at both ends (rad),
            0 ≤ margin < 0.1, so solutions stay inside a robot's software limits.
    """

    orientation_weight: float = 1.0
    rest_weight: float = 0.01
    sigma_x: Any = field(default_factory=lambda: np.eye(3))
    sigma_n: Any = field(default_factory=lambda: np.eye(3))
    sigma_q: Mapping[str, float] = field(default_factory=dict)
    position_tolerance: float = 1e-4
    max_iterations: int = 100
    max_step: float = 0.4
    step_tolerance: float = 1e-3
    cost_tolerance: float = 1e-7
    damping: float = 1e-4
    restarts: int = 4
    seed: int = 0
    limit_margin: float = 0.0

    def __post_init__(self) -> None:
        margin = self.limit_margin
        if not (isinstance(margin, int | float) and math.isfinite(margin) and 0 <= margin < 0.1):
            raise ConfigError(f"limit_margin must be a number in [0, 0.1) rad, got {margin!r}")
        for name in ("orientation_weight", "rest_weight", "step_tolerance", "cost_tolerance"):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value >= 0):
                raise ConfigError(f"{name} must be a finite number >= 0, got {value!r}")
        for name in ("position_tolerance", "max_step", "damping"):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise ConfigError(f"{name} must be a finite number > 0, got {value!r}")
        for name in ("restarts", "seed"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 0:
                raise ConfigError(f"{name} must be an integer >= 0, got {value!r}")
        if (
            isinstance(self.max_iterations, bool)
            or not isinstance(self.max_iterations, int)
            or self.max_iterations < 1
        ):
            raise ConfigError(
                f"max_iterations must be an integer >= 1, got {self.max_iterations!r}"
            )
        object.__setattr__(self, "sigma_x", _matrix3(self.sigma_x, "sigma_x"))
        object.__setattr__(self, "sigma_n", _matrix3(self.sigma_n, "sigma_n"))
        weights = dict(self.sigma_q)
        for joint, weight in weights.items():
            if not (isinstance(weight, int | float) and math.isfinite(weight) and weight >= 0):
                raise ConfigError(
                    f"sigma_q[{joint!r}] must be a finite number >= 0, got {weight!r}"
                )
        object.__setattr__(self, "sigma_q", MappingProxyType(weights))


@dataclass(frozen=True)
class PositionTarget:
    """A hard position constraint on a hand frame (m, root frame): `position`, 3 finite numbers
    its caller checked (a decoded request, `IkSolver.solve`, a validated config), kept as a
    read-only float array.

    With `relative_to` set, the constrained quantity is x_arm − x_relative_to (the hand's position
    relative to the other hand); otherwise x_arm. When several constraints cannot all be met, a
    higher `priority` (0, 1 or 2) is met first.
    """

    arm: str
    position: Any
    relative_to: str | None = None
    priority: int = 0

    def __post_init__(self) -> None:
        check_arm(self.arm)
        if self.relative_to is not None:
            check_arm(self.relative_to)
            if self.relative_to == self.arm:
                raise TargetError(f"relative_to must be the other arm, got {self.relative_to!r}")
        if self.priority not in (0, 1, 2):
            raise ConfigError(f"priority must be 0, 1 or 2, got {self.priority!r}")
        position = np.array(self.position, dtype=float)
        position.setflags(write=False)
        object.__setattr__(self, "position", position)


@dataclass(frozen=True)
class OrientationTarget:
    """A desired hand orientation, part of the cost with weight w1·`weight`.

    `orientation` is an axis-angle 3-vector (rad, root axes) or a 3×3 rotation matrix.
    """

    arm: str
    orientation: Any
    weight: float = 1.0

    def __post_init__(self) -> None:
        check_arm(self.arm)
        if not (
            isinstance(self.weight, int | float) and math.isfinite(self.weight) and self.weight >= 0
        ):
            raise ConfigError(
                f"orientation weight must be a finite number >= 0, got {self.weight!r}"
            )
        object.__setattr__(self, "orientation", as_rotation(self.orientation))


@dataclass(frozen=True)
class TargetsResult:
    """Outcome of `IkSolver.solve_targets`.

    Attributes:
        q: posture {joint: rad} for all 17 joints (joints not solved keep their clipped q0).
        q_vector: the same in `JOINT_NAMES` order (read-only).
        position_errors_m: ‖x̂ − x(q)‖ per position target, in the given order (m).
        orientation_errors_rad: rotation angle still needed per orientation target (rad).
        cost: the Eq. 9 cost at q (rad²).
        reachable: every position constraint holds.
        iterations: Gauss–Newton iterations used.
    """

    q: Mapping[str, float]
    q_vector: np.ndarray
    position_errors_m: tuple[float, ...]
    orientation_errors_rad: tuple[float, ...]
    cost: float
    reachable: bool
    iterations: int


@dataclass(frozen=True)
class IkResult:
    """Outcome of `IkSolver.solve` for one hand.

    Attributes:
        q: posture {joint: rad} for all 17 joints (joints off the chain keep their clipped q0).
        x: hand position reached (m, root frame).
        orientation: hand orientation reached, axis-angle (rad, root axes).
        position_error_m: ‖x̂ − x‖ (m, Euclidean; the constraint itself weighs it by Σx).
        orientation_error_rad: angle of the rotation from the reached to the desired orientation
            (rad); 0 when no orientation was asked.
        reachable: the position constraint holds; when False, q is the closest pose found.
        iterations: Gauss–Newton iterations used.
    """

    q: Mapping[str, float]
    x: np.ndarray
    orientation: np.ndarray
    position_error_m: float
    orientation_error_rad: float
    reachable: bool
    iterations: int


def as_rotation(orientation: Any) -> np.ndarray:
    """A read-only rotation matrix from an axis-angle 3-vector (rad) or a 3×3 rotation matrix.

    Raises:
        TargetError: wrong shape, NaN/inf, or a 3×3 matrix that is not a proper rotation.
    """
    try:
        arr = np.array(orientation, dtype=float)
    except (TypeError, ValueError):
        raise TargetError(
            "orientation must be an axis-angle 3-vector (rad) or a 3×3 rotation, "
            f"got {orientation!r}"
        ) from None
    if not np.all(np.isfinite(arr)):
        raise TargetError(f"orientation must be finite (no NaN/inf), got {orientation!r}")
    if arr.shape == (3,):
        rot = pin.exp3(arr)
    elif arr.shape == (3, 3):
        if not np.allclose(arr @ arr.T, np.eye(3), atol=1e-6) or np.linalg.det(arr) < 0:
            raise TargetError(f"orientation matrix is not a proper rotation: {orientation!r}")
        rot = arr
    else:
        raise TargetError(
            "orientation must be an axis-angle 3-vector (rad) or a 3×3 rotation, "
            f"got shape {arr.shape}"
        )
    rot = np.array(rot)
    rot.setflags(write=False)
    return rot


@dataclass(frozen=True)
class PositionTask:
    """A `PositionTarget` resolved for the solver: the rows x̂ − (x_frame − x_reference) = 0.

    Attributes:
        frame: Pinocchio frame id of the constrained hand.
        reference: Pinocchio frame id of the hand the position is relative to; None when the
            position is in the root frame.
        target: x̂, the wanted position (m, root frame; relative when `reference` is set).
        slack: regularisation of the three equality rows (m² per unit multiplier): smaller is
            stiffer, so a higher-priority target gets a smaller slack.
    """

    frame: int
    reference: int | None
    target: np.ndarray
    slack: float


@dataclass(frozen=True)
class OrientationTask:
    """An `OrientationTarget` resolved for the solver: the cost term ‖S·log(R̂·R(q)ᵀ)‖².

    Attributes:
        frame: Pinocchio frame id of the hand.
        target: R̂, the wanted rotation (3×3, root axes).
        sqrt_weight: S, 3×3 with SᵀS = w·w1·Σn (per rad).
    """

    frame: int
    target: np.ndarray
    sqrt_weight: np.ndarray


@dataclass(frozen=True)
class RestTask:
    """The rest-posture cost term ‖Sq·(q̂ − q)‖² over the joints being solved.

    Attributes:
        target: q̂ of the active joints (rad, Pinocchio order).
        sqrt_weight: diagonal of Sq, √(w2·Σq) per active joint (per rad).
        hessian: diag(Sq²), the term's constant Gauss–Newton Hessian (per rad²).
    """

    target: np.ndarray
    sqrt_weight: np.ndarray
    hessian: np.ndarray


@dataclass(frozen=True)
class FrameJacobian:
    """One hand's Jacobian as it enters a position task's rows.

    Attributes:
        task: index of the `PositionTask` among the solve's position tasks.
        sign: +1 for the constrained hand, −1 for the hand it is relative to.
        jacobian: 6×n frame Jacobian over the active joints, rows (ẋ m/s, ω rad/s) in root
            axes (LOCAL_WORLD_ALIGNED), columns per rad/s.
    """

    task: int
    sign: float
    jacobian: np.ndarray
