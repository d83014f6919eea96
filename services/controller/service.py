"""`archery controller`: iKin-like cartesian controllers and the archery posture on the mesh.

It serves `ROBOT/cartesianController/{left_arm,right_arm}/rpc:i` and
`ROBOT/cartesianController/archery/rpc:i` (their verbs: the tables of
`protocol.verbs.controller`, bound in `handlers`; docs/names.md), reads the
robot's `{part}/state:o`, writes `{part}/command:i` and calls `{part}/rpc:i` (getLimits,
setRefSpeeds and the lease verbs, `--lease-ttl` wall s) through `mesh/robot_client.py`; it
never imports the robot's code. Positions are metres in root_link, orientations iKin
axis-angle [ax, ay, az, angle]. A joint state that arrived more than `--state-max-age` wall s
ago (default 0.5) is never used: the verbs reply `stale_state` naming the key and the age (the
robot is frozen or lost).
"""

from __future__ import annotations

import logging
import threading

from archery.mesh.node import Node
from archery.mesh.robot_client import RobotClient
from archery.mesh.service import service_main
from archery.mesh.signals import wait_for_stop
from archery.protocol.parts import ARM_PARTS, PARTS
from archery.protocol.robotspec import CONTROLLER
from archery.services.controller.config import ControllerConfig, add_arguments, make_config
from archery.services.controller.handlers import ArcheryController, ArmController, MotionLock
from archery.services.controller.model import load_arms_model
from archery.services.controller.posture import ArcheryPosture

__all__ = ["main", "run"]

log = logging.getLogger("archery.controller")


def run(config: ControllerConfig, stop: threading.Event) -> None:
    """Serve the cartesian controllers until `stop` is set."""
    model = load_arms_model()
    posture = ArcheryPosture(config.posture)
    with Node(CONTROLLER, config.net) as node:
        keys = node.keys
        client = RobotClient(
            node,
            timeout=config.robot_timeout,
            reached=config.joint_tolerance,
            state_max_age=config.state_max_age,
            lease_ttl=config.lease_ttl,
        )
        for part in PARTS:  # its states followed, its commands' publishers declared from the start
            client.stream(part)
            client.command(part, ())
        motion = MotionLock()
        for arm in ARM_PARTS:
            controller = ArmController(arm, model, config, client, motion)
            node.serve(keys.cartesian_rpc(arm), controller.verbs())
        archery = ArcheryController(posture, config, client, motion, config.movement)
        node.serve(keys.cartesian_rpc("archery"), archery.verbs())
        node.ready()
        log.info(
            "controller %r ready: trajectory time %g s, torso %s, θ box %s..%s m",
            keys.robot,
            config.traj_time,
            config.use_torso,
            config.posture.theta_box.low,
            config.posture.theta_box.high,
        )
        wait_for_stop(stop)


def main(argv: list[str] | None = None) -> int:
    """`archery controller [flags]`: serve until SIGINT/SIGTERM (exit status 0)."""
    return service_main(
        argv,
        prog=CONTROLLER,
        description="iKin-like cartesian controllers and the archery posture (Pinocchio IK)",
        add_arguments=add_arguments,
        make_config=make_config,
        run=run,
    )
