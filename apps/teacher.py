"""A scripted teacher of the whole shot over the mesh (`archery demonstrate --teach`): the arms'
postures of `apps.shot_plan`, planned with the controller's IK on a copy of the robot's scene
standing as the robot does, moved through the robot's client (`mesh.robot_client`) under the
arms' and the torso's leases, with the robot's grasp, nock and release in their turn. The robot
must run with `--shot whole` and stand as `reset` leaves it (every part at home, the arrow in its
holder): a demonstration starts where every imitation of it starts, and the script is planned
from there. The teacher does not reset the robot itself (a reset is the whole world's: simulated
time back to 0, the arrow back in its holder, under another client's feet too); a robot
elsewhere is refused, naming the reset. Joint angles in rad, positions in m.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import numpy as np

from archery.apps.shot_plan import ShotStep, plan_aim, plan_whole_shot
from archery.mesh.node import Node
from archery.mesh.robot_client import Moved, RobotClient
from archery.mesh.robot_leases import Claim
from archery.protocol.errors import ArcheryError, ConfigError
from archery.protocol.parts import PARTS
from archery.protocol.robotspec import BOW_ARM, COMMAND_RATE, STRING_ARM, TORSO, home_of
from archery.protocol.verbs.base import Reply
from archery.sim.geometry import BOW_HAND
from archery.sim.scene_config import SceneConfig
from archery.sim.world import ArcheryWorld, WorldConfig

__all__ = ["COMMAND_PERIOD", "HOME_TOLERANCE", "OWNER", "NotAtStart", "Teacher"]

HOME_TOLERANCE = 0.01  # rad: a joint this close to its home angle is at home
#: Wall s at least between two moves' commands: under the rate a robot admits by default
#: (`COMMAND_RATE`), whose excess it drops (a dropped waypoint would never be reached).
COMMAND_PERIOD = 1.5 / COMMAND_RATE
OWNER = "teacher"  # the leases' owner (in secure mode the robot names the caller's identity)
#: the parts the teacher holds while it teaches: the arms it moves, the torso its plan stands on
HELD = (BOW_ARM, STRING_ARM, TORSO)


class NotAtStart(ArcheryError):
    """The robot does not stand as `reset` leaves it: a part away from home, or no arrow in its
    holder (an earlier shot)."""

    code = "bad_state"


class Teacher:
    """Drives one robot through the scripted whole shot.

    Args:
        node: a node on the robot's mesh.
        timeout: wall s to wait for each move and each of the robot's verbs.
    """

    def __init__(self, node: Node, timeout: float) -> None:
        self.robot = RobotClient(node, timeout=timeout)
        self.timeout = timeout

    def scene(self) -> SceneConfig:
        """The robot's scene (its `status`).

        Raises:
            ConfigError: the robot does not run the whole shot.
        """
        scene = SceneConfig.of(self.robot.scene())
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
        for part in PARTS:
            world.physics.set_joint_positions(part, self.robot.positions(part))
        world.physics.kinematics()

    def check_start(self) -> SceneConfig:
        """Refuse a robot that is not at its starting posture: every part within
        `HOME_TOLERANCE` of home and the arrow in its holder, as `reset` leaves it; its scene.

        Raises:
            ConfigError: not a whole-shot robot. NotAtStart: elsewhere (the message names
                where, and the reset).
        """
        scene = self.scene()
        away = []
        for part in PARTS:
            off = float(np.max(np.abs(self.robot.positions(part) - np.asarray(home_of(part)))))
            if off > HOME_TOLERANCE:
                away.append(f"{part} {off:.2f} rad from home")
        arrow = self.robot.status().arrow
        if arrow != "stowed":
            away.append(f"the arrow {arrow}, not in its holder")
        if away:
            raise NotAtStart(
                f"the robot is not at its starting posture ({', '.join(away)}): reset it with "
                f"`archery rpc {self.robot.keys.archery_rpc()} reset`, then teach again"
            )
        return scene

    def move(self, step: ShotStep, held: Claim, *, settle: bool = True) -> Moved:
        """Move to the step's arm postures under `held`'s leases, paced by `COMMAND_PERIOD`, and
        wait until the robot rests there (`settle`, `TOLERANCES["rest"]`) or passes it on its
        way (`TOLERANCES["passing"]`: a waypoint the next one follows); the step's action is
        the caller's.

        Raises:
            RobotError: not there within the timeout (`not_reached`), a part taken over
                (`not_owner`), the robot lost (`lost`).
        """
        return self.robot.move(
            step.targets(),
            until="rest" if settle else "passing",
            claim=held,
            timeout=self.timeout,
            pace=COMMAND_PERIOD,
        )

    def act(self, action: str) -> Reply:
        """Call the robot's `grasp`, `nock` or `release`; its reply.

        Raises:
            RpcError: the robot refused it (grasp_missed, nock_missed, arrow_dropped, …).
        """
        verbs: dict[str, Callable[[], Any]] = {
            "grasp": self.robot.grasp,
            "nock": self.robot.nock,
            "release": self.robot.release,
        }
        reply: Reply = verbs[action]()
        return reply

    def teach(self, theta: np.ndarray) -> None:
        """From the robot's starting posture (`check_start`), aim (both arms: bow hand at
        `BOW_HAND`, string hand at + θ), then reach, grasp, lift, carry, nock, draw to bow
        hand + `theta` (m), hold and release; the whole plan is made before anything moves,
        and the arms and the torso held meanwhile (`HELD`, under `OWNER`).

        Raises:
            ConfigError: not a whole-shot robot. NotAtStart: not at its starting posture.
            BadRequest: a posture out of reach. RobotError: the robot refused a step
            (not_owner, grasp_missed, nock_missed, …) or did not reach it.
        """
        world = self.world(self.check_start())
        aim = plan_aim(world, BOW_HAND, theta)
        world.physics.set_joint_positions(STRING_ARM, aim.right_arm)
        if aim.left_arm is not None:
            world.physics.set_joint_positions(BOW_ARM, aim.left_arm)
        world.physics.kinematics()
        steps = plan_whole_shot(world, theta)
        with self.robot.claim(HELD, OWNER) as held:
            self.move(aim, held)
            for step in steps:
                self.move(step, held)
                if step.action is not None:
                    self.act(step.action)

    def close(self) -> None:
        """Stop following the robot (the leases go when `teach` ends)."""
        self.robot.close()
