"""The scripted whole shot: the right arm's joint targets for reach, grasp, carry, nock, draw,
hold and release, planned on a whole-shot scene (`sim.whole_shot`) with `sim.reach`.

`plan_whole_shot` plans from the scene's current state (the bow hand stays where it is): the
grasp site to the arrow's shaft in its holder, `NOCK_GRIP` from its nock; the arrow's nock,
carried in the closed hand, onto the string's rest nocking point; then drawn to the bow hand
+ θ. Offsets (m) move the grasp or the nock target, to try the tolerances. Each step is a
posture of the right arm (rad) to reach and settle, then an action of the world, if any.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import mujoco
import numpy as np

from archery.protocol.robotspec import BOW_ARM, STRING_ARM
from archery.sim.errors import StateError
from archery.sim.reach import PointTarget, reach
from archery.sim.scene import ScenePhysics
from archery.sim.scene_config import ARROW_NOCK_SITE, BOW_HAND_SITE, GRASP_SITE
from archery.sim.whole_props import NOCK_GRIP
from archery.sim.world import ArcheryWorld

__all__ = [
    "APPROACH_HEIGHT",
    "NOCK_SHIFT",
    "ShotStep",
    "plan_aim",
    "plan_draw",
    "plan_string_hand",
    "plan_whole_shot",
]

APPROACH_HEIGHT = 0.06  # m, the hand comes down onto the arrow and lifts it by this much
#: m, how far the bow hand comes toward the right hand for the nock (the string's rest point
#: in the archery posture is beyond the right arm's reach)
NOCK_SHIFT = np.array([0.1, 0.15, -0.1])
_LIMB_TIPS = ("bow_top", "bow_bottom")
_AXIS_LENGTH = 0.1  # m
_SHIFT_WEIGHT, _TURN_WEIGHT = 0.5, 0.2  # how much the bow hand and its turn may give way

Action = Literal["grasp", "nock", "release"] | None


@dataclass(frozen=True)
class ShotStep:
    """One step of the shot: move the arms to `right_arm` and `left_arm` (rad, YARP order; None:
    stay), let them settle, then do `action` ("grasp", "nock", "release" or None)."""

    name: str
    right_arm: np.ndarray
    left_arm: np.ndarray | None = None
    action: Action = None


def plan_whole_shot(
    world: ArcheryWorld,
    theta: np.ndarray,
    *,
    grasp_offset: np.ndarray | None = None,
    nock_offset: np.ndarray | None = None,
) -> list[ShotStep]:
    """The steps of a whole shot that draws the arrow's nock to bow hand + `theta` (m).

    The bow hand starts where the world has it (in its archery posture), comes `NOCK_SHIFT`
    toward the right hand for the nock, its bow turned as before, and goes back for the draw.

    Args:
        world: a whole-shot world with the arrow in its holder; its state is not changed.
        theta: where the nock is drawn to, from the bow hand (m, root frame).
        grasp_offset: added to the grasp site's target on the shaft (m).
        nock_offset: added to the nock's target on the string (m).

    Raises:
        StateError: not a whole-shot world. CommandError: a target is out of the arms' reach.
    """
    whole = world.whole
    if whole is None:
        raise StateError("the world's shot is 'posture': the whole shot needs shot 'whole'")
    physics = world.physics
    physics.kinematics()
    model, data = physics.model, physics.data
    grasp_site = model.site(GRASP_SITE)
    hand = model.body(int(grasp_site.bodyid[0])).name
    site_offset = model.site_pos[grasp_site.id].copy()
    limits = {part: world.joint_limits(part) for part in (STRING_ARM, BOW_ARM)}
    arms = {part: world.joint_positions(part) for part in (STRING_ARM, BOW_ARM)}
    bow_posture = arms[BOW_ARM].copy()
    nock = data.site_xpos[model.site(ARROW_NOCK_SITE).id].copy()
    tip = physics.arrow_tip()
    along = (tip - nock) / np.linalg.norm(tip - nock)
    grip = nock + NOCK_GRIP * along + (np.zeros(3) if grasp_offset is None else grasp_offset)
    up = np.array([0.0, 0.0, APPROACH_HEIGHT])

    def solve(targets: list[PointTarget], parts: tuple[str, ...] = (STRING_ARM,)) -> np.ndarray:
        arms.update(reach(physics, targets, parts, arms, limits))
        return arms[STRING_ARM].copy()

    steps = [
        ShotStep("approach", solve([PointTarget(hand, site_offset, grip + up)])),
        ShotStep("reach", solve([PointTarget(hand, site_offset, grip)]), action="grasp"),
    ]
    # where the nock sits in the hand once grasped: fixed by the weld from then on
    nock_in_hand = _in_body_frame(world, hand, arms[STRING_ARM], nock)
    steps.append(ShotStep("lift", solve([PointTarget(hand, nock_in_hand, nock + up)])))
    # the bow, turned as it is, comes NOCK_SHIFT toward the right hand: three of its points
    bow_points = [model.site(BOW_HAND_SITE), *(model.site(n) for n in _LIMB_TIPS)]
    bow_body = model.body(int(bow_points[0].bodyid[0])).name
    shifted = [
        PointTarget(
            bow_body,
            model.site_pos[p.id].copy(),
            data.site_xpos[p.id] + NOCK_SHIFT,
            _SHIFT_WEIGHT if p.name == BOW_HAND_SITE else _TURN_WEIGHT,
        )
        for p in bow_points
    ]
    # the nock onto the string's rest point (midway between the limb tips), wherever the bow is
    rest = np.mean([model.site_pos[p.id] for p in bow_points[1:]], axis=0)
    rest = rest + (np.zeros(3) if nock_offset is None else _in_frame(world, bow_body, nock_offset))
    onto_string = PointTarget(hand, nock_in_hand, rest, meet=(bow_body, rest))
    right = solve([*shifted, onto_string], (BOW_ARM, STRING_ARM))
    steps.append(ShotStep("carry", right, arms[BOW_ARM].copy(), "nock"))
    arms[BOW_ARM] = bow_posture
    bow, _ = world.hand_positions()
    draw = solve([PointTarget(hand, nock_in_hand, bow + np.asarray(theta))])
    steps.append(ShotStep("draw", draw, bow_posture.copy()))
    steps.append(ShotStep("hold", draw.copy(), action="release"))
    return steps


def plan_aim(world: ArcheryWorld, bow_hand: np.ndarray, theta: np.ndarray) -> ShotStep:
    """Both arms' archery posture: the bow hand at `bow_hand` (m), its grip vertical (thumb up)
    and its back toward the string hand, which is at `bow_hand` + `theta` (m); from the
    world's current posture, the torso as it is.

    Raises:
        CommandError: the hands cannot be there.
    """
    physics = world.physics
    model = physics.model
    bow_hand = np.asarray(bow_hand, dtype=float)
    theta = np.asarray(theta, dtype=float)
    limits = {part: world.joint_limits(part) for part in (STRING_ARM, BOW_ARM)}
    start = {part: world.joint_positions(part) for part in (STRING_ARM, BOW_ARM)}
    site = model.site(BOW_HAND_SITE)
    body = model.body(int(site.bodyid[0])).name
    rot = np.empty(9)
    mujoco.mju_quat2Mat(rot, model.site_quat[site.id])
    axes = rot.reshape(3, 3)
    down, back = np.array([0.0, 0.0, -1.0]), theta / np.linalg.norm(theta)
    string = model.site(GRASP_SITE)
    arms = reach(
        physics,
        [
            PointTarget(body, model.site_pos[site.id].copy(), bow_hand),
            # the orientation, by two points an arm's length of the hand away (soft)
            PointTarget(
                body,
                model.site_pos[site.id] + _AXIS_LENGTH * axes[:, 1],
                bow_hand + _AXIS_LENGTH * down,
                _TURN_WEIGHT,
            ),
            PointTarget(
                body,
                model.site_pos[site.id] + _AXIS_LENGTH * axes[:, 2],
                bow_hand + _AXIS_LENGTH * back,
                _TURN_WEIGHT,
            ),
            PointTarget(
                model.body(int(string.bodyid[0])).name,
                model.site_pos[string.id].copy(),
                bow_hand + theta,
            ),
        ],
        (BOW_ARM, STRING_ARM),
        start,
        limits,
    )
    return ShotStep("aim", arms[STRING_ARM], arms[BOW_ARM])


def _bow_hand(physics: ScenePhysics, bow_arm: np.ndarray) -> np.ndarray:
    """The bow hand's position (m, world) with the bow arm at `bow_arm` (rad) and every other
    joint where the world has it now."""
    model = physics.model
    data = mujoco.MjData(model)
    data.qpos[:] = physics.data.qpos
    data.qpos[physics.qpos_indices(BOW_ARM)] = bow_arm
    mujoco.mj_kinematics(model, data)
    return np.array(data.site_xpos[model.site(BOW_HAND_SITE).id])


def plan_draw(world: ArcheryWorld, theta: np.ndarray, bow_arm: np.ndarray) -> ShotStep:
    """The right arm's posture that draws the nocked arrow's nock to the bow hand + `theta` (m),
    with the bow arm at `bow_arm` (rad: where it will be for the draw, its archery posture).

    Raises:
        StateError: no arrow is nocked. CommandError: out of the arm's reach.
    """
    whole = world.whole
    if whole is None or not whole.nocked:
        raise StateError("no arrow is on the string to draw; nock one first")
    physics = world.physics
    physics.kinematics()
    model = physics.model
    hand = model.body(int(model.site(GRASP_SITE).bodyid[0])).name
    arm = world.joint_positions(STRING_ARM)
    nock = _in_body_frame(world, hand, arm, whole.nocking_point())
    bow = _bow_hand(physics, bow_arm)
    arms = reach(
        physics,
        [PointTarget(hand, nock, bow + np.asarray(theta, dtype=float))],
        (STRING_ARM,),
        {STRING_ARM: arm},
        {STRING_ARM: world.joint_limits(STRING_ARM)},
        others={BOW_ARM: np.asarray(bow_arm, dtype=float)},
    )
    return ShotStep("draw", arms[STRING_ARM], np.asarray(bow_arm, dtype=float).copy())


def plan_string_hand(
    world: ArcheryWorld, theta: np.ndarray, bow_arm: np.ndarray, tolerance: float = 2e-3
) -> ShotStep:
    """The right arm's posture that puts the string hand at the bow hand + `theta` (m, the
    paper's θ) within `tolerance` (m), with the bow arm at `bow_arm` (rad), from the world's
    current posture.

    Raises:
        CommandError: out of the arm's reach.
    """
    physics = world.physics
    model = physics.model
    string = model.site(GRASP_SITE)
    bow = _bow_hand(physics, bow_arm)
    arms = reach(
        physics,
        [
            PointTarget(
                model.body(int(string.bodyid[0])).name,
                model.site_pos[string.id].copy(),
                bow + np.asarray(theta, dtype=float),
            )
        ],
        (STRING_ARM,),
        {STRING_ARM: world.joint_positions(STRING_ARM)},
        {STRING_ARM: world.joint_limits(STRING_ARM)},
        tolerance=tolerance,
        others={BOW_ARM: np.asarray(bow_arm, dtype=float)},
    )
    return ShotStep("hold", arms[STRING_ARM], np.asarray(bow_arm, dtype=float).copy())


def _in_body_frame(
    world: ArcheryWorld, body: str, arm: np.ndarray, point: np.ndarray
) -> np.ndarray:
    """`point` (m, root frame) in `body`'s frame with the right arm at `arm` (rad)."""
    physics = world.physics
    data = mujoco.MjData(physics.model)
    data.qpos[:] = physics.data.qpos
    data.qpos[physics.qpos_indices(STRING_ARM)] = arm
    mujoco.mj_kinematics(physics.model, data)
    b = physics.model.body(body).id
    local: np.ndarray = data.xmat[b].reshape(3, 3).T @ (point - data.xpos[b])
    return local


def _in_frame(world: ArcheryWorld, body: str, vector: np.ndarray) -> np.ndarray:
    """The root-frame `vector` (m) in `body`'s frame as the world stands."""
    rot = world.physics.data.xmat[world.physics.model.body(body).id].reshape(3, 3)
    local: np.ndarray = rot.T @ np.asarray(vector, dtype=float)
    return local
