"""The whole shot's physics on a scene built with `shot="whole"`: the grasp, the nock, the
draw and the release, each gated by the geometry it needs (m, root frame).

The grasp holds only when the hand's grasp site is within `grasp_tolerance` of the arrow's
shaft (a weld then holds the arrow where the hand took it; the holder's lets go). The nock
takes only when the arrow's nock is within `nock_tolerance` of the string's rest nocking point;
the nock then stays between the fingers and the arrow lies from there across the bow hand. The
string bends by how far the nocking point is from its rest; the release opens the fingers and
the arrow leaves along the nock-to-bow-hand line at the bow's `launch_speed` of that line (the
archer's draw, pivot to nock): the posture shot's bow model measured on the arrow.
"""

from __future__ import annotations

import mujoco
import numpy as np

from archery.protocol.direction import arrow_direction
from archery.sim.arrow import arrow_quat
from archery.sim.errors import ArrowDropped, GraspMissed, NockMissed, SceneError, StateError
from archery.sim.scene import ScenePhysics
from archery.sim.scene_config import (
    ARROW_BODY,
    ARROW_NOCK_SITE,
    BOW_HAND_SITE,
    GRASP_SITE,
    GRASP_WELD,
    GRIP_JOINT,
    HOLDER_WELD,
    STRING_HAND_SITE,
    STRING_NOCK_BODY,
)
from archery.sim.whole_props import GRIP_CLOSED

__all__ = ["NOCK_IN_STRING_HAND", "WholeShot"]

#: m, in the string hand's frame (`r_hand_dh_frame`): where the nock of an arrow grasped from
#: the holder as demonstrated sits once nocked (a test measures it across θ's box within 3 mm);
#: the robot tells it in its status, for a controller to aim the arrow rather than the hand
NOCK_IN_STRING_HAND = (-0.0136, 0.0111, -0.0061)


def _segment_distance(point: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    """Distance (m) from `point` to the segment a–b."""
    ab = b - a
    s = float(np.clip(np.dot(point - a, ab) / max(float(np.dot(ab, ab)), 1e-12), 0.0, 1.0))
    return float(np.linalg.norm(point - (a + s * ab)))


class WholeShot:
    """The grasp, nock, draw and release on a whole-shot scene; the world calls it.

    Args:
        physics: the scene (built with `SceneConfig(shot="whole")`).
        grasp_tolerance: largest grasp-site-to-shaft distance a grasp takes (m).
        nock_tolerance: largest nock-to-string distance a nock takes (m).

    Raises:
        SceneError: the scene has no whole-shot props.
    """

    def __init__(self, physics: ScenePhysics, grasp_tolerance: float, nock_tolerance: float):
        model = physics.model
        self.physics = physics
        self.grasp_tolerance = grasp_tolerance
        self.nock_tolerance = nock_tolerance
        try:
            self._grasp_eq = model.equality(GRASP_WELD).id
            self._holder_eq = model.equality(HOLDER_WELD).id
            self._grip = model.actuator(GRIP_JOINT).id
            self._grip_q = int(model.joint(GRIP_JOINT).qposadr[0])
            self._hand = int(model.eq_obj1id[self._grasp_eq])
            self._arrow = model.body(ARROW_BODY).id
            self._grasp_site = model.site(GRASP_SITE).id
            self._nock_site = model.site(ARROW_NOCK_SITE).id
            self._bow_site = model.site(BOW_HAND_SITE).id
            self._string_site = model.site(STRING_HAND_SITE).id
            string = model.joint(STRING_NOCK_BODY)
            self._string_body = model.body(STRING_NOCK_BODY).id
            self._limbs = [model.site("bow_top").id, model.site("bow_bottom").id]
        except KeyError as exc:
            raise SceneError(f"not a whole-shot scene (build it with shot='whole'): {exc}") from exc
        self._string_q = int(string.qposadr[0])
        self._string_v = int(string.dofadr[0])
        self._arrow_length = float(np.linalg.norm(model.site_pos[self._nock_site]))
        self._pinch: np.ndarray | None = None  # the nock in the hand's frame, once nocked
        # N: the forces that hold the string's nocking point and a nocked arrow up (the model's
        # gravity is fixed once built), kept for `pin`, which runs at every physics step
        self._string_weight = -model.body_mass[self._string_body] * physics.gravity
        self._arrow_weight = -physics.arrow_mass * physics.gravity
        self.grasped = False

    # -- where things are -------------------------------------------------------------------
    def rest_point(self) -> np.ndarray:
        """The string's nocking point at rest (m): midway between the limb tips."""
        xpos = self.physics.data.site_xpos
        point: np.ndarray = 0.5 * (xpos[self._limbs[0]] + xpos[self._limbs[1]])
        return point

    def nocking_point(self) -> np.ndarray:
        """Where the string's nocking point is now (m): between the fingers once nocked, else
        at rest."""
        if self._pinch is None:
            return self.rest_point()
        data = self.physics.data
        point: np.ndarray = (
            data.xpos[self._hand] + data.xmat[self._hand].reshape(3, 3) @ self._pinch
        )
        return point

    def draw_length(self) -> float:
        """How far the string's nocking point is from its rest (m); 0 when not nocked."""
        if self._pinch is None:
            return 0.0
        return float(np.linalg.norm(self.nocking_point() - self.rest_point()))

    def grasp_distance(self) -> float:
        """The grasp site's distance from the arrow's shaft, tip to nock (m)."""
        data = self.physics.data
        return _segment_distance(
            data.site_xpos[self._grasp_site],
            data.xpos[self._arrow],
            data.site_xpos[self._nock_site],
        )

    def nock_distance(self) -> float:
        """The arrow's nock's distance from the string's rest nocking point (m)."""
        return float(
            np.linalg.norm(self.physics.data.site_xpos[self._nock_site] - self.rest_point())
        )

    @property
    def nocked(self) -> bool:
        """True from a nock to the release."""
        return self._pinch is not None

    # -- the movement -------------------------------------------------------------------------
    def reset(self) -> None:
        """Fingers open, nothing held, the string at rest (after the data's reset)."""
        self._pinch = None
        self.grasped = False
        self.physics.data.ctrl[self._grip] = 0.0
        self.physics.kinematics()
        self.pin()

    def grasp(self) -> float:
        """Close the fingers on the arrow; returns the grasp site's distance from the shaft (m).

        Raises:
            StateError: an arrow is held already.
            GraspMissed: the shaft is farther than `grasp_tolerance`; nothing moves.
        """
        if self.grasped:
            raise StateError("the hand holds the arrow already")
        physics = self.physics
        physics.kinematics()
        distance = self.grasp_distance()
        if distance > self.grasp_tolerance:
            raise GraspMissed(
                f"the hand is {distance * 1000:.1f} mm from the arrow's shaft, more than the "
                f"grasp tolerance of {self.grasp_tolerance * 1000:.1f} mm: nothing grasped"
            )
        model, data = physics.model, physics.data
        hand_quat, relquat = np.empty(4), np.empty(4)
        mujoco.mju_negQuat(hand_quat, data.xquat[self._hand])
        mujoco.mju_mulQuat(relquat, hand_quat, data.xquat[self._arrow])
        rot = data.xmat[self._hand].reshape(3, 3)
        relpos = rot.T @ (data.xpos[self._arrow] - data.xpos[self._hand])
        # the model is written: worlds that share a model grasp one at a time
        model.eq_data[self._grasp_eq, 3:10] = np.concatenate([relpos, relquat])
        data.eq_active[self._grasp_eq] = 1
        data.eq_active[self._holder_eq] = 0
        # the arm compensates the held arrow's weight as it does its own links' (gravcomp)
        physics.set_arrow_force(-physics.arrow_mass * physics.gravity)
        data.ctrl[self._grip] = GRIP_CLOSED
        self.grasped = True
        return distance

    def nock(self) -> float:
        """Put the held arrow's nock on the string; returns its distance from the string (m).

        Raises:
            StateError: no arrow is held.
            NockMissed: the nock is farther than `nock_tolerance`; the arrow stays in the hand.
        """
        if not self.grasped:
            raise StateError("the hand holds no arrow to nock; grasp one first")
        physics = self.physics
        physics.kinematics()
        distance = self.nock_distance()
        if distance > self.nock_tolerance:
            raise NockMissed(
                f"the arrow's nock is {distance * 1000:.1f} mm from the string, more than the "
                f"nock tolerance of {self.nock_tolerance * 1000:.1f} mm: not nocked"
            )
        data = physics.data
        rot = data.xmat[self._hand].reshape(3, 3)
        self._pinch = rot.T @ (data.site_xpos[self._nock_site] - data.xpos[self._hand])
        data.eq_active[self._grasp_eq] = 0  # the string and the bow hold the arrow now
        self.pin()
        return distance

    def arrow_line(self) -> np.ndarray:
        """The nocked arrow's θ (m): its nock relative to the bow hand's pivot, the arrow lying
        along its negative; the nock at rest when not nocked."""
        line: np.ndarray = self.nocking_point() - self.physics.data.site_xpos[self._bow_site]
        return line

    def nock_in_hand(self) -> np.ndarray:
        """The nocking point in the string hand's frame (m, `r_hand_dh_frame`)."""
        data = self.physics.data
        site = self._string_site
        rot = data.site_xmat[site].reshape(3, 3)
        local: np.ndarray = rot.T @ (self.nocking_point() - data.site_xpos[site])
        return local

    def release(self) -> tuple[np.ndarray, np.ndarray]:
        """Open the fingers on the nocked arrow: the string goes back to rest.

        Returns:
            (the arrow's tip (m), its θ (`arrow_line`, m)) at the release.

        Raises:
            ArrowDropped: the arrow was held but not nocked; it now falls.
            StateError: no arrow is held.
        """
        data = self.physics.data
        if not self.grasped:
            raise StateError("the hand holds no arrow")
        self.physics.kinematics()
        data.ctrl[self._grip] = 0.0
        self.grasped = False
        if self._pinch is None:
            data.eq_active[self._grasp_eq] = 0
            self.physics.set_arrow_force(np.zeros(3))
            raise ArrowDropped("the fingers opened on an arrow that was not nocked: it fell")
        tip, _ = self._nocked_pose()
        line = self.arrow_line()
        self._pinch = None
        self.pin()
        return tip, line

    def _nocked_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """(tip (m), unit direction) of the nocked arrow: from the nock across the bow hand."""
        nock = self.nocking_point()
        direction = arrow_direction(nock - self.physics.data.site_xpos[self._bow_site])
        tip: np.ndarray = nock + self._arrow_length * direction
        return tip, direction

    def pin(self) -> None:
        """Keep the string's nocking point (and a nocked arrow) where they belong, at rest; call
        after the physics steps, with the kinematics current."""
        physics = self.physics
        data = physics.data
        q, v = self._string_q, self._string_v
        data.qpos[q : q + 3] = self.nocking_point()
        data.qpos[q + 3 : q + 7] = (1.0, 0.0, 0.0, 0.0)
        data.qvel[v : v + 6] = 0.0
        data.xfrc_applied[self._string_body, :3] = self._string_weight
        if self._pinch is not None:
            tip, direction = self._nocked_pose()
            physics.set_arrow_pose(tip, arrow_quat(direction))
            physics.set_arrow_velocity(np.zeros(3))
            physics.set_arrow_force(self._arrow_weight)

    def grip_angle(self) -> float:
        """The fingers' hinge angle (rad): 0 open, `GRIP_CLOSED` closed."""
        return float(self.physics.data.qpos[self._grip_q])
