"""The controlboards of a fake robot on the mesh: every part's `getLimits` and `setRefSpeeds`
served (limits ±3 rad, no leases), its archery `status` (a posture shot), its commands handed
to a callback, its state publishers."""

from __future__ import annotations

import abc
import threading
from collections.abc import Callable

from archery.mesh.node import Node
from archery.mesh.publisher import Publisher
from archery.protocol.messages import JointCommand, JointState
from archery.protocol.parts import PARTS
from archery.protocol.verbs import ServedVerbs
from archery.protocol.verbs import robot as rv
from archery.sim.scene_config import SceneConfig
from tests.rpc import some_verbs


def part_verbs(part: str, speeds_set: list[list[float]] | None = None) -> ServedVerbs:
    """`getLimits` (±3 rad) and `setRefSpeeds` (the speeds given, no lease; each call's
    appended to `speeds_set`) of `part`."""
    names = list(PARTS[part])
    n = len(names)
    limits = rv.LimitsReply(names=names, min=[-3.0] * n, max=[3.0] * n, tolerance=0.01)

    def speeds(a: rv.SetRefSpeedsArgs) -> rv.RefSpeedsReply:
        given = a.speeds if isinstance(a.speeds, list) else [a.speeds] * n
        if speeds_set is not None:
            speeds_set.append(given)
        return rv.RefSpeedsReply(names=names, speeds=given)

    return some_verbs(rv.PART_VERBS, {"getLimits": lambda a: limits, "setRefSpeeds": speeds})


def archery_verbs() -> ServedVerbs:
    """The archery `status` of a posture-shot robot at rtf 0 (what a controller asks before a
    posture)."""
    status = rv.ArcheryStatusReply(
        sim_time=0.0,
        arrow="stowed",
        phase="idle",
        shot=0,
        motion_done=True,
        seed=None,
        rtf=0.0,
        state_rate=100.0,
        world_rate=30.0,
        watchdog=0.5,
        limit_tolerance=0.01,
        timestep=0.002,
        counters={},
        scene=SceneConfig(meshes=False).to_status(),
        world={},
    )
    return some_verbs(rv.ARCHERY_VERBS, {"status": lambda a: status})


def serve_parts(
    node: Node,
    on_command: Callable[[JointCommand], None],
    speeds_set: dict[str, list[list[float]]] | None = None,
) -> dict[str, Publisher[JointState]]:
    """Serve every part's verbs and commands on `node` (ready once it returns; the speeds
    each part is set recorded in `speeds_set`); its state publishers by part."""
    keys = node.keys
    pubs = {p: node.publisher(keys.state(p), JointState) for p in PARTS}
    for part in PARTS:
        node.subscribe(keys.command(part), JointCommand, callback=on_command)
        recorded = None if speeds_set is None else speeds_set.setdefault(part, [])
        node.serve(keys.part_rpc(part), part_verbs(part, recorded))
    node.serve(keys.archery_rpc(), archery_verbs())
    node.ready()
    return pubs


class FakeRobot(abc.ABC):
    """A fake robot's controlboards (`serve_parts`) and its publishing thread, which runs
    `_publish` (a subclass's; set its own fields before calling this constructor);
    `commanded` is set by the first command."""

    def __init__(self, node: Node) -> None:
        self.commanded = threading.Event()
        self.speeds_set: dict[str, list[list[float]]] = {}  # by part, each setRefSpeeds call's
        self._pubs = serve_parts(node, lambda command: self.commanded.set(), self.speeds_set)
        self._thread = threading.Thread(target=self._publish, daemon=True)
        self._thread.start()

    @abc.abstractmethod
    def _publish(self) -> None:
        """Publish the joint states until the fake robot is closed (the thread's body)."""

    def _join(self) -> None:
        self._thread.join(5)
