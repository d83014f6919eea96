"""Everything in the archery scene that is not the robot: bow, arrow, target, floor, lights,
cameras. Each `add_*` adds its part to an `MjSpec` (positions in metres, root frame).

The bow hangs from the left hand at the bow-hand site's pose with a bowstring tendon through the
string-hand site (in the whole shot, through the nocking point of `sim.whole_props`); the arrow
is a free body whose origin is its tip (marked in bright green); the target is a ringed face in
the plane x = −target_distance on a stand. None of them collides:
contact is disabled, and the arrow's impact is found geometrically by `sim.arrow`.
"""

from __future__ import annotations

import math
from itertools import pairwise

import mujoco
import numpy as np

from archery.sim.errors import SceneError
from archery.sim.geometry import TARGET_DIAMETER, target_centre
from archery.sim.scene_config import (
    ARROW_BODY,
    ARROW_JOINT,
    ARROW_TIP_RGBA,
    ARROW_TIP_SITE,
    BOWSTRING_TENDON,
    RING_COLOURS,
    SIDE_CAMERA,
    TARGET_CAMERA,
    TARGET_CENTRE_SITE,
    SceneConfig,
)
from archery.sim.whole_props import holder_arrow_pose

__all__ = ["add_arrow", "add_bow", "add_environment", "add_target", "look_at_quat"]


def look_at_quat(eye: np.ndarray, target: np.ndarray, up: np.ndarray | None = None) -> np.ndarray:
    """Quaternion (w, x, y, z) of a MuJoCo camera at `eye` looking at `target` (m), `up` ≈ +z.

    A MuJoCo camera looks along its −z axis with +y up in the image.
    """
    up = np.array([0.0, 0.0, 1.0]) if up is None else np.asarray(up, dtype=float)
    forward = np.asarray(target, dtype=float) - np.asarray(eye, dtype=float)
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    cam_up = np.cross(right, forward)
    mat = np.column_stack([right, cam_up, -forward])
    quat = np.empty(4)
    mujoco.mju_mat2Quat(quat, mat.ravel())
    return quat


def add_bow(
    spec: mujoco.MjSpec, hand_site: tuple[np.ndarray, np.ndarray], string_site: str
) -> None:
    """A bow held in the left hand, its string through the site `string_site` between the limb
    tips. In the hand frame: −y up along the grip (thumb side), −z toward the target (out of the
    palm), +z toward the string hand."""
    pos, quat = hand_site
    bow = spec.body("l_hand").add_body(name="bow", pos=pos, quat=quat, gravcomp=1.0)
    bow.explicitinertial = True
    bow.mass = 0.15
    bow.inertia = [3e-3, 3e-3, 1e-4]
    wood = [0.45, 0.27, 0.12, 1.0]
    capsule = mujoco.mjtGeom.mjGEOM_CAPSULE

    def seg(a: tuple[float, float, float], b: tuple[float, float, float], radius: float) -> None:
        bow.add_geom(
            type=capsule,
            fromto=[*a, *b],
            size=[radius, 0, 0],
            rgba=wood,
            contype=0,
            conaffinity=0,
            group=2,
            mass=0,
        )

    # The hand mesh is an open hand: fingers along +x, thumb along −y, palm surface at z ≈ −0.012.
    gx, gz = 0.02, -0.028  # grip axis: across the palm, just in front of it (m)
    seg((gx, -0.06, gz), (gx, 0.06, gz), 0.012)
    # Each limb: three segments curving back toward the string side (+z).
    for sign in (-1.0, 1.0):
        points = [
            (gx, sign * 0.06, gz),
            (gx, sign * 0.16, gz + 0.012),
            (gx, sign * 0.25, gz + 0.035),
            (gx, sign * 0.32, gz + 0.07),
        ]
        for (a, b), radius in zip(pairwise(points), (0.009, 0.007, 0.005), strict=True):
            seg(a, b, radius)
    bow.add_site(name="bow_top", pos=[gx, -0.32, gz + 0.07], size=[0.004, 0, 0], group=4)
    bow.add_site(name="bow_bottom", pos=[gx, 0.32, gz + 0.07], size=[0.004, 0, 0], group=4)
    string = spec.add_tendon(name=BOWSTRING_TENDON, width=0.0015, rgba=[0.95, 0.95, 0.9, 1.0])
    string.wrap_site("bow_top")
    string.wrap_site(string_site)
    string.wrap_site("bow_bottom")


def add_arrow(spec: mujoco.MjSpec, config: SceneConfig) -> None:
    """The arrow: a free body whose origin is its tip and whose +x axis points forward."""
    length, mass = config.arrow_length, config.arrow_mass
    if config.shot == "whole":
        stowed, quat = holder_arrow_pose(config)  # in its holder, within the right arm's reach
    else:
        stowed = np.array([0.12, 0.30, -config.root_height + 0.002])  # upright by the right foot
        quat = np.array([math.sqrt(0.5), 0, math.sqrt(0.5), 0])
    arrow = spec.worldbody.add_body(name=ARROW_BODY, pos=stowed, quat=quat)
    arrow.add_freejoint(name=ARROW_JOINT)
    arrow.explicitinertial = True
    arrow.mass = mass
    arrow.ipos = [-0.5 * length, 0.0, 0.0]
    arrow.inertia = [0.5 * mass * 0.004**2, mass * length**2 / 12, mass * length**2 / 12]
    cyl = mujoco.mjtGeom.mjGEOM_CYLINDER
    common = {"contype": 0, "conaffinity": 0, "group": 2, "mass": 0}
    # Suction cup: a flat disc whose front face is the tip.
    arrow.add_geom(
        type=cyl, fromto=[0, 0, 0, -0.012, 0, 0], size=[0.015, 0, 0], rgba=ARROW_TIP_RGBA, **common
    )
    arrow.add_geom(
        type=cyl,
        fromto=[-0.012, 0, 0, -length, 0, 0],
        size=[0.0035, 0, 0],
        rgba=[0.35, 0.35, 0.38, 1.0],
        **common,
    )
    for angle in (0.0, 2 * math.pi / 3, 4 * math.pi / 3):
        arrow.add_geom(
            type=mujoco.mjtGeom.mjGEOM_BOX,
            pos=[-length + 0.045, 0.012 * math.cos(angle), 0.012 * math.sin(angle)],
            quat=[math.cos(angle / 2), math.sin(angle / 2), 0, 0],
            size=[0.035, 0.0005, 0.011],
            rgba=[0.55, 0.55, 0.55, 1.0],
            **common,
        )
    arrow.add_site(name=ARROW_TIP_SITE, size=[0.003, 0, 0], group=4)


def add_target(spec: mujoco.MjSpec, config: SceneConfig) -> None:
    """The target face in the plane x = −distance, facing the robot, on a stand."""
    centre = target_centre(config.target_distance)
    # Local frame: +z toward the robot (world +x), y = world y, x = world −z.
    target = spec.worldbody.add_body(
        name="target", pos=centre, quat=[math.sqrt(0.5), 0, math.sqrt(0.5), 0]
    )
    cyl = mujoco.mjtGeom.mjGEOM_CYLINDER
    common = {"contype": 0, "conaffinity": 0, "group": 2}
    if abs(RING_COLOURS[-1][0] - TARGET_DIAMETER / 2) > 1e-12:
        raise SceneError("the outer ring must have the target's radius")
    step = 0.0004  # m, each outer ring sits this much behind the one inside it
    for i, (radius, rgba) in enumerate(RING_COLOURS):
        front = -i * step
        target.add_geom(
            type=cyl,
            fromto=[0, 0, front - 0.004, 0, 0, front],
            size=[radius, 0, 0],
            rgba=rgba,
            name=f"target_ring_{i}",
            **common,
        )
    boss = -len(RING_COLOURS) * step - 0.004
    target.add_geom(
        type=cyl,
        fromto=[0, 0, boss - 0.06, 0, 0, boss],
        size=[TARGET_DIAMETER / 2, 0, 0],
        rgba=[0.42, 0.40, 0.36, 1.0],
        name="target_boss",
        **common,
    )
    target.add_site(name=TARGET_CENTRE_SITE, size=[0.004, 0, 0], group=4)
    # Stand: two legs from behind the face's rim down to the floor, and a back strut (world frame).
    floor_z = -config.root_height
    x0 = centre[0] - 0.07
    stand_rgba = [0.30, 0.30, 0.30, 1.0]
    for side in (-1.0, 1.0):
        y = centre[1] + side * 0.18
        spec.worldbody.add_geom(
            type=mujoco.mjtGeom.mjGEOM_CAPSULE,
            fromto=[x0, y, centre[2] + 0.1, x0 + 0.05, y, floor_z],
            size=[0.015, 0, 0],
            rgba=stand_rgba,
            name=f"stand_leg_{int(side > 0)}",
            **common,
        )
    spec.worldbody.add_geom(
        type=mujoco.mjtGeom.mjGEOM_CAPSULE,
        fromto=[x0, centre[1], centre[2], x0 - 0.35, centre[1], floor_z],
        size=[0.015, 0, 0],
        rgba=stand_rgba,
        name="stand_strut",
        **common,
    )


def add_environment(spec: mujoco.MjSpec, config: SceneConfig) -> None:
    """Floor, sky, lights, offscreen buffer size and the two fixed cameras."""
    floor_z = -config.root_height
    spec.add_texture(
        name="grid",
        type=mujoco.mjtTexture.mjTEXTURE_2D,
        builtin=mujoco.mjtBuiltin.mjBUILTIN_CHECKER,
        width=512,
        height=512,
        rgb1=[0.55, 0.55, 0.55],
        rgb2=[0.50, 0.50, 0.50],
    )
    floor_mat = spec.add_material(name="floor", texrepeat=[8, 8], reflectance=0.0)
    floor_mat.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = "grid"
    spec.add_texture(
        name="sky",
        type=mujoco.mjtTexture.mjTEXTURE_SKYBOX,
        builtin=mujoco.mjtBuiltin.mjBUILTIN_GRADIENT,
        width=256,
        height=256,
        rgb1=[0.80, 0.85, 0.90],
        rgb2=[0.35, 0.40, 0.45],
    )
    spec.worldbody.add_geom(
        name="floor",
        type=mujoco.mjtGeom.mjGEOM_PLANE,
        pos=[-1.5, 0, floor_z],
        size=[5, 5, 0.1],
        material="floor",
        contype=0,
        conaffinity=0,
        group=0,
    )
    light = spec.worldbody.add_light(
        name="sun",
        type=mujoco.mjtLightType.mjLIGHT_DIRECTIONAL,
        pos=[1.0, 1.0, 3.0],
        dir=[-0.6, -0.3, -1.0],
        castshadow=True,
    )
    light.diffuse = [0.6, 0.6, 0.6]
    light.specular = [0.1, 0.1, 0.1]
    # A soft fill light facing the target face so the rings keep their colours in the camera.
    fill = spec.worldbody.add_light(
        name="fill",
        type=mujoco.mjtLightType.mjLIGHT_DIRECTIONAL,
        pos=[0.5, 0.0, 1.5],
        dir=[-1.0, 0.0, -0.3],
        castshadow=False,
    )
    fill.diffuse = [0.35, 0.35, 0.35]
    fill.specular = [0.0, 0.0, 0.0]
    headlight = spec.visual.headlight
    headlight.ambient = [0.35, 0.35, 0.35]
    headlight.diffuse = [0.25, 0.25, 0.25]
    headlight.specular = [0.05, 0.05, 0.05]
    spec.visual.global_.offwidth = 1920
    spec.visual.global_.offheight = 1080
    spec.visual.quality.shadowsize = 2048  # software GL renders 1280×720 in ~0.1 s with this
    centre = target_centre(config.target_distance)
    eye = np.asarray(config.camera_pos)
    spec.worldbody.add_camera(
        name=TARGET_CAMERA, pos=eye, quat=look_at_quat(eye, centre), fovy=config.camera_fovy
    )
    side_eye = np.array([-1.15, 3.2, 0.35])
    side_look = np.array([-1.15, 0.0, -0.05])
    spec.worldbody.add_camera(
        name=SIDE_CAMERA, pos=side_eye, quat=look_at_quat(side_eye, side_look), fovy=45.0
    )
