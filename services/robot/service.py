"""`archery robot`: the simulated iCub's controlboards and archery verbs on the mesh.

`run` wires the simulation (`simloop`) to its ports: each part's `command:i` subscription,
screened raw by the lease gate (`leases`) before decoding, and the verb handlers (`handlers`).
The ports are listed in docs/names.md, the verbs in
`protocol.verbs.robot` (`archery interface KEY` prints them); ARCHITECTURE.md places the robot in
the life of one rollout.
"""

from __future__ import annotations

import logging
import threading
from functools import partial

from archery.mesh.node import Node
from archery.mesh.service import service_main
from archery.protocol.messages import JointCommand
from archery.protocol.robotspec import ROBOT
from archery.services.robot.config import RobotConfig, add_arguments, make_config
from archery.services.robot.handlers import RobotHandlers
from archery.services.robot.simloop import SimLoop
from archery.services.robot.sink import MeshSink
from archery.sim.world import ArcheryWorld

__all__ = ["main", "run"]

log = logging.getLogger("archery.robot")


def run(config: RobotConfig, stop: threading.Event) -> None:
    """Serve the simulated robot until `stop` is set."""
    world = ArcheryWorld(config.world)
    world.reset(config.seed)
    with Node(ROBOT, config.net) as node:
        keys = node.keys
        loop = SimLoop(world, config, MeshSink(node, world.parts), seed=config.seed)
        thread = threading.Thread(target=loop.run, args=(stop,), name="robot sim", daemon=True)
        thread.start()
        try:
            commands = {
                part: node.subscribe(
                    keys.command(part),
                    JointCommand,
                    callback=lambda msg, part=part: loop.command(  # type: ignore[misc]  # mypy can't type lambda defaults (mypy#15459)
                        part, msg.position, msg.names, msg.part, msg.batch, msg.lease
                    ),
                    admit=partial(loop.leases.screen, part),  # its lease, checked here
                )
                for part in world.parts
            }
            handlers = RobotHandlers(loop, commands, secure=config.net.secure is not None)
            for part in world.parts:
                node.serve(keys.part_rpc(part), handlers.part_verbs(part))
            node.serve(keys.archery_rpc(), handlers.archery_verbs())
            node.ready()
            log.info(
                "robot %r ready: rtf %g, seed %s, joint states %g Hz, world %g Hz (sim time); "
                "at rest %g Hz after %g s",
                keys.robot,
                config.rtf,
                config.seed,
                config.state_rate,
                config.world_rate,
                config.rest_rate,
                config.rest_after,
            )
            stop.wait()
        finally:
            stop.set()
            loop.close()
            thread.join(timeout=10)


def main(argv: list[str] | None = None) -> int:
    """`archery robot [flags]`: run the simulated robot until SIGINT/SIGTERM (exit status 0)."""
    return service_main(
        argv,
        prog=ROBOT,
        description=__doc__.split("\n", 1)[0] if __doc__ else "the simulated iCub",
        add_arguments=add_arguments,
        make_config=make_config,
        run=run,
    )
