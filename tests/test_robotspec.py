"""The shared robot spec holds in both robot models: the MuJoCo scene (sim) and Pinocchio
(controller), both built from the same icub-models URDF, agree on every name and put the hand
frames at the same pose (1 mm, 1 mrad) at the home posture and elsewhere."""

from __future__ import annotations

import pathlib

import icub_models
import numpy as np
import pinocchio as pin
import pytest

from archery.protocol import robotspec
from archery.protocol.parts import ARM_PARTS, PARTS
from archery.protocol.robotspec import SERVICES
from archery.services.controller.model import ArmsModel, load_arms_model
from archery.sim.model_build import build_scene
from archery.sim.scene import ScenePhysics
from archery.sim.scene_config import SceneConfig

POSITION_TOL = 1e-3  # m
ANGLE_TOL = 1e-3  # rad


@pytest.fixture(scope="module")
def scene() -> ScenePhysics:
    return ScenePhysics(build_scene(SceneConfig(meshes=False)))


@pytest.fixture(scope="module")
def arms() -> ArmsModel:
    return load_arms_model()


def _pose(scene: ScenePhysics, arms: ArmsModel, q: dict[str, float], arm: str) -> tuple:
    """(MuJoCo position, MuJoCo rotation, Pinocchio position, Pinocchio rotation) of `arm`'s
    hand frame at the joint angles `q` (rad)."""
    for part, joints in PARTS.items():
        scene.set_joint_positions(part, np.array([q[j] for j in joints]))
    scene.kinematics()
    frame = robotspec.HAND_FRAMES[arm]
    x_pin, r_pin = arms.hand_pose(q, arm)
    return scene.site_position(frame), scene.site_rotation(frame), x_pin, r_pin


def _assert_same_pose(scene: ScenePhysics, arms: ArmsModel, q: dict[str, float]) -> None:
    for arm in ARM_PARTS:
        x_mj, r_mj, x_pin, r_pin = _pose(scene, arms, q, arm)
        # The scene welds root_link to the world origin (the floor is moved, not the robot), so
        # no base offset separates the two frames.
        assert np.linalg.norm(x_mj - x_pin) < POSITION_TOL, (arm, x_mj, x_pin)
        angle = float(np.linalg.norm(pin.log3(r_mj.T @ r_pin)))
        assert angle < ANGLE_TOL, (arm, angle)


def test_hand_frames_agree_at_home(scene: ScenePhysics, arms: ArmsModel) -> None:
    _assert_same_pose(scene, arms, dict(robotspec.HOME_POSTURE))


def test_hand_frames_agree_away_from_home(scene: ScenePhysics, arms: ArmsModel) -> None:
    rng = np.random.default_rng(3)
    for _ in range(4):
        q = rng.uniform(arms.lower, arms.upper)
        _assert_same_pose(scene, arms, dict(zip(arms.joint_names, q.tolist(), strict=True)))


def test_hand_frames_differ_when_the_posture_differs(scene: ScenePhysics, arms: ArmsModel) -> None:
    # The comparison above can fail: move one MuJoCo elbow only and the hand frames part.
    home = dict(robotspec.HOME_POSTURE)
    x_mj, _, _, _ = _pose(scene, arms, home | {"l_elbow": home["l_elbow"] + 0.2}, "left_arm")
    x_pin, _ = arms.hand_pose(home, "left_arm")
    assert np.linalg.norm(x_mj - x_pin) > 10 * POSITION_TOL


def test_every_spec_name_exists_in_both_models(scene: ScenePhysics, arms: ArmsModel) -> None:
    model = scene.model
    # Same URDF: the controller loads the file of MODEL_NAME.
    assert pathlib.Path(arms.urdf_path) == pathlib.Path(
        icub_models.get_model_file(robotspec.MODEL_NAME)
    )
    assert robotspec.MODEL_NAME in arms.urdf_path
    for frame in robotspec.HAND_FRAMES.values():
        assert model.site(frame).name == frame
        assert arms.model.existFrame(frame)
    assert set(robotspec.HAND_FRAMES) == set(ARM_PARTS)
    for name in robotspec.HOME_POSTURE:
        assert model.joint(name).name == name
        assert arms.model.existJointName(name)
    assert set(robotspec.HOME_POSTURE) == {j for joints in PARTS.values() for j in joints}
    assert {robotspec.BOW_ARM, robotspec.STRING_ARM} == set(ARM_PARTS)
    # The bow (fused into its hand's body) hangs from the body carrying the bow hand's frame.
    assert model.site("bow_top").bodyid[0] == model.site(robotspec.BOW_HAND_FRAME).bodyid[0]
    assert SERVICES == robotspec.SERVICES
    assert len(set(robotspec.SERVICES)) == 5


def test_home_is_inside_the_limits_of_both_models(scene: ScenePhysics, arms: ArmsModel) -> None:
    q = arms.vector(robotspec.HOME_POSTURE)
    assert np.all(q > arms.lower) and np.all(q < arms.upper)
    for part in PARTS:
        lower, upper = scene.joint_limits(part)
        margin = scene.joint_margins(part)
        home = np.array(robotspec.home_of(part))
        assert np.all(home >= lower + margin) and np.all(home <= upper - margin), part


def test_home_of_names_the_parts() -> None:
    assert robotspec.home_of("left_arm") == robotspec.home_of("right_arm")
    with pytest.raises(KeyError, match=r"unknown part 'head'.*torso, left_arm, right_arm"):
        robotspec.home_of("head")
