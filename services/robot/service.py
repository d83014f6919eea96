"""`archery robot`: the simulated iCub's controlboards and archery verbs on the mesh.

Ports (ROBOT = the robot prefix, e.g. icubSim):

* `ROBOT/{torso,left_arm,right_arm}/state:o` JointState at `state_rate` per simulated second
  (at rtf 0 at most that many per wall second); at rtf 0 and at rest (every motion done, no arrow
  flying) at that rate per wall second for `rest_after` s after the last command, move, nock,
  release or reset, then a heartbeat at `rest_rate` (10 Hz by default), full rate again at once
  on any of them (see `pacing`);
* `ROBOT/{part}/command:i` JointCommand position targets (validated as in `commands`), from the
  holder of the part's lease only while one runs, at most `--command-rate` per wall s (see
  `gate`);
* `ROBOT/{part}/rpc:i` controlboard verbs: getJointNames, getLimits, getPositions, getTargets,
  checkMotionDone, setRefSpeeds, getRefSpeeds, positionMove, counters, status, and the lease
  verbs claim, renewClaim, dropClaim, getClaim;
* `ROBOT/archery/rpc:i`: nock, release (replies after the landing), reset, status;
* `ROBOT/world/state:o` WorldState at `world_rate` per simulated second (paced like the joint
  states, the heartbeat at rest too) and after each nock, release, landing and reset;
* `ROBOT/world/events:o` WorldEvent, lossless: nocked, released, landed / missed, reset, and
  watchdog (a part's command stream stopped mid-motion for `--watchdog` wall s, default 0.1:
  the part is held at its measured positions, `watchdog_trips` counts it; see `watchdog`).

Verbs (args → result; joint vectors in YARP order, rad; the types are in `protocol.verbs.robot`,
where the RPC server checks every request before a handler sees it):

* getJointNames → {names}; getLimits → {names, min, max, tolerance} (software limits);
  getPositions → {names, position, velocity, sim_time}; getTargets → {names, position};
  checkMotionDone → {done}; setRefSpeeds {speeds: number or list, rad/s} → {names, speeds};
  getRefSpeeds → {names, speeds}; positionMove {position, names?, lease?} → {names, position}
  (the part's targets after the move, validated as a command); counters → {accepted, clamped,
  rejected, rejected_by_reason, watchdog_trips, last_rejection, streaming, undecodable};
  status → names, motion_done, counters and getPositions' fields.
* claim {owner, ttl? (wall s, default 2), takeover?} → {lease, owner, ttl, expires_in,
  took_over}; renewClaim {lease} → the same; dropClaim {lease} → getClaim's reply; getClaim →
  {held, owner, ttl, expires_in}. While a lease runs, a command, positionMove or setRefSpeeds
  without its id is refused (`not_owner`, counted with the command counters); with none held
  the part takes commands from anyone.
* nock → {shot, arrow, sim_time}; release → {shot, outcome, hit, reason, sim_time,
  release_sim_time, flight_time, theta} once the arrow has landed; reset {seed?} → {sim_time,
  seed, shot}; status → {sim_time, arrow, phase, shot, motion_done, seed, rtf, rates,
  watchdog, limit_tolerance, timestep, counters, scene (SceneConfig.to_dict()), world
  (WorldConfig.to_dict())}.

Requests on one key are served one at a time, so a release holds `archery/rpc:i` until its
landing and a reset sent meanwhile is answered after it (the world itself refuses a reset during
a flight). The ground-truth impact r is only in the landed / missed events (tests and plots);
the release reply tells the outcome, never r. The simulation runs on its own thread (`simloop`).
"""

from __future__ import annotations

import logging
import threading
from functools import partial

from mesh.node import Node
from mesh.service import service_main
from protocol.messages import JointCommand
from protocol.robotspec import ROBOT
from services.robot.config import RobotConfig, add_arguments, make_config
from services.robot.handlers import RobotHandlers
from services.robot.simloop import SimLoop
from services.robot.sink import MeshSink
from sim.world import ArcheryWorld

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
                    admit=partial(loop.screen, part),
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
