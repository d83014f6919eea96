"""The controller service's frozen, validated configuration and its command-line flags."""

from __future__ import annotations

import argparse
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

from archery.mesh.configflags import add_config_args, check_bounds, config_from_args, flag
from archery.mesh.netflags import NetConfig
from archery.protocol.errors import ConfigError
from archery.protocol.robotspec import (
    LEASE_TTL,
    LEASE_TTL_RANGE,
    ROBOT_TIMEOUT,
    STATE_MAX_AGE,
    TOLERANCES,
)
from archery.services.controller.demonstration_file import read_demonstration
from archery.services.controller.ik_types import IkSettings
from archery.services.controller.posture import PostureConfig

if TYPE_CHECKING:
    from archery.services.controller.movement import Movement

__all__ = ["LIMIT_MARGIN", "ControllerConfig", "add_arguments", "make_config"]

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
        state_max_age: a robot joint state that arrived longer ago than this is stale, never
            used: the verbs reply `stale_state` (wall s; see `mesh/robot_client.py`).
        demonstration: the whole shot's demonstration, whose DMPs a posture for a `--shot
            whole` robot plays (None: `SHIPPED_DEMONSTRATION`).
        lease_ttl: a move holds a lease on each part it commands (no other client moves the
            part meanwhile); it lasts this long unless renewed (every quarter of it), so a
            controller that dies frees the arm within it (wall s).
    """

    net: NetConfig = field(default_factory=NetConfig)
    ik: IkSettings = field(default_factory=lambda: IkSettings(limit_margin=LIMIT_MARGIN))
    posture: PostureConfig = field(
        default_factory=lambda: PostureConfig(
            ik=IkSettings(rest_weight=0.1, limit_margin=LIMIT_MARGIN)
        )
    )
    use_torso: bool = flag(True, "hold the torso: arms (and posture) only", name="--no-torso")
    traj_time: float = flag(
        1.0, "trajectory time of a move", unit="s of sim time", low=0.05, high=60
    )
    motion_timeout: float = flag(30.0, "longest wait for a move", unit="wall s", low=0.1, high=3600)
    robot_timeout: float = flag(
        ROBOT_TIMEOUT,
        "longest wait for the robot's states and RPC",
        unit="wall s",
        low=0.05,
        high=600,
    )
    joint_tolerance: float = flag(
        TOLERANCES["rest"],
        "a joint within this of its target is there",
        unit="rad",
        low=1e-4,
        high=0.5,
    )
    state_max_age: float = flag(
        STATE_MAX_AGE, "a robot state older than this is stale", unit="wall s", low=0.05, high=60
    )
    lease_ttl: float = flag(
        LEASE_TTL,
        "a move's lease on each part it commands lasts this long unless renewed",
        unit="wall s",
        low=0.2,
        high=LEASE_TTL_RANGE[1],
    )
    demonstration: str | None = flag(
        None,
        "the whole shot's demonstration, played as DMPs on a robot with --shot whole "
        "(default: the one shipped)",
        metavar="FILE",
    )

    def __post_init__(self) -> None:
        check_bounds(self)
        if self.demonstration is not None:
            read_demonstration(self.demonstration)

    def movement(self) -> Movement:
        """The whole shot's DMPs, of `demonstration` (else the shipped one).

        Raises:
            ConfigError: the demonstration is not readable or not valid, or the DMPs' library
                (the `imitate` extra) is not installed.
        """
        try:
            from archery.services.controller.movement import Movement
        except ImportError as exc:
            raise ConfigError(
                f"the robot runs the whole shot, whose movement needs the DMPs' library "
                f"({exc.name}): pip install 'archery[imitate]'"
            ) from None
        return Movement(read_demonstration(self.demonstration))


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the controller's own flags: the config's and the IK's (tolerance, limit margin)."""
    add_config_args(parser, ControllerConfig)
    parser.add_argument(
        "--tolerance",
        type=float,
        default=ControllerConfig().ik.position_tolerance,
        help="IK hand position tolerance (m)",
    )
    parser.add_argument(
        "--limit-margin",
        type=float,
        default=LIMIT_MARGIN,
        help="IK solutions keep this far inside the URDF joint limits (rad)",
    )


def make_config(args: argparse.Namespace, net: NetConfig) -> ControllerConfig:
    """Build the config from parsed flags.

    Raises:
        ConfigError: an invalid value; the message names it and its valid range.
    """
    base = ControllerConfig()
    ik = replace(base.ik, position_tolerance=args.tolerance, limit_margin=args.limit_margin)
    posture_ik = replace(
        base.posture.ik, position_tolerance=args.tolerance, limit_margin=args.limit_margin
    )
    posture = replace(base.posture, ik=posture_ik, use_torso=args.use_torso)
    result: ControllerConfig = config_from_args(
        ControllerConfig, args, net=net, ik=ik, posture=posture
    )
    return result
