"""The controller core's exception hierarchy: every bad input raises a `ControllerError`."""

from __future__ import annotations

__all__ = ["ConfigError", "ControllerError", "JointError", "TargetError"]


class ControllerError(ValueError):
    """Base class of the controller's errors; each message names the bad value and what is valid."""


class ConfigError(ControllerError):
    """An invalid solver or posture setting (weight, tolerance, covariance, bounds)."""


class JointError(ControllerError):
    """An unknown joint name, a non-finite joint angle or an unknown arm."""


class TargetError(ControllerError):
    """A target that cannot be posed as a problem: wrong shape, NaN/inf, θ outside its bounds.

    A finite target the robot cannot reach is not an error: the solver returns its closest pose
    with `reachable=False`.
    """
