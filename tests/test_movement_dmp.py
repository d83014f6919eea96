"""The whole shot learned as DMPs from the shipped demonstration: the reproduction's error, the
movement from the DMPs alone in the simulator (grasp, nock, draw, release), and its goal moved
to the archery posture of another θ."""

from __future__ import annotations

import itertools
from collections.abc import Mapping

import msgspec
import numpy as np
import pytest

from archery.protocol.demonstration import BadDemonstration, Demonstration, parse_demonstration
from archery.protocol.parts import PARTS
from archery.protocol.robotspec import BOW_ARM, STRING_ARM
from archery.protocol.theta import THETA_BOX
from archery.services.controller.demonstration_file import SHIPPED_DEMONSTRATION
from archery.services.controller.movement import Movement, Reproduction
from archery.services.controller.posture import ArcheryPosture, PostureConfig
from archery.services.controller.whole_shot import (
    PARTS_MOVED,
    aim_arrow,
    plan_whole_shot,
    whole_shot_trajectory,
)
from archery.sim.arrow import Launch
from archery.sim.geometry import START_THETA
from archery.sim.scene_config import SceneConfig
from archery.sim.whole_shot import NOCK_IN_STRING_HAND
from archery.sim.world import ArcheryWorld, ArrowState, WorldConfig
from tests.world_steps import move_until_done

SHIPPED = SHIPPED_DEMONSTRATION
WORLD = WorldConfig(
    scene=SceneConfig(meshes=False, shot="whole"), speed_noise=0.0, direction_noise=0.0
)


@pytest.fixture(scope="module")
def demo() -> Demonstration:
    return parse_demonstration(SHIPPED.read_bytes())


@pytest.fixture(scope="module")
def movement(demo: Demonstration) -> Movement:
    return Movement(demo)


@pytest.fixture(scope="module")
def posture() -> ArcheryPosture:
    return ArcheryPosture(PostureConfig())


def _goal(posture: ArcheryPosture, theta: np.ndarray) -> np.ndarray:
    """Both arms' angles (rad, left then right) of the controller's posture for θ (m)."""
    return _goal_of(posture.solve_checked(theta).q)


def _goal_of(q: Mapping[str, float]) -> np.ndarray:
    """Both arms' angles (rad, left then right) of the posture q."""
    return np.array([q[j] for part in (BOW_ARM, STRING_ARM) for j in PARTS[part]])


def _at_start(demo: Demonstration) -> ArcheryWorld:
    """A whole-shot world standing in the demonstration's first posture."""
    world = ArcheryWorld(WORLD)
    first = demo.samples[0]
    world.set_joint_targets(BOW_ARM, first.left_arm)
    world.set_joint_targets(STRING_ARM, first.right_arm)
    assert move_until_done(world)
    return world


def _follow(world: ArcheryWorld, rollout: Reproduction, start: float, end: float) -> None:
    """Stream the rollout's postures as the arms' targets from `start` to `end` (s)."""
    dt = float(np.median(np.diff(rollout.t)))
    when = start
    while when < end - 1e-9:
        when = min(when + dt, end)
        left, right = rollout.at(when)
        world.set_joint_targets(BOW_ARM, left)
        world.set_joint_targets(STRING_ARM, right)
        world.step(dt)


def _to_the_nock(world: ArcheryWorld, rollout: Reproduction) -> None:
    _follow(world, rollout, 0.0, rollout.grasp)
    world.grasp()
    _follow(world, rollout, rollout.grasp, rollout.nock)
    world.nock()


def _release(world: ArcheryWorld, rollout: Reproduction) -> Launch:
    _follow(world, rollout, rollout.nock, rollout.release)
    launch = world.launch()
    while world.step(0.01) is None:
        pass
    return launch


def test_the_dmps_reproduce_the_demonstration(demo: Demonstration, movement: Movement) -> None:
    assert movement.error(demo) < 0.01  # rad, joint RMS
    final = movement.reproduce()
    goal = np.array([*demo.samples[-1].left_arm, *demo.samples[-1].right_arm])
    ends = np.concatenate([final.left_arm[-1], final.right_arm[-1]])
    np.testing.assert_allclose(ends, goal, atol=1e-3)


def test_the_dmps_alone_grasp_nock_draw_and_release(
    demo: Demonstration, movement: Movement
) -> None:
    world = _at_start(demo)
    rollout = movement.reproduce()
    _to_the_nock(world, rollout)
    assert world.arrow_state is ArrowState.NOCKED
    launch = _release(world, rollout)
    assert np.linalg.norm(launch.velocity) > 1.0
    assert world.arrow_state is ArrowState.LANDED


def _drawn(
    demo: Demonstration, movement: Movement, posture: ArcheryPosture, theta: np.ndarray
) -> tuple[float, float]:
    """The DMPs to the nock, then to the controller's archery posture of `theta` (m) as the
    goal (its torso too): checks the hands are drawn there; returns (draw length (m), launch
    speed (m/s))."""
    world = _at_start(demo)
    _to_the_nock(world, movement.reproduce())
    q = posture.solve_checked(theta).q
    moved = movement.reproduce(_goal(posture, theta))
    world.set_joint_targets("torso", [q[j] for j in PARTS["torso"]])
    _follow(world, moved, moved.nock, moved.release)
    assert move_until_done(world)
    np.testing.assert_allclose(world.theta(), theta, atol=5e-3)
    assert world.whole is not None
    length = float(np.linalg.norm(world.whole.arrow_line())) - WORLD.bow.brace_height
    return length, float(np.linalg.norm(world.launch().velocity))


@pytest.mark.parametrize("corner", ["low", "nominal", "high"])
def test_the_controller_aims_the_arrow_along_theta(
    demo: Demonstration, movement: Movement, posture: ArcheryPosture, corner: str
) -> None:
    """The hands drawn to θ less the nock's offset (told by the robot): the nocked arrow lies
    along θ from the bow hand, its nock where the robot says it sits in the string hand."""
    theta = {"low": THETA_BOX.low, "nominal": START_THETA, "high": THETA_BOX.high}[corner]
    theta = np.asarray(theta, dtype=float)
    world = _at_start(demo)
    _to_the_nock(world, movement.reproduce())
    q = aim_arrow(posture, theta, NOCK_IN_STRING_HAND)[0].q
    moved = movement.reproduce(_goal_of(q))
    world.set_joint_targets("torso", [q[j] for j in PARTS["torso"]])
    _follow(world, moved, moved.nock, moved.release)
    assert move_until_done(world)
    assert world.whole is not None
    np.testing.assert_allclose(world.whole.nock_in_hand(), NOCK_IN_STRING_HAND, atol=3e-3)
    np.testing.assert_allclose(world.whole.arrow_line(), theta, atol=6e-3)
    assert not aim_arrow(posture, theta, None)[1].any()


def test_the_goal_of_another_theta_draws_there(
    demo: Demonstration, movement: Movement, posture: ArcheryPosture
) -> None:
    (short, slow), (long, fast) = (
        _drawn(demo, movement, posture, k * START_THETA) for k in (0.9, 1.1)
    )
    assert long > short + 0.01 and fast > slow
    assert fast == pytest.approx(WORLD.bow.speed_for_draw(long), rel=1e-9)


def test_a_demonstration_without_a_grasp_is_refused(demo: Demonstration) -> None:
    posture_only = msgspec.structs.replace(
        demo, events=[e for e in demo.events if e.kind != "grasped"]
    )
    with pytest.raises(BadDemonstration, match="no grasped event"):
        Movement(posture_only)


def test_the_whole_shot_ends_in_the_posture_for_every_corner_of_the_box(
    movement: Movement, posture: ArcheryPosture
) -> None:
    """The controller's whole shot for each corner of the θ box ends in its IK posture for
    that corner: the hands at the θ it achieves, from a robot at home."""
    world = ArcheryWorld(WorldConfig(scene=SceneConfig(meshes=False, shot="whole")))
    standing = {
        j: float(v) for p in PARTS for j, v in zip(PARTS[p], world.joint_positions(p), strict=True)
    }
    for corner in itertools.product(*zip(THETA_BOX.low, THETA_BOX.high, strict=True)):
        solved = posture.solve_checked(np.array(corner))
        plan = whole_shot_trajectory(movement, solved.q, standing)
        assert plan.lead < 0.05  # the demonstration starts at home
        at = 0
        for part in PARTS_MOVED:
            n = len(PARTS[part])
            world.physics.set_joint_positions(part, plan.rows[-1, at : at + n])
            at += n
        world.physics.kinematics()
        # the hands where the controller's IK put them (the two models differ by < 1 cm there)
        assert np.linalg.norm(world.theta() - solved.theta_achieved) < 0.01, corner
        assert solved.relative_error_m < 0.01, corner


def test_the_movement_stays_within_the_joint_limits_where_the_goal_is_at_one(
    movement: Movement, posture: ArcheryPosture
) -> None:
    """A posture with a joint at its limit: the DMPs drawn there overshoot it; the waypoints
    sent are clipped to the model's limits (the robot would refuse them: bad_trajectory)."""
    theta = np.array([0.127, 0.01, -0.036])
    standing = {j: 0.0 for part in PARTS for j in PARTS[part]}
    aimed = plan_whole_shot(movement, posture, theta, NOCK_IN_STRING_HAND, standing)
    model = posture.model
    moved = [model.index(j) for part in PARTS_MOVED for j in PARTS[part]]
    lower, upper = model.lower[moved], model.upper[moved]
    free = whole_shot_trajectory(movement, aimed.posture.q, standing)
    assert np.any(free.rows > upper + 1e-3)  # the overshoot this guards against
    assert np.all((aimed.plan.rows >= lower) & (aimed.plan.rows <= upper))
