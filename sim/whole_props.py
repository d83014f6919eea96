"""The props of the whole shot (`SceneConfig.shot == "whole"`): the arrow's holder within the
right arm's reach, the right hand's fingers and grasp site, the bowstring's nocking point and
the two welds that hold the arrow (in the holder; in the hand).

The holder is a stand whose cradle holds the arrow level, pointing forward (−x), its nock end
toward the robot at `HOLDER_NOCK` (m, root frame). The fingers are one hinge (`GRIP_JOINT`, 0
open, `GRIP_CLOSED` rad closed) driven by a position servo. The nocking point is a small free
body the world keeps at the string's rest point or on the drawing fingers; the bowstring runs
from one limb tip through it to the other, so the string bends as the hand draws.
"""

from __future__ import annotations

import mujoco
import numpy as np

from archery.sim.scene_config import (
    ARROW_BODY,
    ARROW_NOCK_SITE,
    GRASP_SITE,
    GRASP_WELD,
    GRIP_JOINT,
    HOLDER_BODY,
    HOLDER_WELD,
    STRING_HAND_SITE,
    STRING_NOCK_BODY,
    STRING_NOCK_SITE,
    SceneConfig,
)

__all__ = ["GRIP_CLOSED", "HOLDER_NOCK", "NOCK_GRIP", "add_whole_shot_props", "holder_arrow_pose"]

HOLDER_NOCK = np.array([-0.18, 0.30, -0.05])  # m, the held arrow's nock end (root frame)
NOCK_GRIP = 0.02  # m, from the nock along the shaft to where the fingers take it
GRIP_CLOSED = 1.2  # rad, the grip hinge's closed angle (0: open)
_GRIP_SERVO = (0.0625, 0.005)  # kp (N·m/rad), kv (N·m·s/rad): settles in about 0.15 s
_STRING_NOCK_MASS = 1e-3  # kg
# A stiff weld: time constant (s) and damping ratio, impedance; MuJoCo's defaults let the light
# arrow sag 8° about its tip, these 0.1°.
_WELD_SOLREF = [0.004, 1.0]
_WELD_SOLIMP = [0.99, 0.999, 0.001, 0.5, 2.0]


def holder_arrow_pose(config: SceneConfig) -> tuple[np.ndarray, np.ndarray]:
    """(tip (m), quaternion w, x, y, z) of the arrow in its holder: level, pointing along −x."""
    tip = HOLDER_NOCK - np.array([config.arrow_length, 0.0, 0.0])
    return tip, np.array([0.0, 0.0, 0.0, 1.0])  # the arrow's +x axis turned to −x about z


def _add_holder(spec: mujoco.MjSpec, config: SceneConfig) -> None:
    """A post from the floor with two cradles under the arrow's shaft."""
    tip, _ = holder_arrow_pose(config)
    common = {"contype": 0, "conaffinity": 0, "group": 2}
    rgba = [0.25, 0.22, 0.20, 1.0]
    holder = spec.worldbody.add_body(name=HOLDER_BODY, pos=HOLDER_NOCK)
    shaft_x = [0.35 * (tip[0] - HOLDER_NOCK[0]), 0.8 * (tip[0] - HOLDER_NOCK[0])]
    for i, x in enumerate(shaft_x):
        holder.add_geom(
            type=mujoco.mjtGeom.mjGEOM_BOX,
            pos=[x, 0.0, -0.012],
            size=[0.006, 0.012, 0.006],
            rgba=rgba,
            name=f"holder_cradle_{i}",
            **common,
        )
    middle = 0.5 * (shaft_x[0] + shaft_x[1])
    holder.add_geom(
        type=mujoco.mjtGeom.mjGEOM_CAPSULE,
        fromto=[middle, 0.0, -0.018, middle, 0.0, -config.root_height - HOLDER_NOCK[2]],
        size=[0.008, 0, 0],
        rgba=rgba,
        name="holder_post",
        **common,
    )
    for x in shaft_x:
        holder.add_geom(
            type=mujoco.mjtGeom.mjGEOM_CAPSULE,
            fromto=[x, 0.0, -0.018, middle, 0.0, -0.06],
            size=[0.005, 0, 0],
            rgba=rgba,
            **common,
        )


def _add_fingers(spec: mujoco.MjSpec, site: tuple[np.ndarray, np.ndarray]) -> None:
    """The grasp site at the string hand's frame and a finger that closes around it."""
    pos, quat = site
    hand = spec.body("r_hand")
    hand.add_site(name=GRASP_SITE, pos=pos, quat=quat, size=[0.004, 0, 0], group=4)
    fingers = hand.add_body(name="r_fingers", pos=pos, quat=quat)
    fingers.explicitinertial = True
    fingers.mass = 0.01
    fingers.inertia = [2e-6, 2e-6, 2e-6]
    joint = fingers.add_joint(name=GRIP_JOINT, axis=[1, 0, 0], range=[0.0, GRIP_CLOSED])
    joint.armature = 1e-4
    skin = [0.93, 0.78, 0.65, 1.0]
    common = {"contype": 0, "conaffinity": 0, "group": 2, "mass": 0, "rgba": skin}
    # Open, the finger stands off the grasp point; closed, it curls across it.
    fingers.add_geom(
        type=mujoco.mjtGeom.mjGEOM_CAPSULE,
        fromto=[0.0, 0.0, 0.02, 0.0, 0.025, 0.03],
        size=[0.006, 0, 0],
        **common,
    )
    fingers.add_geom(
        type=mujoco.mjtGeom.mjGEOM_CAPSULE,
        fromto=[0.0, 0.025, 0.03, 0.0, 0.03, 0.008],
        size=[0.005, 0, 0],
        **common,
    )
    servo = spec.add_actuator(name=GRIP_JOINT, target=GRIP_JOINT, group=1)
    servo.trntype = mujoco.mjtTrn.mjTRN_JOINT
    servo.set_to_position(kp=_GRIP_SERVO[0], kv=_GRIP_SERVO[1])
    servo.ctrllimited = True
    servo.ctrlrange = [0.0, GRIP_CLOSED]


def _add_nocking_point(spec: mujoco.MjSpec) -> None:
    """The string's nocking point: a free body the world places (rest point or drawn)."""
    nock = spec.worldbody.add_body(name=STRING_NOCK_BODY)
    nock.add_freejoint(name=STRING_NOCK_BODY)
    nock.explicitinertial = True
    nock.mass = _STRING_NOCK_MASS
    nock.inertia = [1e-8, 1e-8, 1e-8]
    nock.add_site(name=STRING_NOCK_SITE, size=[0.002, 0, 0], group=4)


def add_whole_shot_props(
    spec: mujoco.MjSpec, config: SceneConfig, hand_sites: dict[str, tuple[np.ndarray, np.ndarray]]
) -> None:
    """Add the holder, the fingers, the nocking point, the arrow's nock site and both welds
    (the holder's active from the start, the hand's off until a grasp)."""
    _add_holder(spec, config)
    _add_fingers(spec, hand_sites[STRING_HAND_SITE])
    _add_nocking_point(spec)
    spec.body(ARROW_BODY).add_site(
        name=ARROW_NOCK_SITE, pos=[-config.arrow_length, 0, 0], size=[0.003, 0, 0], group=4
    )
    weld = mujoco.mjtEq.mjEQ_WELD
    body = mujoco.mjtObj.mjOBJ_BODY
    # A weld's data: the anchor in body2 (the arrow's tip), body2's position in body1's frame,
    # body2's orientation relative to body1 (w, x, y, z), the torque scale.
    tip, quat = holder_arrow_pose(config)
    holder = spec.add_equality(
        name=HOLDER_WELD, type=weld, objtype=body, name1=HOLDER_BODY, name2=ARROW_BODY, active=True
    )
    holder.solref, holder.solimp = _WELD_SOLREF, _WELD_SOLIMP
    holder.data[:11] = [0.0, 0.0, 0.0, *(tip - HOLDER_NOCK), *quat, 1.0]
    grasp = spec.add_equality(
        name=GRASP_WELD, type=weld, objtype=body, name1="r_hand", name2=ARROW_BODY, active=False
    )
    # the relative pose is written at the grasp (`sim.whole_shot`)
    grasp.solref, grasp.solimp = _WELD_SOLREF, _WELD_SOLIMP
    grasp.data[:11] = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
