"""The controller service's frozen, validated configuration and its command-line flags."""

from __future__ import annotations

import argparse
from dataclasses import dataclass, field, replace

from protocol.errors import ConfigError
from protocol.netflags import NetConfig
from protocol.robotspec import ROBOT_TIMEOUT
from protocol.service import config_number
from services.controller.ik import IkSettings
from services.controller.posture import PostureConfig

__all__ = ["LIMIT_MARGIN", "ControllerConfig", "add_controller_arguments", "config_from_args"]

# rad: IK solutions keep this far inside the URDF limits, more than the simulated robot's own
# margin (3 mrad), so the targets sent are never clamped by the robot.
LIMIT_MARGIN = 0.005


@dataclass(frozen=True)
class ControllerConfig:
    """Everything `archery controller` needs.

    Attributes:
        net: network settings (the common flags).
        ik: Eq. 9 settings of the single-arm controllers (left_arm, right_arm).
        posture: the archery posture (θ box, bow-hand position, its own IK settings).
        use_torso: the arm controllers start with the torso in their chain (setDOF changes it
            per arm); the posture's own `use_torso` says whether it moves the torso.
        traj_time: trajectory time T of a move (s of simulated time): each joint's reference
            speed is |Δq|/T, within the robot's bounds.
        motion_timeout: longest wait for the robot to report a move done (wall s).
        robot_timeout: longest wait for a joint state or a controlboard RPC reply (wall s).
        joint_tolerance: the robot is at the targets when motion is done and every joint is
            within this of its target (rad).
    """

    net: NetConfig = field(default_factory=NetConfig)
    ik: IkSettings = field(default_factory=lambda: IkSettings(limit_margin=LIMIT_MARGIN))
    posture: PostureConfig = field(
        default_factory=lambda: PostureConfig(
            ik=IkSettings(rest_weight=0.1, limit_margin=LIMIT_MARGIN)
        )
    )
    use_torso: bool = True
    traj_time: float = 1.0
    motion_timeout: float = 30.0
    robot_timeout: float = ROBOT_TIMEOUT
    joint_tolerance: float = 0.005

    def __post_init__(self) -> None:
        if not isinstance(self.net, NetConfig):
            raise ConfigError(f"net must be a NetConfig, got {self.net!r}")
        if not isinstance(self.ik, IkSettings):
            raise ConfigError(f"ik must be an IkSettings, got {self.ik!r}")
        if not isinstance(self.posture, PostureConfig):
            raise ConfigError(f"posture must be a PostureConfig, got {self.posture!r}")
        if not isinstance(self.use_torso, bool):
            raise ConfigError(f"use_torso must be True or False, got {self.use_torso!r}")
        bounds = {
            "traj_time": (0.05, 60.0),
            "motion_timeout": (0.1, 3600.0),
            "robot_timeout": (0.05, 600.0),
            "joint_tolerance": (1e-4, 0.5),
        }
        for name, (low, high) in bounds.items():
            flag = "--" + name.replace("_", "-")
            object.__setattr__(self, name, config_number(flag, getattr(self, name), low, high))


def add_controller_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the controller's own flags."""
    defaults = ControllerConfig()
    parser.add_argument(
        "--traj-time",
        type=float,
        default=defaults.traj_time,
        help="trajectory time of a move (s of sim time, default %(default)s)",
    )
    parser.add_argument(
        "--motion-timeout",
        type=float,
        default=defaults.motion_timeout,
        help="longest wait for a move (wall s)",
    )
    parser.add_argument(
        "--robot-timeout",
        type=float,
        default=defaults.robot_timeout,
        help="longest wait for the robot's states and RPC (wall s)",
    )
    parser.add_argument(
        "--joint-tolerance",
        type=float,
        default=defaults.joint_tolerance,
        help="a joint within this of its target is there (rad)",
    )
    parser.add_argument(
        "--tolerance",
        type=float,
        default=defaults.ik.position_tolerance,
        help="IK hand position tolerance (m)",
    )
    parser.add_argument(
        "--limit-margin",
        type=float,
        default=LIMIT_MARGIN,
        help="IK solutions keep this far inside the URDF joint limits (rad)",
    )
    parser.add_argument(
        "--no-torso", action="store_true", help="hold the torso: arms (and posture) only"
    )


def config_from_args(args: argparse.Namespace, net: NetConfig) -> ControllerConfig:
    """Build the config from parsed flags.

    Raises:
        ConfigError: an invalid value; the message names it and its valid range.
    """
    base = ControllerConfig()
    ik = replace(base.ik, position_tolerance=args.tolerance, limit_margin=args.limit_margin)
    posture_ik = replace(
        base.posture.ik, position_tolerance=args.tolerance, limit_margin=args.limit_margin
    )
    posture = replace(base.posture, ik=posture_ik, use_torso=not args.no_torso)
    return ControllerConfig(
        net=net,
        ik=ik,
        posture=posture,
        use_torso=not args.no_torso,
        traj_time=args.traj_time,
        motion_timeout=args.motion_timeout,
        robot_timeout=args.robot_timeout,
        joint_tolerance=args.joint_tolerance,
    )
