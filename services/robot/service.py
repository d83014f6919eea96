"""`archery robot`: the simulated iCub's controlboards and archery verbs on the mesh.

Ports (ROBOT = the robot prefix, e.g. icubSim):

* `ROBOT/{torso,left_arm,right_arm}/state:o` JointState at `state_rate` per simulated second;
* `ROBOT/{part}/command:i` JointCommand position targets (validated as in `commands`);
* `ROBOT/{part}/rpc:i` controlboard verbs: getJointNames, getLimits, getPositions, getTargets,
  checkMotionDone, setRefSpeeds, getRefSpeeds, positionMove, counters, status;
* `ROBOT/archery/rpc:i`: nock, release (replies after the landing), reset, status;
* `ROBOT/world/state:o` WorldState at `world_rate` per simulated second and after each landing;
* `ROBOT/world/events:o` WorldEvent, lossless: nocked, released, landed / missed, reset.

Verbs (args → result; joint vectors in YARP order, rad; the types are in `protocol.verbs.robot`,
where the RPC server checks every request before a handler sees it):

* getJointNames → {names}; getLimits → {names, min, max, tolerance} (software limits);
  getPositions → {names, position, velocity, sim_time}; getTargets → {names, position};
  checkMotionDone → {done}; setRefSpeeds {speeds: number or list, rad/s} → {names, speeds};
  getRefSpeeds → {names, speeds}; positionMove {position, names?} → {names, position} (the
  part's targets after the move, validated as a command); counters → {accepted, clamped,
  rejected, rejected_by_reason, watchdog_trips, last_rejection, streaming, undecodable};
  status → names, motion_done, counters and getPositions' fields.
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

import numpy as np

from protocol.messages import Array, JointCommand, JointState, WorldEvent, WorldState
from protocol.node import Node, Subscription
from protocol.robotspec import ROBOT
from protocol.service import service_main
from protocol.verbs import NoArgs, ServedVerbs
from protocol.verbs import robot as rv
from services.robot.config import RobotConfig, add_robot_arguments, config_from_args
from services.robot.simloop import SimLoop
from sim.world import ArcheryWorld

__all__ = ["main", "run"]

log = logging.getLogger("archery.robot")


class _MeshSink:
    """The loop's streams as Zenoh publishers."""

    def __init__(self, node: Node, parts: tuple[str, ...]) -> None:
        keys = node.keys
        self._states = {p: node.publisher(keys.state(p), JointState) for p in parts}
        self._world = node.publisher(keys.world_state(), WorldState)
        self._events = node.publisher(keys.world_events(), WorldEvent, lossless=True)

    def joint_state(
        self,
        part: str,
        names: tuple[str, ...],
        position: list[float],
        velocity: list[float],
        motion_done: bool,
        sim_time: float,
    ) -> None:
        self._states[part].put(
            JointState(
                part=part,
                names=list(names),
                position=position,
                velocity=velocity,
                motion_done=motion_done,
                sim_time=sim_time,
            )
        )

    def world_state(self, qpos: np.ndarray, phase: str, shot: int, sim_time: float) -> None:
        self._world.put(
            WorldState(qpos=Array.from_numpy(qpos), phase=phase, shot=shot, sim_time=sim_time)
        )

    def event(
        self,
        kind: str,
        shot: int,
        sim_time: float,
        impact_m: list[float] | None = None,
        reason: str = "",
    ) -> None:
        self._events.put(
            WorldEvent(
                kind=kind,  # type: ignore[arg-type]
                shot=shot,
                impact_m=impact_m,
                reason=reason,
                sim_time=sim_time,
            )
        )


def _part_handlers(loop: SimLoop, part: str, commands: Subscription[JointCommand]) -> ServedVerbs:
    limits = loop.limits[part]
    names = list(limits.names)

    def counters(_: NoArgs) -> rv.CountersReply:
        return rv.CountersReply(**loop.counters(part), undecodable=commands.dropped)

    def status(_: NoArgs) -> rv.PartStatusReply:
        return rv.PartStatusReply(
            part=part,
            names=names,
            motion_done=loop.motion_done(part),
            counters=counters(NoArgs()),
            **loop.positions(part),
        )

    return rv.PART_VERBS.bind(
        {
            "getJointNames": lambda a: rv.JointNamesReply(names=names),
            "getLimits": lambda a: rv.LimitsReply(
                names=names,
                min=list(limits.lower),
                max=list(limits.upper),
                tolerance=limits.tolerance,
            ),
            "getPositions": lambda a: rv.PositionsReply(**loop.positions(part)),
            "getTargets": lambda a: rv.TargetsReply(names=names, position=loop.targets(part)),
            "checkMotionDone": lambda a: rv.MotionDoneReply(done=loop.motion_done(part)),
            "setRefSpeeds": lambda a: rv.RefSpeedsReply(
                names=names, speeds=loop.set_ref_speeds(part, a.speeds)
            ),
            "getRefSpeeds": lambda a: rv.RefSpeedsReply(names=names, speeds=loop.ref_speeds(part)),
            "positionMove": lambda a: rv.TargetsReply(
                names=names, position=loop.position_move(part, a.position, a.names)
            ),
            "counters": counters,
            "status": status,
        }
    )


def _archery_handlers(loop: SimLoop) -> ServedVerbs:
    return rv.ARCHERY_VERBS.bind(
        {
            "nock": lambda a: rv.NockReply(**loop.nock()),
            "release": lambda a: rv.ReleaseReply(**loop.release()),
            "reset": lambda a: rv.ResetReply(**loop.reset(a.seed)),
            "status": lambda a: rv.ArcheryStatusReply(**loop.status()),
        }
    )


def run(config: RobotConfig, stop: threading.Event) -> None:
    """Serve the simulated robot until `stop` is set."""
    world = ArcheryWorld(config.world)
    world.reset(config.seed)
    with Node(ROBOT, config.net) as node:
        keys = node.keys
        sink = _MeshSink(node, world.parts)
        loop = SimLoop(world, config, sink, seed=config.seed)
        thread = threading.Thread(target=loop.run, args=(stop,), name="robot sim", daemon=True)
        thread.start()
        try:
            for part in world.parts:

                def on_command(msg: JointCommand, part: str = part) -> None:
                    loop.command(part, msg.position, msg.names, msg.part)

                commands = node.subscribe(keys.command(part), JointCommand, callback=on_command)
                node.serve(keys.part_rpc(part), _part_handlers(loop, part, commands))
            node.serve(keys.archery_rpc(), _archery_handlers(loop))
            node.ready()
            log.info(
                "robot %r ready: rtf %g, seed %s, joint states %g Hz, world %g Hz (sim time)",
                keys.robot,
                config.rtf,
                config.seed,
                config.state_rate,
                config.world_rate,
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
        prog="robot",
        description=__doc__.split("\n", 1)[0] if __doc__ else "the simulated iCub",
        add_arguments=add_robot_arguments,
        make_config=config_from_args,
        run=run,
    )
