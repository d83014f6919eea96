"""A scripted teacher of the whole shot over the mesh (`archery demonstrate --teach`): the arms'
postures of `apps.shot_plan`, planned with the controller's IK on a copy of the robot's scene,
driven on the mesh (`apps.arms`), with the robot's grasp, nock and release in their turn. The
robot must run with `--shot whole`; joint angles in rad, positions in m.
"""

from __future__ import annotations

import numpy as np

from archery.apps.arms import ArmDriver
from archery.apps.shot_plan import plan_aim, plan_whole_shot
from archery.protocol.robotspec import BOW_ARM, STRING_ARM
from archery.sim.geometry import BOW_HAND

__all__ = ["Teacher"]


class Teacher(ArmDriver):
    """Drives one robot through the scripted whole shot (`ArmDriver`'s node and timeout)."""

    def teach(self, theta: np.ndarray) -> None:
        """Aim (both arms: bow hand at `BOW_HAND`, string hand at + θ), then reach, grasp,
        lift, carry, nock, draw to bow hand + `theta` (m), hold and release.

        Raises:
            ConfigError: not a whole-shot robot. BadRequest: a posture out of reach.
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
