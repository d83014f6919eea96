"""`archery imitate DEMO.json [--theta X,Y,Z]`: the whole shot from a demonstration's DMPs alone
on a running robot (`archery robot --shot whole`).

The movement is learned as DMPs (`services.controller.movement`) and planned as the
controller plans a whole shot (`services.controller.whole_shot`): the draw's goal is the
archery posture for θ (the controller's IK), grasp and nock at their demonstrated times; the
robot plays it as one trajectory under the parts' leases (`archery/rpc:i followTrajectory`,
through the robot's client, `mesh.robot_client`), then the release, whose reply is printed. A
bad file, or θ outside the controller's box (nothing moves): one line, exit status 2.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING

import msgspec
import numpy as np

from archery.apps.waits import announce, interrupted_line
from archery.mesh.cliargs import ArgumentParser, seconds
from archery.mesh.netflags import NetConfig, add_network_args
from archery.mesh.node import open_node
from archery.mesh.robot_client import RobotClient
from archery.protocol.demonstration import BadDemonstration
from archery.protocol.errors import ArcheryError, ConfigError
from archery.protocol.exit_status import BAD_INPUT, INTERRUPTED, OK, for_error
from archery.protocol.parts import PARTS
from archery.protocol.robotspec import NOMINAL_THETA, ROBOT
from archery.protocol.theta import THETA_BOX
from archery.protocol.vectors import parse_vector
from archery.services.controller.demonstration_file import read_demonstration

if TYPE_CHECKING:
    from archery.services.controller.movement import Movement

__all__ = ["main"]

PROG = "imitate"


def _theta(text: str) -> np.ndarray:
    """θ (m) from X,Y,Z, inside the controller's box (`protocol.theta.THETA_BOX`): its check
    of θ in this program.

    Raises:
        ConfigError: not 3 finite numbers, or outside the box.
    """
    theta = parse_vector("--theta", text, ConfigError, unit="m")
    if not THETA_BOX.contains(theta):
        raise ConfigError(f"{THETA_BOX.outside('--theta', theta.round(4))}: nothing moved")
    return theta


def _play(args: argparse.Namespace, theta: np.ndarray, movement: Movement) -> int:
    from archery.services.controller.posture import ArcheryPosture, PostureConfig
    from archery.services.controller.whole_shot import PARTS_MOVED, plan_whole_shot

    net = NetConfig.from_args(args)
    on_wait = announce(PROG)
    with open_node(net, args.wait, on_wait=on_wait) as node:
        node.wait_alive([ROBOT], args.wait, on_wait=on_wait)
        robot = RobotClient(node, timeout=args.wait)
        try:
            status = robot.status()
            shot = status.scene.shot
            if shot != "whole":
                raise ArcheryError(
                    f"the robot runs the {shot!r} shot; start it with `archery robot --shot whole`",
                    code="bad_state",
                )
            standing: dict[str, float] = {}
            for part in PARTS_MOVED:
                standing.update(zip(PARTS[part], robot.positions(part).tolist(), strict=True))
            posture = ArcheryPosture(PostureConfig())
            plan = plan_whole_shot(movement, posture, theta, status.nock_in_hand, standing).plan
            robot.follow(
                PARTS_MOVED,
                plan.times,
                plan.rows,
                {"grasp": plan.grasp, "nock": plan.nock},
                owner=PROG,
                rtf=status.rtf,
            )
            reply = robot.release()
        finally:
            robot.close()
    print(json.dumps(msgspec.to_builtins(reply)), flush=True)
    return OK


def main(argv: list[str] | None = None) -> int:
    """Play a demonstration's DMPs for θ; exit status 0, 1 (the robot refused a step or is not
    there), 2 (bad file or θ) or 130 (Ctrl-C)."""
    parser = ArgumentParser(
        prog=f"archery {PROG}",
        description="the whole shot from a demonstration's DMPs alone, drawn for θ, on a "
        "running robot (--shot whole)",
    )
    add_network_args(parser, default_mode="client")
    parser.add_argument("demonstration", type=Path, help="a demonstration (archery demonstrate)")
    parser.add_argument(
        "--theta",
        default=",".join(f"{v:g}" for v in NOMINAL_THETA),
        metavar="X,Y,Z",
        help="draw the string hand to bow hand + θ (m), inside the controller's box",
    )
    parser.add_argument(
        "--wait", type=seconds, default=30.0, help="wall s to wait for the robot and each step"
    )
    args = parser.parse_args(argv)
    try:
        theta = _theta(args.theta)
        from archery.services.controller.movement import Movement

        movement = Movement(read_demonstration(args.demonstration, flag=""))
    except (ConfigError, BadDemonstration) as exc:
        print(f"archery {PROG}: {exc.message}", file=sys.stderr)
        return BAD_INPUT
    try:
        return _play(args, theta, movement)
    except KeyboardInterrupt:
        print(interrupted_line(PROG), file=sys.stderr)
        return INTERRUPTED
    except ArcheryError as exc:
        print(f"archery {PROG}: {exc.message}", file=sys.stderr)
        return for_error(exc.code)
