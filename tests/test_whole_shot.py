"""The whole shot in the simulator (`SceneConfig(shot="whole")`): the arrow in its holder, the
grasp and nock gated by their tolerances, the string drawn, the release from the draw length."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from archery.apps.shot_plan import APPROACH_HEIGHT, ShotStep, plan_aim, plan_whole_shot
from archery.protocol.errors import BadRequest
from archery.protocol.robotspec import BOW_ARM, STRING_ARM
from archery.sim.errors import ArrowDropped, GraspMissed, NockMissed, StateError
from archery.sim.geometry import BOW_HAND, START_THETA
from archery.sim.model_build import build_scene
from archery.sim.scene_config import BOWSTRING_TENDON, STRING_NOCK_SITE, SceneConfig
from archery.sim.whole_props import HOLDER_NOCK
from archery.sim.world import ArcheryWorld, ArrowState, WorldConfig
from tests.postures import archery_posture
from tests.world_steps import move_until_done

SCENE = SceneConfig(meshes=False, shot="whole")
EXACT = {"drag": 0.0, "speed_noise": 0.0, "direction_noise": 0.0}


@pytest.fixture(scope="module")
def model() -> mujoco.MjModel:
    return build_scene(SCENE)


@pytest.fixture(scope="module")
def posture(model: mujoco.MjModel) -> dict[str, np.ndarray]:
    return archery_posture(model, BOW_HAND, BOW_HAND + START_THETA, tolerance=5e-3)


def _ready(model: mujoco.MjModel, posture: dict[str, np.ndarray]) -> ArcheryWorld:
    """A whole-shot world in the archery posture, the arrow in its holder."""
    world = ArcheryWorld(WorldConfig(scene=SCENE, **EXACT), model=model)  # type: ignore[arg-type]  # WorldConfig's float fields
    for part, values in posture.items():
        world.set_joint_targets(part, values)
    assert move_until_done(world)
    return world


def _move(world: ArcheryWorld, step: ShotStep) -> None:
    world.set_joint_targets(STRING_ARM, step.right_arm)
    if step.left_arm is not None:
        world.set_joint_targets(BOW_ARM, step.left_arm)
    assert move_until_done(world), f"the arms did not settle at {step.name}"


def _drive(world: ArcheryWorld, steps: list[ShotStep], until: str) -> None:
    """Move through the steps and do their actions, up to the action of step `until`."""
    for step in steps:
        _move(world, step)
        if step.name == until:
            return
        if step.action == "grasp":
            world.grasp()
        elif step.action == "nock":
            world.nock()


def _arrow_in_hand(world: ArcheryWorld) -> np.ndarray:
    """The arrow's tip in the right hand's frame (m)."""
    physics = world.physics
    physics.kinematics()
    hand = physics.model.body("r_hand").id
    rot = physics.data.xmat[hand].reshape(3, 3)
    local: np.ndarray = rot.T @ (physics.arrow_tip() - physics.data.xpos[hand])
    return local


def test_the_arrow_waits_in_its_holder_off_the_floor(
    model: mujoco.MjModel, posture: dict[str, np.ndarray]
) -> None:
    world = _ready(model, posture)
    tip = world.physics.arrow_tip()
    assert world.arrow_state is ArrowState.STOWED
    np.testing.assert_allclose(tip, HOLDER_NOCK - [SCENE.arrow_length, 0, 0], atol=1e-3)
    assert tip[2] > -SCENE.root_height + 0.3  # waist high, not on the floor
    world.step(1.0)
    np.testing.assert_allclose(world.physics.arrow_tip(), tip, atol=1e-3)  # the holder holds it


def test_a_good_grasp_holds_while_the_arm_moves(
    model: mujoco.MjModel, posture: dict[str, np.ndarray]
) -> None:
    world = _ready(model, posture)
    steps = plan_whole_shot(world, START_THETA)
    _drive(world, steps, until="reach")
    assert world.whole is not None
    distance = world.grasp()
    assert distance <= world.config.grasp_tolerance
    assert world.arrow_state is ArrowState.GRASPED
    held = _arrow_in_hand(world)
    before = world.physics.arrow_tip()
    for step in steps[2:4]:  # lift, carry
        _move(world, step)
        np.testing.assert_allclose(_arrow_in_hand(world), held, atol=2e-3)
    assert np.linalg.norm(world.physics.arrow_tip() - before) > APPROACH_HEIGHT


def test_a_grasp_off_by_more_than_the_tolerance_fails_and_the_arrow_stays(
    model: mujoco.MjModel, posture: dict[str, np.ndarray]
) -> None:
    world = _ready(model, posture)
    tolerance = world.config.grasp_tolerance
    steps = plan_whole_shot(world, START_THETA, grasp_offset=np.array([0, 0, 1.5 * tolerance]))
    tip = world.physics.arrow_tip()
    _drive(world, steps, until="reach")
    with pytest.raises(GraspMissed) as missed:
        world.grasp()
    assert missed.value.code == "grasp_missed"
    assert world.arrow_state is ArrowState.STOWED
    _move(world, steps[2])  # the hand lifts away: the arrow stays in its holder
    np.testing.assert_allclose(world.physics.arrow_tip(), tip, atol=1e-3)
    assert world.whole is not None and world.whole.grip_angle() < 0.05  # fingers stay open


def test_a_grasp_off_by_less_than_the_tolerance_holds(
    model: mujoco.MjModel, posture: dict[str, np.ndarray]
) -> None:
    world = _ready(model, posture)
    tolerance = world.config.grasp_tolerance
    steps = plan_whole_shot(world, START_THETA, grasp_offset=np.array([0, 0, 0.5 * tolerance]))
    _drive(world, steps, until="reach")
    assert 0.4 * tolerance < world.grasp() <= tolerance
    _move(world, steps[2])
    assert world.physics.arrow_tip()[2] > HOLDER_NOCK[2] + 0.5 * APPROACH_HEIGHT


@pytest.mark.parametrize(("scale", "nocks"), [(0.5, True), (1.5, False)])
def test_the_nock_takes_only_within_its_tolerance(
    model: mujoco.MjModel, posture: dict[str, np.ndarray], scale: float, nocks: bool
) -> None:
    world = _ready(model, posture)
    offset = np.array([0.0, 0.0, scale * world.config.nock_tolerance])
    steps = plan_whole_shot(world, START_THETA, nock_offset=offset)
    _drive(world, steps, until="carry")
    if nocks:
        assert world.nock() <= world.config.nock_tolerance
        assert world.arrow_state is ArrowState.NOCKED
        return
    with pytest.raises(NockMissed) as missed:
        world.nock()
    assert missed.value.code == "nock_missed"
    assert world.arrow_state is ArrowState.GRASPED  # still in the hand
    held = _arrow_in_hand(world)
    _move(world, steps[4])
    np.testing.assert_allclose(_arrow_in_hand(world), held, atol=2e-3)


def _shoot(world: ArcheryWorld, theta: np.ndarray) -> tuple[float, float]:
    """Draw to bow hand + θ and release: (the archer's draw, the arrow's length from the bow
    hand to the nock (m), launch speed (m/s))."""
    steps = plan_whole_shot(world, theta)
    _drive(world, steps, until="hold")
    assert world.whole is not None
    draw = float(np.linalg.norm(world.whole.arrow_line()))
    launch = world.launch()
    return draw, float(np.linalg.norm(launch.velocity))


def test_the_string_bends_with_the_draw(
    model: mujoco.MjModel, posture: dict[str, np.ndarray]
) -> None:
    world = _ready(model, posture)
    physics = world.physics
    tendon = model.tendon(BOWSTRING_TENDON).id
    site = model.site(STRING_NOCK_SITE).id
    mujoco.mj_forward(model, physics.data)
    braced = float(physics.data.ten_length[tendon])
    assert world.whole is not None
    np.testing.assert_allclose(physics.data.site_xpos[site], world.whole.rest_point(), atol=1e-9)
    _drive(world, plan_whole_shot(world, START_THETA), until="hold")
    mujoco.mj_forward(model, physics.data)
    draw = world.whole.draw_length()
    assert draw > 0.1
    np.testing.assert_allclose(
        np.linalg.norm(physics.data.site_xpos[site] - world.whole.rest_point()), draw, atol=1e-9
    )
    top, bottom = (physics.data.site_xpos[model.site(n).id] for n in ("bow_top", "bow_bottom"))
    nock = physics.data.site_xpos[site]
    bent = np.linalg.norm(top - nock) + np.linalg.norm(nock - bottom)  # through the nock
    assert physics.data.ten_length[tendon] == pytest.approx(bent, abs=1e-9)
    assert bent > braced + 0.05


def test_a_longer_draw_gives_a_faster_arrow(
    model: mujoco.MjModel, posture: dict[str, np.ndarray]
) -> None:
    shots = [_shoot(_ready(model, posture), scale * START_THETA) for scale in (0.8, 1.0)]
    (short_draw, short_speed), (long_draw, long_speed) = shots
    assert long_draw > short_draw + 0.02
    assert long_speed > short_speed
    bow = WorldConfig().bow
    for draw, speed in shots:  # the posture shot's bow, measured on the arrow
        assert speed == pytest.approx(bow.speed_for_draw(draw - bow.brace_height), rel=1e-9)


def test_release_opens_the_fingers_and_the_arrow_flies_and_lands(
    model: mujoco.MjModel, posture: dict[str, np.ndarray]
) -> None:
    world = _ready(model, posture)
    _drive(world, plan_whole_shot(world, START_THETA), until="hold")
    assert world.whole is not None
    landing = world.release()
    assert landing.flight_time > 0.05
    assert world.arrow_state is ArrowState.LANDED
    world.step(0.5)
    assert world.whole.grip_angle() < 0.05  # open
    world.physics.kinematics()
    np.testing.assert_allclose(
        world.physics.data.site_xpos[model.site(STRING_NOCK_SITE).id],
        world.whole.rest_point(),
        atol=1e-9,
    )
    # the next grasp reaches for the holder's next arrow (the hand is far from it here)
    with pytest.raises(GraspMissed):
        world.grasp()
    assert world.arrow_state is ArrowState.STOWED
    np.testing.assert_allclose(world.physics.arrow_pose()[0], world.physics.stowed_arrow_pose()[0])


def test_opening_the_hand_before_the_nock_drops_the_arrow(
    model: mujoco.MjModel, posture: dict[str, np.ndarray]
) -> None:
    world = _ready(model, posture)
    _drive(world, plan_whole_shot(world, START_THETA), until="lift")
    with pytest.raises(ArrowDropped) as dropped:
        world.launch()
    assert dropped.value.code == "arrow_dropped"
    assert world.arrow_state is ArrowState.DROPPED
    world.step(1.0)
    assert world.physics.arrow_tip()[2] == pytest.approx(-SCENE.root_height)


def test_a_posture_world_has_no_grasp() -> None:
    world = ArcheryWorld(WorldConfig(scene=SceneConfig(meshes=False)))
    with pytest.raises(StateError):
        world.grasp()
    with pytest.raises(StateError):
        plan_whole_shot(world, START_THETA)


def test_the_plan_is_the_controllers_ik_and_refuses_what_it_cannot_reach(
    model: mujoco.MjModel, posture: dict[str, np.ndarray]
) -> None:
    """The teacher's postures come from the controller's solver (Pinocchio): the aim puts the
    world's hand sites where it was asked, and a hand out of reach is refused in words, with
    the world untouched."""
    world = _ready(model, posture)
    aim = plan_aim(world, BOW_HAND, START_THETA)
    assert aim.left_arm is not None
    world.physics.set_joint_positions(STRING_ARM, aim.right_arm)
    world.physics.set_joint_positions(BOW_ARM, aim.left_arm)
    world.physics.kinematics()
    bow, string = world.hand_positions()
    np.testing.assert_allclose(bow, BOW_HAND, atol=1e-3)
    np.testing.assert_allclose(string - bow, START_THETA, atol=1e-3)
    before = world.physics.data.qpos.copy()
    with pytest.raises(BadRequest, match="aim is out of the arms' reach"):
        plan_aim(world, BOW_HAND, np.array([1.5, 0.0, 0.0]))
    np.testing.assert_array_equal(world.physics.data.qpos, before)
