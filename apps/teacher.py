"""A scripted teacher of the whole shot over the mesh (`archery demonstrate --teach`): the arms'
postures of `apps.shot_plan`, planned with the controller's IK on a copy of the robot's scene,
driven on the mesh (`apps.arms`), with the robot's grasp, nock and release in their turn. The
robot must run with `--shot whole` and stand as `reset` leaves it (every part at home, the arrow
in its holder): a demonstration starts where every imitation of it starts, and the script is
planned from there. The teacher does not reset the robot itself (a reset is the whole world's:
simulated time back to 0, the arrow back in its holder, under another client's feet too); a
robot elsewhere is refused, naming the reset. Joint angles in rad, positions in m.
"""

from __future__ import annotations

import numpy as np

from archery.apps.arms import ArmDriver
from archery.apps.shot_plan import plan_aim, plan_whole_shot
from archery.protocol.errors import ArcheryError
from archery.protocol.parts import PARTS
from archery.protocol.robotspec import BOW_ARM, STRING_ARM, home_of
from archery.protocol.verbs import robot as rv
from archery.sim.geometry import BOW_HAND

__all__ = ["HOME_TOLERANCE", "NotAtStart", "Teacher"]

HOME_TOLERANCE = 0.01  # rad: a joint this close to its home angle is at home


class NotAtStart(ArcheryError):
    """The robot does not stand as `reset` leaves it: a part away from home, or no arrow in its
    holder (an earlier shot)."""

    code = "bad_state"


class Teacher(ArmDriver):
    """Drives one robot through the scripted whole shot (`ArmDriver`'s node and timeout)."""

    def check_start(self) -> None:
        """Refuse a robot that is not at its starting posture: every part within
        `HOME_TOLERANCE` of home and the arrow in its holder, as `reset` leaves it.

        Raises:
            ConfigError: not a whole-shot robot. NotAtStart: elsewhere (the message names
                where, and the reset).
        """
        self.scene()
        node = self._node
        keys = node.keys
        away = []
        for part in PARTS:
            encoders = node.call_typed(keys.part_rpc(part), rv.GET_POSITIONS)
            off = float(np.max(np.abs(np.asarray(encoders.position) - np.asarray(home_of(part)))))
            if off > HOME_TOLERANCE:
                away.append(f"{part} {off:.2f} rad from home")
        arrow = node.call_typed(keys.archery_rpc(), rv.ARCHERY_STATUS).arrow
        if arrow != "stowed":
            away.append(f"the arrow {arrow}, not in its holder")
        if away:
            raise NotAtStart(
                f"the robot is not at its starting posture ({', '.join(away)}): reset it with "
                f"`archery rpc {keys.archery_rpc()} reset`, then teach again"
            )

    def teach(self, theta: np.ndarray) -> None:
        """From the robot's starting posture (`check_start`), aim (both arms: bow hand at
        `BOW_HAND`, string hand at + θ), then reach, grasp, lift, carry, nock, draw to bow
        hand + `theta` (m), hold and release.

        Raises:
            ConfigError: not a whole-shot robot. NotAtStart: not at its starting posture.
            BadRequest: a posture out of reach. RpcError: the robot refused a step
            (grasp_missed, nock_missed, …).
        """
        self.check_start()
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
