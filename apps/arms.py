"""Both arms driven over the mesh for the whole shot: postures on the parts' `command:i` ports,
each awaited on `state:o`, and the robot's grasp, nock and release (`--shot whole`); joint
angles in rad. `archery demonstrate --teach` drives the arms through it, a posture at a time,
as a teacher would (a movement to play whole is a trajectory of the robot's own:
`followTrajectory`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import time
from typing import Any

import numpy as np

from archery.apps.shot_plan import ShotStep
from archery.mesh.node import Node
from archery.protocol.errors import ArcheryError, ConfigError, Unreachable
from archery.protocol.messages import JointCommand, JointState
from archery.protocol.parts import PARTS
from archery.protocol.robotspec import BOW_ARM, COMMAND_RATE, STRING_ARM, TORSO
from archery.protocol.verbs import robot as rv
from archery.protocol.verbs.base import NoArgs, Reply, Verb
from archery.sim.scene_config import SceneConfig
from archery.sim.world import ArcheryWorld, WorldConfig

__all__ = ["ACTIONS", "COMMAND_PERIOD", "PASSING", "REACHED", "ArmDriver"]

REACHED = 2e-3  # rad: a part has reached its targets when this close and its motion is done
PASSING = 0.03  # rad: a part passes a waypoint when this close to it, still moving
#: Wall s between two commands to a part: under the rate a robot admits by default
#: (`COMMAND_RATE`), whose excess it drops (a dropped waypoint would never be reached).
COMMAND_PERIOD = 1.5 / COMMAND_RATE
ACTIONS: dict[str, Verb[NoArgs, Any]] = {  # replies: GraspReply, NockReply, ReleaseReply
    "grasp": rv.GRASP,
    "nock": rv.NOCK,
    "release": rv.RELEASE,
}


class ArmDriver:
    """Drives one robot's arms and its archery verbs.

    Args:
        node: a node on the robot's mesh.
        timeout: wall s to wait for each move and each verb.
    """

    def __init__(self, node: Node, timeout: float) -> None:
        self._node = node
        self._timeout = timeout
        keys = node.keys
        self._states = {part: node.subscribe(keys.state(part), JointState) for part in PARTS}
        self._commands = {part: node.publisher(keys.command(part), JointCommand) for part in PARTS}
        self.leases: dict[str, str] = {}  # part -> the lease id the commands carry
        self._sent_at = -float("inf")  # monotonic s of the last commands sent

    def scene(self) -> SceneConfig:
        """The robot's scene (its `status`).

        Raises:
            ConfigError: the robot does not run the whole shot.
        """
        node = self._node
        status = node.call_typed(node.keys.archery_rpc(), rv.ARCHERY_STATUS)
        scene = SceneConfig.of(status.scene)
        if scene.shot != "whole":
            raise ConfigError(
                f"the robot's shot is {scene.shot!r}; start it with `archery robot --shot whole`"
            )
        return scene

    def world(self, scene: SceneConfig | None = None) -> ArcheryWorld:
        """A copy of the robot's scene (`scene`, else asked for) without meshes, standing as
        the robot does now (`stand`).

        Raises:
            ConfigError: the robot does not run the whole shot.
        """
        scene = self.scene() if scene is None else scene
        world = ArcheryWorld(WorldConfig(scene=dataclasses.replace(scene, meshes=False)))
        self.stand(world)
        return world

    def stand(self, world: ArcheryWorld) -> None:
        """Set `world`'s joints to the robot's encoders now."""
        node = self._node
        for part in PARTS:
            encoders = node.call_typed(node.keys.part_rpc(part), rv.GET_POSITIONS)
            world.physics.set_joint_positions(part, np.asarray(encoders.position))
        world.physics.kinematics()

    def claim(self, owner: str, ttl: float, speed: float) -> None:
        """Take the arms' and the torso's leases under `owner` for `ttl` wall s (the commands
        then carry them) and set their joints' reference speeds to `speed` (rad/s; a move
        before may have left them slow), one call per part.

        Raises:
            RpcError: another client holds a part (`not_owner`); the leases taken are dropped.
        """
        node = self._node
        claim = rv.ClaimArgs(owner=owner, ttl=ttl)
        try:
            for part in (BOW_ARM, STRING_ARM, TORSO):
                reply = node.call_typed(
                    node.keys.part_rpc(part),
                    rv.SET_REF_SPEEDS,
                    rv.SetRefSpeedsArgs(speeds=speed, claim=claim),
                )
                self.leases[part] = reply.lease
        except BaseException:
            self.drop()
            raise

    def drop(self) -> None:
        """Drop the leases taken (one the robot no longer knows is gone anyway)."""
        node = self._node
        leases, self.leases = self.leases, {}
        for part, lease in leases.items():
            if lease:
                with contextlib.suppress(ArcheryError):  # best effort: it ends with its ttl
                    node.call_typed(
                        node.keys.part_rpc(part), rv.DROP_CLAIM, rv.LeaseArgs(lease=lease)
                    )

    def move(self, step: ShotStep, torso: np.ndarray | None = None, *, settle: bool = True) -> None:
        """Command the step's arms (and the `torso`, rad, when given) on `command:i` and wait
        until `state:o` shows them there, at rest within `REACHED` (`settle`) or on their way
        within `PASSING` of it (a waypoint the next one follows; the step's action is the
        caller's).

        Raises:
            RpcTimeout: a part did not get there within the timeout. Unreachable: no robot
                takes the commands.
        """
        arms = {STRING_ARM: step.right_arm}
        if step.left_arm is not None:
            arms[BOW_ARM] = step.left_arm
        if torso is not None:
            arms[TORSO] = torso
        after = {part: self._seq(part) for part in arms}
        wait = self._sent_at + COMMAND_PERIOD - time.monotonic()
        if wait > 0:
            time.sleep(wait)  # paced: the robot drops commands above its rate
        self._sent_at = time.monotonic()
        for part, values in arms.items():
            if not self._commands[part].wait_matched(self._timeout):
                raise Unreachable(f"nobody subscribes to {self._commands[part].key}")
            self._commands[part].put(
                JointCommand(
                    part=part,
                    position=values.tolist(),
                    batch=len(arms),
                    lease=self.leases.get(part, ""),
                )
            )
        for part, values in arms.items():

            def there(msg: JointState, wanted: np.ndarray = values) -> bool:
                error = np.max(np.abs(np.asarray(msg.position) - wanted))
                if not settle:
                    return bool(error < PASSING)
                return msg.motion_done and bool(error < REACHED)

            self._states[part].wait_newer(self._timeout, there, after_seq=after[part])

    def _seq(self, part: str) -> int:
        latest = self._states[part].latest()
        return 0 if latest is None else latest.seq

    def act(self, action: str) -> Reply:
        """Call the robot's `grasp`, `nock` or `release`; its reply.

        Raises:
            RpcError: the robot refused it (grasp_missed, nock_missed, arrow_dropped, …).
        """
        node = self._node
        reply: Reply = node.call_typed(
            node.keys.archery_rpc(), ACTIONS[action], timeout=self._timeout
        )
        return reply

    def close(self) -> None:
        """Drop the leases and stop following the robot's states."""
        self.drop()
        for sub in self._states.values():
            sub.close()
