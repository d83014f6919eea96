"""`archery robot`: the simulated iCub's controlboards and archery verbs on the mesh.

`run` wires the simulation (`simloop`) to its ports: each part's `command:i` subscription,
screened raw by the lease gate (`leases`) before decoding, and the verb handlers (`handlers`).
The ports are listed in docs/names.md, the verbs in
`protocol.verbs.robot` (`archery interface KEY` prints them); ARCHITECTURE.md places the robot in
the life of one rollout. With `--body yarp` (`run_yarp`) the same part ports and verbs serve a
YARP robot's control boards (`yarp_loop`) instead; its start-up failures exit with status 2.
"""

from __future__ import annotations

import logging
import sys
import threading
from functools import partial

from archery.mesh.node import Node
from archery.mesh.service import service_main
from archery.mesh.signals import wait_for_stop
from archery.protocol.errors import ConfigError
from archery.protocol.exit_status import BAD_INPUT
from archery.protocol.messages import JointCommand
from archery.protocol.robotspec import ROBOT, ROBOT_TIMEOUT, RPC_TIMEOUT
from archery.services.robot.config import RobotConfig, add_arguments, make_config
from archery.services.robot.handlers import RobotHandlers
from archery.services.robot.simloop import SimLoop
from archery.services.robot.sink import MeshSink
from archery.services.robot.yarp_archery import ArcheryLink
from archery.services.robot.yarp_loop import YarpLoop
from archery.services.robot.yarp_parts import BodyError, open_parts
from archery.services.robot.yarp_shot import LabShot
from archery.sim.world import ArcheryWorld

__all__ = ["main", "run", "run_yarp"]

log = logging.getLogger("archery.robot")


def run(config: RobotConfig, stop: threading.Event) -> None:
    """Serve the simulated robot (`--body yarp`: a YARP robot's, `run_yarp`) until `stop` is
    set."""
    if config.body == "yarp":
        run_yarp(config, stop)
        return
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
            wait_for_stop(stop)
        finally:
            stop.set()
            loop.close()
            thread.join(timeout=10)


def run_yarp(config: RobotConfig, stop: threading.Event) -> None:
    """Serve the YARP robot `config.remote`'s parts (`yarp_loop`) until `stop` is set: each
    part's `state:o`, `command:i` and controlboard verbs, with the simulated robot's lease
    rules; the archery verbs answer `unsupported`, or, with `config.archery_rpc`, are the
    robot's own port's answers, its world events forwarded (`yarp_archery`).

    Raises:
        BodyError: the body does not open (no name server, a part or an axis missing, an
            encoder refused, YARP's bindings absent, no archery RPC port), before anything is
            served.
    """
    try:
        body = open_parts(config.remote, timeout=ROBOT_TIMEOUT)
    except BodyError:
        raise
    except ConfigError as exc:  # YARP's bindings are not installed
        raise BodyError(str(exc)) from None
    archery: ArcheryLink | None = None
    try:
        node = Node(ROBOT, config.net)
        try:
            events = bool(config.archery_rpc) and config.landing == "events"
            sink = MeshSink(node, tuple(body.parts), world=False, events=events)
            if config.archery_rpc:
                archery = ArcheryLink(
                    body.yarp,
                    config.archery_rpc,
                    f"{config.remote}/world/events:o" if events else "",
                    sink,
                    timeout=RPC_TIMEOUT,  # a release answers once the arrow landed
                )
            loop = YarpLoop(body, config, sink, archery)
        except BaseException:
            if archery is not None:
                archery.close()
            node.close()
            raise
    except BaseException:
        body.close()
        raise
    with node:
        thread = threading.Thread(target=loop.run, args=(stop,), name="robot yarp", daemon=True)
        thread.start()
        try:
            _serve(node, loop, tuple(body.parts), config)
            loop.on_whole = lambda whole: node.ready() if whole else node.withdraw()
            log.info(
                "robot %r ready: the YARP robot %s (%s), joint states %g Hz (wall time); "
                "archery verbs: %s",
                node.keys.robot,
                config.remote,
                ", ".join(body.parts),
                config.state_rate,
                _shot_of(loop, config),
            )
            wait_for_stop(stop)
        finally:
            stop.set()
            thread.join(timeout=10)
            loop.close()


def _shot_of(loop: YarpLoop, config: RobotConfig) -> str:
    """How the body's archery verbs are answered, for its start line."""
    if config.archery_rpc:
        return f"{config.archery_rpc}, landing told by the {config.landing}"
    if isinstance(loop.shot, LabShot):
        postures = ", ".join(loop.shot.postures) or "none"
        return (
            f"release by {loop.shot.finger.name} to {loop.shot.open:g}°, hand postures: "
            f"{postures} (others by the operator), landing told by the camera"
        )
    return "refused"


def _serve(node: Node, loop: YarpLoop, parts: tuple[str, ...], config: RobotConfig) -> None:
    """Each part's `command:i` (screened by its lease gate) and verbs, the archery verbs."""
    keys = node.keys
    commands = {
        part: node.subscribe(
            keys.command(part),
            JointCommand,
            callback=lambda msg, part=part: loop.command(  # type: ignore[misc]  # mypy can't type lambda defaults (mypy#15459)
                part, msg.position, msg.names, msg.part, msg.batch, msg.lease
            ),
            admit=partial(loop.leases.screen, part),
        )
        for part in parts
    }
    handlers = RobotHandlers(loop, commands, secure=config.net.secure is not None)
    for part in parts:
        node.serve(keys.part_rpc(part), handlers.part_verbs(part))
    node.serve(keys.archery_rpc(), handlers.archery_verbs())
    node.ready()


def main(argv: list[str] | None = None) -> int:
    """`archery robot [flags]`: run the simulated robot (or `--body yarp`, a YARP robot's
    control boards) until SIGINT/SIGTERM (exit status 0); a YARP body that does not open: one
    line, exit status 2."""
    refused: list[BodyError] = []

    def serve(config: RobotConfig, stop: threading.Event) -> None:
        try:
            run(config, stop)
        except BodyError as exc:
            refused.append(exc)

    status = service_main(
        argv,
        prog=ROBOT,
        description=__doc__.split("\n", 1)[0] if __doc__ else "the simulated iCub",
        add_arguments=add_arguments,
        make_config=make_config,
        run=serve,
    )
    if refused:
        print(f"archery {ROBOT}: {refused[0]}", file=sys.stderr)
        return BAD_INPUT
    return status
