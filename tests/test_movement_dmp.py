"""The whole shot learned as DMPs from the shipped demonstration: the reproduction's error, the
movement from the DMPs alone in the simulator (grasp, nock, draw, release), and its goal moved
to the archery posture of another θ."""

from __future__ import annotations

import itertools

import msgspec
import numpy as np
import pytest

from protocol.demonstration import BadDemonstration, Demonstration, parse_demonstration
from protocol.robotspec import BOW_ARM, STRING_ARM
from protocol.verbs.controller import THETA_MAX, THETA_MIN
from services.learner.config import SHIPPED_DEMONSTRATION
from services.learner.movement import Movement, Reproduction
from services.learner.whole_movement import DRAW_TOLERANCE, plan
from sim.arrow import Launch
from sim.geometry import START_THETA
from sim.scene_config import SceneConfig
from sim.shot_script import plan_draw
from sim.world import ArcheryWorld, ArrowState, WorldConfig
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


def _drawn(demo: Demonstration, movement: Movement, theta: np.ndarray) -> tuple[float, float]:
    """The DMPs to the nock, then to the archery posture of `theta` (m) as the goal: checks
    the nock is drawn there; returns (draw length (m), launch speed (m/s))."""
    world = _at_start(demo)
    _to_the_nock(world, movement.reproduce())
    draw = plan_draw(world, theta, movement.goal[:7])
    moved = movement.reproduce(np.concatenate([movement.goal[:7], draw.right_arm]))
    _follow(world, moved, moved.nock, moved.release)
    assert move_until_done(world)
    bow, _ = world.hand_positions()
    assert world.whole is not None
    np.testing.assert_allclose(world.whole.nocking_point() - bow, theta, atol=5e-3)
    length = world.whole.draw_length()
    return length, float(np.linalg.norm(world.launch().velocity))


def test_the_goal_of_another_theta_draws_there(demo: Demonstration, movement: Movement) -> None:
    (short, slow), (long, fast) = (_drawn(demo, movement, k * START_THETA) for k in (0.9, 1.1))
    assert long > short + 0.01 and fast > slow
    assert fast == pytest.approx(WORLD.bow.speed_for_draw(long), rel=1e-9)


def test_a_demonstration_without_a_grasp_is_refused(demo: Demonstration) -> None:
    posture_only = msgspec.structs.replace(
        demo, events=[e for e in demo.events if e.kind != "grasped"]
    )
    with pytest.raises(BadDemonstration, match="no grasped event"):
        Movement(posture_only)


def test_the_draw_is_planned_for_every_corner_of_the_controllers_box() -> None:
    """The string arm alone, the bow arm as demonstrated, reaches each corner of the θ box
    within the draw's tolerance (the controller's posture, with the torso, does the rest)."""
    world = ArcheryWorld(WorldConfig(scene=SceneConfig(meshes=False, shot="whole")))
    movement = Movement(parse_demonstration(SHIPPED.read_bytes()))
    for corner in itertools.product(*zip(THETA_MIN, THETA_MAX, strict=True)):
        rollout = plan(world, movement, np.array(corner))
        world.physics.set_joint_positions(BOW_ARM, rollout.left_arm[-1])
        world.physics.set_joint_positions(STRING_ARM, rollout.right_arm[-1])
        assert np.linalg.norm(world.theta() - np.array(corner)) < DRAW_TOLERANCE + 0.005, corner
