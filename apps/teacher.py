"""A scripted teacher of the whole shot over the mesh (`archery demonstrate --teach`): the arms'
postures of `sim.shot_script`, planned on a copy of the robot's scene, sent on the parts'
`command:i` ports and each awaited on `state:o`; the robot's grasp, nock and release called in
their turn. The robot must run with `--shot whole`; joint angles in rad, positions in m.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from mesh.node import Node
from protocol.errors import ConfigError, Unreachable
from protocol.messages import JointCommand, JointState
from protocol.parts import PARTS
from protocol.robotspec import BOW_ARM, STRING_ARM
from protocol.verbs import robot as rv
from protocol.verbs.base import Verb
from sim.geometry import BOW_HAND
from sim.scene_config import SceneConfig
from sim.shot_script import ShotStep, plan_aim, plan_whole_shot
from sim.world import ArcheryWorld, WorldConfig

__all__ = ["Teacher"]

REACHED = 2e-3  # rad: a part has reached its targets when this close and its motion is done
_ACTIONS: dict[str, Verb] = {"grasp": rv.GRASP, "nock": rv.NOCK, "release": rv.RELEASE}


class Teacher:
    """Drives one robot through the whole shot.

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

    def world(self) -> ArcheryWorld:
        """A copy of the robot's scene standing as the robot does now.

        Raises:
            ConfigError: the robot does not run the whole shot.
        """
        node = self._node
        status = node.call_typed(node.keys.archery_rpc(), rv.ARCHERY_STATUS)
        scene = SceneConfig(**status.scene)
        if scene.shot != "whole":
            raise ConfigError(
                f"the robot's shot is {scene.shot!r}; start it with `archery robot --shot whole`"
            )
        world = ArcheryWorld(WorldConfig(scene=dataclasses.replace(scene, meshes=False)))
        for part in PARTS:
            encoders = node.call_typed(node.keys.part_rpc(part), rv.GET_POSITIONS)
            world.physics.set_joint_positions(part, np.asarray(encoders.position))
        world.physics.kinematics()
        return world

    def move(self, step: ShotStep) -> None:
        """Command the step's arms on `command:i` and wait until `state:o` shows them there.

        Raises:
            RpcTimeout: a part did not get there within the timeout. Unreachable: no robot
                takes the commands.
        """
        arms = {STRING_ARM: step.right_arm}
        if step.left_arm is not None:
            arms[BOW_ARM] = step.left_arm
        after = {part: self._seq(part) for part in arms}
        for part, values in arms.items():
            if not self._commands[part].wait_matched(self._timeout):
                raise Unreachable(f"nobody subscribes to {self._commands[part].key}")
            self._commands[part].put(
                JointCommand(part=part, position=values.tolist(), batch=len(arms))
            )
        for part, values in arms.items():

            def there(msg: JointState, wanted: np.ndarray = values) -> bool:
                error = np.max(np.abs(np.asarray(msg.position) - wanted))
                return msg.motion_done and bool(error < REACHED)

            self._states[part].wait_newer(self._timeout, there, after_seq=after[part])

    def _seq(self, part: str) -> int:
        latest = self._states[part].latest()
        return 0 if latest is None else latest.seq

    def teach(self, theta: np.ndarray) -> None:
        """Aim (both arms: bow hand at `BOW_HAND`, string hand at + θ), then reach, grasp,
        lift, carry, nock, draw to bow hand + `theta` (m), hold and release.

        Raises:
            ConfigError: not a whole-shot robot. CommandError: a posture out of reach.
            RpcError: the robot refused a step (grasp_missed, nock_missed, …).
        """
        world = self.world()
        aim = plan_aim(world, BOW_HAND, theta)
        self.move(aim)
        world.physics.set_joint_positions(STRING_ARM, aim.right_arm)
        if aim.left_arm is not None:
            world.physics.set_joint_positions(BOW_ARM, aim.left_arm)
        world.physics.kinematics()
        for step in plan_whole_shot(world, theta):
            self.move(step)
            if step.action is not None:
                self.act(step.action)

    def act(self, action: str) -> object:
        """Call the robot's `grasp`, `nock` or `release`; its reply.

        Raises:
            RpcError: the robot refused it (grasp_missed, nock_missed, arrow_dropped, …).
        """
        node = self._node
        return node.call_typed(node.keys.archery_rpc(), _ACTIONS[action], timeout=self._timeout)

    def close(self) -> None:
        """Stop following the robot's states."""
        for sub in self._states.values():
            sub.close()
