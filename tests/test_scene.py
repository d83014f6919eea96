"""Tests of the MuJoCo archery scene: structure, frames, Pinocchio agreement, stability, camera."""

from __future__ import annotations

import dataclasses
import math

import icub_models
import msgspec
import mujoco
import numpy as np
import pinocchio as pin
import pytest

from archery.protocol.errors import ConfigError
from archery.protocol.parts import PARTS
from archery.protocol.robotspec import MODEL_NAME, home_of
from archery.protocol.verbs.robot import Scene
from archery.sim.errors import CommandError, SceneError
from archery.sim.geometry import (
    BOW_HAND,
    START_THETA,
    TARGET_DIAMETER,
    TARGET_DISTANCE,
    target_centre,
)
from archery.sim.model_build import build_scene
from archery.sim.scene import ScenePhysics
from archery.sim.scene_config import (
    ARROW_JOINT,
    ARROW_TIP_SITE,
    BOW_HAND_SITE,
    BOWSTRING_TENDON,
    RING_COLOURS,
    SIDE_CAMERA,
    STRING_HAND_SITE,
    TARGET_CAMERA,
    TARGET_CENTRE_SITE,
    SceneConfig,
)
from archery.sim.urdf import urdf_frame_placement
from tests.postures import archery_posture

CHEAP = SceneConfig(meshes=False)

# `protocol.robotspec.HOME_POSTURE` per part (rad, YARP order)
HOME_BY_PART = {part: home_of(part) for part in PARTS}


@pytest.fixture(scope="module")
def cheap_model() -> mujoco.MjModel:
    return build_scene(CHEAP)


@pytest.fixture(scope="module")
def full_model() -> mujoco.MjModel:
    return build_scene(SceneConfig())


@pytest.fixture(scope="module")
def pinocchio_model() -> tuple[pin.Model, pin.Data]:
    model = pin.buildModelFromUrdf(icub_models.get_model_file(MODEL_NAME))
    return model, model.createData()


def _random_posture(physics: ScenePhysics, rng: np.random.Generator) -> dict[str, np.ndarray]:
    posture = {}
    for part in PARTS:
        low, high = physics.joint_limits(part)
        posture[part] = rng.uniform(low, high)
        physics.set_joint_positions(part, posture[part])
    return posture


def test_scene_has_the_named_parts(full_model: mujoco.MjModel) -> None:
    m = full_model
    for site in (BOW_HAND_SITE, STRING_HAND_SITE, ARROW_TIP_SITE, TARGET_CENTRE_SITE):
        assert m.site(site).id >= 0
    for camera in (TARGET_CAMERA, SIDE_CAMERA):
        assert m.camera(camera).id >= 0
    assert m.tendon(BOWSTRING_TENDON).id >= 0
    assert m.jnt_type[m.joint(ARROW_JOINT).id] == mujoco.mjtJoint.mjJNT_FREE
    assert m.nmesh > 0  # the robot's meshes were found and loaded
    # Exactly the 17 controlled joints plus the arrow's free joint; one servo per joint, YARP order.
    names = [name for joints in PARTS.values() for name in joints]
    assert m.njnt == len(names) + 1
    assert [m.actuator(i).name for i in range(m.nu)] == names
    for name in names:
        act = m.actuator(name)
        joint = m.joint(name)
        assert m.actuator_trnid[act.id, 0] == joint.id
        np.testing.assert_allclose(m.actuator_ctrlrange[act.id], m.jnt_range[joint.id])
        assert m.actuator_gainprm[act.id, 0] > 0 and m.actuator_biasprm[act.id, 2] <= 0


def test_contacts_are_off_and_robot_geoms_never_collide(full_model: mujoco.MjModel) -> None:
    m = full_model
    assert m.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_CONTACT
    assert not np.any(m.geom_contype) and not np.any(m.geom_conaffinity)
    assert m.opt.density == 0.0 and m.opt.viscosity == 0.0  # drag is explicit (sim.arrow)


def test_world_frame_is_the_root_frame(cheap_model: mujoco.MjModel) -> None:
    physics = ScenePhysics(cheap_model)
    physics.forward()
    np.testing.assert_allclose(
        physics.site_position(TARGET_CENTRE_SITE), target_centre(TARGET_DISTANCE), atol=1e-12
    )
    floor = cheap_model.geom("floor")
    assert cheap_model.geom_pos[floor.id][2] == pytest.approx(-CHEAP.root_height)
    ring_radii = [
        cheap_model.geom_size[cheap_model.geom(f"target_ring_{i}").id][0] for i in range(5)
    ]
    assert ring_radii == pytest.approx([radius for radius, _ in RING_COLOURS])
    assert ring_radii[-1] == pytest.approx(TARGET_DIAMETER / 2)
    assert ring_radii[0] == pytest.approx(0.05)


def test_arrow_tip_colour_is_not_a_target_colour(cheap_model: mujoco.MjModel) -> None:
    arrow = cheap_model.body("arrow").id
    tip_geom = next(g for g in range(cheap_model.ngeom) if cheap_model.geom_bodyid[g] == arrow)
    tip = cheap_model.geom_rgba[tip_geom, :3]
    assert tip[1] > 0.8 and tip[0] < 0.3 and tip[2] < 0.3  # bright green
    for _, rgba in RING_COLOURS:
        assert np.linalg.norm(np.asarray(rgba[:3]) - tip) > 0.8


def test_hand_sites_match_pinocchio_forward_kinematics(
    cheap_model: mujoco.MjModel, pinocchio_model: tuple[pin.Model, pin.Data]
) -> None:
    pmodel, pdata = pinocchio_model
    physics = ScenePhysics(cheap_model)
    rng = np.random.default_rng(7)
    for _ in range(25):
        posture = _random_posture(physics, rng)
        physics.kinematics()
        q = pin.neutral(pmodel)
        for part, values in posture.items():
            for name, value in zip(PARTS[part], values, strict=True):
                q[pmodel.joints[pmodel.getJointId(name)].idx_q] = value
        pin.framesForwardKinematics(pmodel, pdata, q)
        for site in (BOW_HAND_SITE, STRING_HAND_SITE):
            frame = pdata.oMf[pmodel.getFrameId(site)]
            np.testing.assert_allclose(physics.site_position(site), frame.translation, atol=1e-6)
            np.testing.assert_allclose(physics.site_rotation(site), frame.rotation, atol=1e-6)


def test_urdf_frame_placement_composes_fixed_joints() -> None:
    body, pos, quat = urdf_frame_placement("l_hand_dh_frame")
    assert body == "l_hand"
    np.testing.assert_allclose(pos, [0.05765429784284365, -0.0055568, 0.013693832308330513])
    assert np.linalg.norm(quat) == pytest.approx(1.0)
    with pytest.raises(SceneError, match="not a link"):
        urdf_frame_placement("no_such_frame")


def test_scene_steps_stably_for_minutes(cheap_model: mujoco.MjModel) -> None:
    physics = ScenePhysics(cheap_model)
    physics.reset()
    rng = np.random.default_rng(3)
    steps_per_target = round(2.0 / physics.timestep)
    for _ in range(60):  # 120 s of simulated time, a new random setpoint every 2 s
        for part in PARTS:
            low, high = physics.joint_limits(part)
            physics.data.ctrl[physics.actuator_indices(part)] = rng.uniform(low, high)
        for _ in range(steps_per_target):
            physics.step()
        assert not physics.data.warning[mujoco.mjtWarning.mjWARN_BADQACC].number  # no NaN/Inf
    assert physics.time == pytest.approx(120.0)
    assert np.all(np.isfinite(physics.data.qpos)) and np.all(np.isfinite(physics.data.qvel))
    for part in PARTS:
        assert np.max(np.abs(physics.joint_velocities(part))) < 5.0


def test_servos_hold_a_posture_against_gravity(cheap_model: mujoco.MjModel) -> None:
    physics = ScenePhysics(cheap_model)
    physics.reset()
    for part, values in HOME_BY_PART.items():
        physics.set_joint_positions(part, np.asarray(values))
        physics.data.ctrl[physics.actuator_indices(part)] = values
    for _ in range(round(1.0 / physics.timestep)):
        physics.step()
    for part, values in HOME_BY_PART.items():
        np.testing.assert_allclose(physics.joint_positions(part), values, atol=1e-6)


def test_same_config_builds_the_same_scene(cheap_model: mujoco.MjModel) -> None:
    again = build_scene(SceneConfig(**CHEAP.to_dict()))
    assert again.nq == cheap_model.nq and again.nbody == cheap_model.nbody
    np.testing.assert_array_equal(again.qpos0, cheap_model.qpos0)
    np.testing.assert_array_equal(again.actuator_gainprm, cheap_model.actuator_gainprm)
    np.testing.assert_array_equal(again.actuator_biasprm, cheap_model.actuator_biasprm)
    a, b = ScenePhysics(cheap_model), ScenePhysics(again)
    rng = np.random.default_rng(11)
    posture = _random_posture(a, rng)
    for part, values in posture.items():
        b.set_joint_positions(part, values)
    a.kinematics()
    b.kinematics()
    np.testing.assert_array_equal(a.data.site_xpos, b.data.site_xpos)


def _pixel(model: mujoco.MjModel, data: mujoco.MjData, point: np.ndarray) -> np.ndarray:
    cam = model.camera(TARGET_CAMERA).id
    rot = data.cam_xmat[cam].reshape(3, 3)
    local = rot.T @ (point - data.cam_xpos[cam])
    assert local[2] < 0  # in front of the camera (which looks along its −z)
    focal = 360.0 / math.tan(math.radians(model.cam_fovy[cam]) / 2)
    return np.array([640.0 + focal * local[0] / -local[2], 360.0 - focal * local[1] / -local[2]])


@pytest.mark.parametrize("posture", ["home", "archery"])
def test_target_camera_frames_the_whole_target_unoccluded(
    full_model: mujoco.MjModel, posture: str
) -> None:
    physics = ScenePhysics(full_model)
    if posture == "home":
        joints = {part: np.asarray(values) for part, values in HOME_BY_PART.items()}
    else:
        joints = archery_posture(full_model, BOW_HAND, BOW_HAND + START_THETA, tolerance=5e-3)
    for part, values in joints.items():
        physics.set_joint_positions(part, values)
    physics.forward()
    centre = target_centre(TARGET_DISTANCE)
    angles = np.linspace(0, 2 * np.pi, 24, endpoint=False)
    rim = [centre + 0.25 * np.array([0.0, math.cos(a), math.sin(a)]) for a in angles]
    pixels = np.array([_pixel(full_model, physics.data, p) for p in rim])
    margin = 0.1 * 720
    assert np.all(pixels[:, 0] > margin) and np.all(pixels[:, 0] < 1280 - margin)
    assert np.all(pixels[:, 1] > margin) and np.all(pixels[:, 1] < 720 - margin)
    assert np.ptp(pixels[:, 1]) > 250  # the face spans a good part of the 720-pixel height
    cam = full_model.camera(TARGET_CAMERA).id
    eye = physics.data.cam_xpos[cam].copy()
    ring_ids = {full_model.geom(f"target_ring_{i}").id for i in range(len(RING_COLOURS))}
    geomid = np.zeros(1, dtype=np.int32)
    for point in [centre, *(centre + 0.24 / 0.25 * (p - centre) for p in rim)]:
        direction = point - eye
        mujoco.mj_ray(full_model, physics.data, eye, direction, None, 1, -1, geomid)
        assert int(geomid[0]) in ring_ids, f"the view of {point} is blocked by geom {geomid[0]}"


def test_physics_queries_reject_unknown_names(cheap_model: mujoco.MjModel) -> None:
    physics = ScenePhysics(cheap_model)
    with pytest.raises(CommandError, match=r"unknown part 'head'.*torso, left_arm, right_arm"):
        physics.joint_positions("head")
    with pytest.raises(CommandError, match="unknown site 'nose'"):
        physics.site_position("nose")


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("root_height", -1.0),
        ("timestep", 0.5),
        ("arrow_length", float("nan")),
        ("camera_pos", (1, 2)),
    ],
)
def test_scene_config_rejects_bad_values(field: str, value: object) -> None:
    with pytest.raises(ConfigError, match=field):
        SceneConfig(**{field: value})


def test_the_status_scene_is_the_scene_config_typed() -> None:
    """The robot's status carries the scene as `protocol.verbs.robot.Scene`: the same
    parameters as `SceneConfig`, and back to an equal config."""
    assert Scene.__struct_fields__ == tuple(f.name for f in dataclasses.fields(SceneConfig))
    config = SceneConfig(meshes=False, shot="whole", target_distance=7.5)
    wire = msgspec.msgpack.decode(msgspec.msgpack.encode(config.to_status()), type=Scene)
    assert wire.shot == "whole" and SceneConfig.of(wire) == config
