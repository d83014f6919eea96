"""The exception hierarchy of the MuJoCo simulation (`sim.scene`, `sim.arrow`, `sim.world`)."""

from __future__ import annotations

__all__ = ["CommandError", "ConfigError", "SceneError", "SimError", "StateError"]


class SimError(Exception):
    """Base of every error raised by the MuJoCo simulation."""


class ConfigError(SimError, ValueError):
    """An invalid scene or world parameter; the message names it and its valid range."""


class SceneError(SimError, RuntimeError):
    """The scene cannot be built (model file missing, unexpected URDF content)."""


class CommandError(SimError, ValueError):
    """A bad command: unknown part or joint, wrong vector length, non-finite value."""


class StateError(SimError, RuntimeError):
    """A command that the world's current state does not allow (e.g. release with no arrow)."""
