"""The controller core's exceptions, under the project's `ArcheryError` (codes for RPC replies)."""

from __future__ import annotations

from archery.protocol import errors as project

__all__ = ["ControllerError", "JointError", "TargetError"]


class ControllerError(project.ArcheryError, ValueError):
    """Base of the controller's errors; each message names the bad value and what is valid."""

    code = "controller_error"


class JointError(ControllerError, project.BadRequest):
    """An unknown joint name or arm, a wrong-length joint vector, a non-finite joint angle."""

    code = "bad_request"


class TargetError(ControllerError, project.BadRequest):
    """A target that cannot be posed as a problem: wrong shape, NaN/inf, θ outside its bounds.

    A finite target the robot cannot reach is not an error: the solver returns its closest pose
    with `reachable=False`.
    """

    code = "bad_request"
