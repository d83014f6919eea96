"""Assembling and compiling the archery scene: the edited iCub (`sim.urdf`), its position
servos, the hand sites and the props (`sim.props`, and the whole shot's: `sim.whole_props`),
tuned so every joint settles alike.

Frame: the MuJoCo world frame *is* the iCub `root_link` frame of `sim.geometry` (x backward,
y right, z up; metres). The URDF's root link is welded to the world, and the floor is the plane
z = −root_height below it, so every position the physics reports is already in the frame the
controller, the learner and the reward use. The robot faces −x; the target face is the plane
x = −target_distance. Contact is disabled globally; the servos are tuned by `_tune_servos`.
"""

from __future__ import annotations

import mujoco
import numpy as np

from archery.protocol.parts import PARTS
from archery.protocol.robotspec import HOME_POSTURE
from archery.sim.errors import SceneError
from archery.sim.props import add_arrow, add_bow, add_environment, add_target
from archery.sim.scene_config import BOW_HAND_SITE, STRING_HAND_SITE, STRING_NOCK_SITE, SceneConfig
from archery.sim.urdf import add_hand_sites, robot_spec
from archery.sim.whole_props import add_whole_shot_props

__all__ = ["build_scene"]


def _add_servos(spec: mujoco.MjSpec) -> None:
    """One position servo per controlled joint (gains set by `_tune_servos` once compiled);
    the torso's in actuator group 0, the arms' in group 1."""
    for part, joints in PARTS.items():
        for name in joints:
            actuator = spec.add_actuator(name=name, target=name, group=int(part != "torso"))
            actuator.trntype = mujoco.mjtTrn.mjTRN_JOINT
            actuator.set_to_position(kp=1.0, kv=0.0)
            actuator.ctrllimited = True
            actuator.inheritrange = 1.0  # ctrlrange = the joint's range


def _tune_servos(model: mujoco.MjModel, config: SceneConfig) -> None:
    """Set kp = I·ω² and kv = 2ζ·I·ω − (joint damping), with I the joint's inertia at home
    (`protocol.robotspec.HOME_POSTURE`), so every joint settles alike: a second-order system of
    bandwidth ω (rad/s) and damping ratio ζ (1 by default: critically damped)."""
    data = mujoco.MjData(model)
    for name, value in HOME_POSTURE.items():
        data.qpos[model.joint(name).qposadr[0]] = value
    mujoco.mj_forward(model, data)
    mass = np.zeros((model.nv, model.nv))
    mujoco.mj_fullM(model, data, mass)
    omega, zeta = config.servo_bandwidth, config.servo_damping_ratio
    for joints in PARTS.values():
        for name in joints:
            dof = model.joint(name).dofadr[0]
            act = model.actuator(name).id
            inertia = mass[dof, dof]
            kp = inertia * omega**2
            kv = max(0.0, 2.0 * zeta * inertia * omega - model.dof_damping[dof])
            model.actuator_gainprm[act, 0] = kp
            model.actuator_biasprm[act, :3] = (0.0, -kp, -kv)


def build_scene(config: SceneConfig | None = None) -> mujoco.MjModel:
    """Build and compile the archery scene described by `config` (defaults if None).

    Raises:
        SceneError: the icub-models file or its meshes are missing or unexpected.
    """
    config = SceneConfig() if config is None else config
    spec = robot_spec(config)
    _add_servos(spec)
    spec.modelname = "icub_archery"
    option = spec.option
    option.timestep = config.timestep
    option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    option.disableflags |= mujoco.mjtDisableBit.mjDSBL_CONTACT
    option.density = 0.0  # air drag is applied explicitly to the arrow (sim.arrow)
    option.viscosity = 0.0
    sites = add_hand_sites(spec)
    whole = config.shot == "whole"
    add_bow(spec, sites[BOW_HAND_SITE], STRING_NOCK_SITE if whole else STRING_HAND_SITE)
    add_arrow(spec, config)
    if whole:
        add_whole_shot_props(spec, config, sites)
    add_target(spec, config)
    add_environment(spec, config)
    try:
        model = spec.compile()
    except ValueError as exc:
        raise SceneError(f"the archery scene does not compile: {exc}") from exc
    _tune_servos(model, config)
    return model
