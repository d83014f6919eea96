"""The exception hierarchy of the MuJoCo simulation, under the project's `ArcheryError` (an
invalid parameter is the project's `protocol.errors.ConfigError`)."""

from __future__ import annotations

from archery.protocol import errors as project

__all__ = [
    "ArrowDropped",
    "CommandError",
    "GraspMissed",
    "NockMissed",
    "SceneError",
    "SimError",
    "StateError",
]


class SimError(project.ArcheryError):
    """Base of every error raised by the MuJoCo simulation (sim.scene, sim.arrow, sim.world)."""

    code = "sim_error"


class SceneError(SimError, RuntimeError):
    """The scene cannot be built (model file missing, unexpected URDF content)."""

    code = "scene_error"


class CommandError(SimError, project.BadRequest):
    """A bad command: unknown part or site, wrong vector length, non-finite value."""

    code = "bad_request"


class StateError(SimError, RuntimeError):
    """A command that the world's current state does not allow (e.g. release with no arrow)."""

    code = "bad_state"


class GraspMissed(SimError):
    """The fingers closed farther from the arrow's shaft than the grasp tolerance: nothing is
    held, the arrow stays where it was (in its holder)."""

    code = "grasp_missed"


class NockMissed(SimError):
    """The arrow's nock is farther from the string's nocking point than the nock tolerance: the
    arrow stays in the hand, off the string."""

    code = "nock_missed"


class ArrowDropped(SimError):
    """The fingers opened on an arrow that was not on the string: it fell."""

    code = "arrow_dropped"
