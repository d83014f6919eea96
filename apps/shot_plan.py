"""The scripted whole shot, planned with the controller's inverse kinematics (Eq. 9, Pinocchio):
the arms' postures for aim, approach, reach, lift, carry, draw and hold, with the world's grasp,
nock and release in their turn, for the scripted teacher (`apps.teacher`); each step's joint
targets by name (`ShotStep.targets`), as the robot's client moves them.

Where things are (the arrow in its holder, the string's rest point on the bow, where a grasped
nock sits in the hand) is read from a copy of the robot's world (`sim.world`); every posture is
solved by `services.controller.ik.IkSolver`, the arms alone (the torso stays), each from the one
before and resting near it, inside the world's software limits. A point of a hand away from its
frame is placed by fixed-point iteration on the hand's solved orientation (as the controller's
`aim_arrow`). Positions in m (root frame), angles in rad.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from archery.protocol.errors import BadRequest
from archery.protocol.parts import PARTS
from archery.protocol.robotspec import BOW_ARM, STRING_ARM
from archery.services.controller.ik import IkSolver
from archery.services.controller.ik_types import IkSettings, OrientationTarget, PositionTarget
from archery.services.controller.model import load_arms_model
from archery.services.controller.posture import hand_orientations
from archery.sim.errors import StateError
from archery.sim.scene_config import ARROW_NOCK_SITE, BOW_HAND_SITE
from archery.sim.whole_props import NOCK_GRIP
from archery.sim.world import ArcheryWorld

__all__ = ["APPROACH_HEIGHT", "NOCK_SHIFT", "ShotStep", "plan_aim", "plan_whole_shot"]

APPROACH_HEIGHT = 0.06  # m, the hand comes down onto the arrow and lifts it by this much
#: m, how far the bow hand comes toward the right hand for the nock (the string's rest point
#: in the archery posture is beyond the right arm's reach)
NOCK_SHIFT = np.array([0.1, 0.15, -0.1])
#: the most solves that place a point of a hand, and the point's change (m) at which it stops
FIT_ITERATIONS = 6
FIT_TOLERANCE = 2e-4
_LIMB_TIPS = ("bow_top", "bow_bottom")

Action = Literal["grasp", "nock", "release"] | None


@dataclass(frozen=True)
class ShotStep:
    """One step of the shot: move the arms to `right_arm` and `left_arm` (rad, YARP order; None:
    stay), let them settle, then do `action` ("grasp", "nock", "release" or None)."""

    name: str
    right_arm: np.ndarray
    left_arm: np.ndarray | None = None
    action: Action = None

    def targets(self) -> dict[str, float]:
        """The step's joint targets {joint: rad} (the contract's `PARTS` names): the right
        arm's, and the left arm's when it moves."""
        arms = {STRING_ARM: self.right_arm, BOW_ARM: self.left_arm}
        return {
            joint: float(x)
            for part, q in arms.items()
            if q is not None
            for joint, x in zip(PARTS[part], q, strict=True)
        }


@functools.cache
def _solver(margin: float) -> IkSolver:
    """The arms' solver whose solutions stay `margin` (rad) inside the URDF limits (the
    world's software limits: the robot clamps its targets to them)."""
    return IkSolver(load_arms_model(), IkSettings(limit_margin=margin))


@dataclass
class _Planner:
    """The postures of one plan, each solved from the one before (`q`, {joint: rad})."""

    world: ArcheryWorld
    q: dict[str, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        for part in PARTS:
            self.q.update(zip(PARTS[part], self.world.joint_positions(part).tolist(), strict=True))
        self.solver = _solver(self.world.config.scene.limit_margin)

    def pose(self, arm: str) -> tuple[np.ndarray, np.ndarray]:
        """The hand frame's position (m) and rotation of `arm` at the current posture."""
        return self.solver.hand_pose(self.q, arm)

    def arm(self, part: str) -> np.ndarray:
        return np.array([self.q[j] for j in PARTS[part]])

    def solve(
        self,
        name: str,
        targets: Sequence[PositionTarget],
        orientations: Sequence[OrientationTarget] = (),
        parts: Sequence[str] = (STRING_ARM,),
    ) -> dict[str, float]:
        """The posture (not yet taken) that meets `targets`, moving `parts`' arm joints.

        Raises:
            BadRequest: a target out of the arms' reach (the message names the step).
        """
        joints = [j for part in parts for j in self.solver.model.chain(part, use_torso=False)]
        result = self.solver.solve_targets(
            targets, orientations, joints=joints, q0=self.q, rest=self.q
        )
        if not result.reachable:
            worst = max(result.position_errors_m)
            raise BadRequest(f"the shot's {name} is out of the arms' reach: {worst:.4f} m off")
        return dict(result.q)

    def place(
        self,
        name: str,
        local: np.ndarray,
        wanted: np.ndarray,
        *,
        bow: tuple[np.ndarray, np.ndarray] | None = None,
        orientations: Sequence[OrientationTarget] = (),
    ) -> None:
        """Take the posture that puts the string hand's point `local` (m, its frame) at `wanted`
        (m, root frame); with `bow` (the bow hand's position, m, and a point of its frame, m),
        the bow hand goes to that position too and the point meets the bow's point wherever the
        solution turns the bow hand."""
        q = self.q
        offsets = [self.pose(STRING_ARM)[1] @ local, np.zeros(3)]
        if bow is not None:
            offsets[1] = self.pose(BOW_ARM)[1] @ bow[1]
        for _ in range(FIT_ITERATIONS):
            if bow is None:
                targets = [PositionTarget(STRING_ARM, wanted - offsets[0])]
                parts: tuple[str, ...] = (STRING_ARM,)
            else:
                targets = [
                    PositionTarget(BOW_ARM, bow[0], priority=0),
                    PositionTarget(
                        STRING_ARM, offsets[1] - offsets[0], relative_to=BOW_ARM, priority=1
                    ),
                ]
                parts = (BOW_ARM, STRING_ARM)
            q = self.solve(name, targets, orientations, parts)
            moved = [self.solver.hand_pose(q, STRING_ARM)[1] @ local, np.zeros(3)]
            if bow is not None:
                moved[1] = self.solver.hand_pose(q, BOW_ARM)[1] @ bow[1]
            change = max(float(np.linalg.norm(m - o)) for m, o in zip(moved, offsets, strict=True))
            offsets = moved
            if change < FIT_TOLERANCE:
                break
        self.q = q

    def step(self, name: str, *, left: bool = False, action: Action = None) -> ShotStep:
        return ShotStep(name, self.arm(STRING_ARM), self.arm(BOW_ARM) if left else None, action)


def _in_site_frame(world: ArcheryWorld, site: str, point: np.ndarray) -> np.ndarray:
    """`point` (m, root frame) in the frame of the world's `site` as the world stands."""
    data, index = world.physics.data, world.physics.model.site(site).id
    local: np.ndarray = data.site_xmat[index].reshape(3, 3).T @ (point - data.site_xpos[index])
    return local


def plan_aim(world: ArcheryWorld, bow_hand: np.ndarray, theta: np.ndarray) -> ShotStep:
    """Both arms' archery posture from the world's current posture, the torso as it is: the bow
    hand at `bow_hand` (m), the string hand at `bow_hand` + `theta` (m), the hands turned as
    the controller turns them for θ (`hand_orientations`: bow grip vertical, its back toward
    the string hand; the string hand's fingers along the arrow).

    Raises:
        BadRequest: the hands cannot be there.
    """
    plan = _Planner(world)
    theta = np.asarray(theta, dtype=float)
    left, right = hand_orientations(theta)
    plan.q = plan.solve(
        "aim",
        [
            PositionTarget(BOW_ARM, np.asarray(bow_hand, dtype=float)),
            PositionTarget(STRING_ARM, theta, relative_to=BOW_ARM, priority=1),
        ],
        [OrientationTarget(BOW_ARM, left), OrientationTarget(STRING_ARM, right)],
        (BOW_ARM, STRING_ARM),
    )
    return plan.step("aim", left=True)


def plan_whole_shot(
    world: ArcheryWorld,
    theta: np.ndarray,
    *,
    grasp_offset: np.ndarray | None = None,
    nock_offset: np.ndarray | None = None,
) -> list[ShotStep]:
    """The steps of a whole shot that draws the arrow's nock to bow hand + `theta` (m).

    The bow hand starts where the world has it (in its archery posture), comes `NOCK_SHIFT`
    toward the right hand for the nock, its turn kept, and goes back for the draw.

    Args:
        world: a whole-shot world with the arrow in its holder; its state is not changed.
        theta: where the nock is drawn to, from the bow hand (m, root frame).
        grasp_offset: added to the grasp site's target on the shaft (m).
        nock_offset: added to the nock's target on the string (m).

    Raises:
        StateError: not a whole-shot world. BadRequest: a target is out of the arms' reach.
    """
    if world.whole is None:
        raise StateError("the world's shot is 'posture': the whole shot needs shot 'whole'")
    world.physics.kinematics()
    model, data = world.physics.model, world.physics.data
    plan = _Planner(world)
    nock = data.site_xpos[model.site(ARROW_NOCK_SITE).id].copy()
    tip = world.physics.arrow_tip()
    along = (tip - nock) / np.linalg.norm(tip - nock)
    grip = nock + NOCK_GRIP * along + (np.zeros(3) if grasp_offset is None else grasp_offset)
    up = np.array([0.0, 0.0, APPROACH_HEIGHT])
    site = np.zeros(3)  # the grasp site is the string hand's frame (`sim.whole_props`)
    steps = []
    plan.place("approach", site, grip + up)
    steps.append(plan.step("approach"))
    plan.place("reach", site, grip)
    steps.append(plan.step("reach", action="grasp"))
    # where the nock sits in the hand once grasped: fixed by the weld from then on
    x, rot = plan.pose(STRING_ARM)
    in_hand = rot.T @ (nock - x)
    plan.place("lift", in_hand, nock + up)
    steps.append(plan.step("lift"))
    # the string's rest point, midway between the limb tips, in the bow hand's frame
    tips = [data.site_xpos[model.site(n).id] for n in _LIMB_TIPS]
    rest = _in_site_frame(world, BOW_HAND_SITE, np.mean(tips, axis=0))
    if nock_offset is not None:  # a root-frame vector, turned into the bow hand's frame
        turn = data.site_xmat[model.site(BOW_HAND_SITE).id].reshape(3, 3)
        rest = rest + turn.T @ np.asarray(nock_offset, dtype=float)
    bow_posture = plan.arm(BOW_ARM)
    bow_hand, bow_turn = plan.pose(BOW_ARM)
    plan.place(
        "carry",
        in_hand,
        np.zeros(3),
        bow=(bow_hand + NOCK_SHIFT, rest),
        orientations=[OrientationTarget(BOW_ARM, bow_turn)],
    )
    steps.append(plan.step("carry", left=True, action="nock"))
    plan.q.update(zip(PARTS[BOW_ARM], bow_posture.tolist(), strict=True))
    plan.place("draw", in_hand, bow_hand + np.asarray(theta, dtype=float))
    steps.append(plan.step("draw", left=True))
    steps.append(plan.step("hold", action="release"))
    return steps
