"""The robot service: the simulated iCub's joint ports, bow, arrow and target on the mesh."""

from services.robot.commands import (
    REJECTION_REASONS,
    CommandRejected,
    PartCounters,
    PartLimits,
    check_command,
)
from services.robot.config import RobotConfig
from services.robot.simloop import SimLoop, SimUnavailable, phase_of
from services.robot.sink import Sink

__all__ = [
    "REJECTION_REASONS",
    "CommandRejected",
    "PartCounters",
    "PartLimits",
    "RobotConfig",
    "SimLoop",
    "SimUnavailable",
    "Sink",
    "check_command",
    "phase_of",
]
