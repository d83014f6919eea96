"""The MuJoCo archery scene at run time: `ScenePhysics`, physics queries by name.

The scene is an iCub (the `icub-models` URDF edited by `sim.urdf`), a bow, an arrow, a target,
a floor and cameras, assembled by `sim.model_build.build_scene` from a `sim.scene_config.
SceneConfig`; the model is fully determined by its config, so a renderer that rebuilds it with
the same config reproduces any state from `qpos` alone. `ScenePhysics` is the thin layer of
physics queries by name (joint slices per part, sites, the arrow's pose and velocity) that task
logic builds on.

Frame: the MuJoCo world frame is the iCub `root_link` frame (x backward, y right, z up; metres);
angles are radians, times seconds.
"""

from __future__ import annotations

import mujoco
import numpy as np

from archery.protocol.parts import PARTS
from archery.sim.errors import CommandError, SceneError
from archery.sim.scene_config import (
    ARROW_BODY,
    ARROW_JOINT,
    ARROW_TIP_SITE,
    BOW_HAND_SITE,
    STRING_HAND_SITE,
    TARGET_CENTRE_SITE,
)

__all__ = ["ScenePhysics"]


class ScenePhysics:
    """Name-resolved access to a compiled archery scene's state; no task logic.

    Positions are metres in the root frame (= MuJoCo world), angles radians, times seconds.
    """

    def __init__(self, model: mujoco.MjModel, data: mujoco.MjData | None = None) -> None:
        self.model = model
        self.data = mujoco.MjData(model) if data is None else data
        try:
            self._qpos = {
                p: np.array([model.joint(j).qposadr[0] for j in js]) for p, js in PARTS.items()
            }
            self._dof = {
                p: np.array([model.joint(j).dofadr[0] for j in js]) for p, js in PARTS.items()
            }
            self._act = {p: np.array([model.actuator(j).id for j in js]) for p, js in PARTS.items()}
            self._margin = {
                p: model.jnt_margin[[model.joint(j).id for j in js]].copy()
                for p, js in PARTS.items()
            }
            self._range = {
                p: model.jnt_range[[model.joint(j).id for j in js]].copy()
                for p, js in PARTS.items()
            }
            self._site = {
                n: model.site(n).id
                for n in (BOW_HAND_SITE, STRING_HAND_SITE, ARROW_TIP_SITE, TARGET_CENTRE_SITE)
            }
            arrow = model.joint(ARROW_JOINT)
            self._arrow_body = model.body(ARROW_BODY).id
        except KeyError as exc:
            raise SceneError(
                f"not an archery scene (build it with sim.scene.build_scene): {exc}"
            ) from exc
        self._arrow_qpos = int(arrow.qposadr[0])
        self._arrow_dof = int(arrow.dofadr[0])
        self.arrow_mass = float(model.body_mass[self._arrow_body])
        # views of the arrow's state in the data, read and written at every step of a flight
        a, d = self._arrow_qpos, self._arrow_dof
        self._tip, self._velocity = self.data.qpos[a : a + 3], self.data.qvel[d : d + 3]
        self._force = self.data.xfrc_applied[self._arrow_body]

    # -- joints ---------------------------------------------------------------------------
    def _part(self, part: str) -> str:
        if part not in PARTS:
            raise CommandError(f"unknown part {part!r}; parts: {', '.join(PARTS)}")
        return part

    def joint_names(self, part: str) -> tuple[str, ...]:
        """Joint names of `part` in YARP order."""
        return PARTS[self._part(part)]

    def qpos_indices(self, part: str) -> np.ndarray:
        """Indices of `part`'s joint angles in `data.qpos`, YARP order."""
        return self._qpos[self._part(part)].copy()

    def dof_indices(self, part: str) -> np.ndarray:
        """Indices of `part`'s joint velocities in `data.qvel`, YARP order."""
        return self._dof[self._part(part)].copy()

    def actuator_indices(self, part: str) -> np.ndarray:
        """Indices of `part`'s position servos in `data.ctrl`, YARP order."""
        return self._act[self._part(part)].copy()

    def joint_limits(self, part: str) -> tuple[np.ndarray, np.ndarray]:
        """(lower, upper) URDF joint limits of `part` (rad)."""
        limits = self._range[self._part(part)]
        return limits[:, 0].copy(), limits[:, 1].copy()

    def joint_margins(self, part: str) -> np.ndarray:
        """How far inside its URDF limits each of `part`'s joint stops engages (rad)."""
        return self._margin[self._part(part)].copy()

    def joint_positions(self, part: str) -> np.ndarray:
        """Joint angles of `part` (rad)."""
        return self.data.qpos[self._qpos[self._part(part)]].copy()

    def joint_velocities(self, part: str) -> np.ndarray:
        """Joint velocities of `part` (rad/s)."""
        return self.data.qvel[self._dof[self._part(part)]].copy()

    def set_joint_positions(self, part: str, values: np.ndarray) -> None:
        """Teleport `part`'s joints to `values` (rad) at rest; kinematics are not recomputed."""
        self.data.qpos[self._qpos[self._part(part)]] = values
        self.data.qvel[self._dof[part]] = 0.0

    # -- sites ----------------------------------------------------------------------------
    def site_position(self, name: str) -> np.ndarray:
        """Position of the site `name` (m) as of the last kinematics pass."""
        site = self._site.get(name)
        if site is None:
            raise CommandError(f"unknown site {name!r}; sites: {', '.join(self._site)}")
        return self.data.site_xpos[site].copy()

    def site_rotation(self, name: str) -> np.ndarray:
        """3×3 rotation of the site `name` (columns: its axes in the root frame)."""
        site = self._site.get(name)
        if site is None:
            raise CommandError(f"unknown site {name!r}; sites: {', '.join(self._site)}")
        return self.data.site_xmat[site].reshape(3, 3).copy()

    def hand_positions(self) -> tuple[np.ndarray, np.ndarray]:
        """(bow hand, string hand) end-effector positions (m) as of the last kinematics pass."""
        return self.site_position(BOW_HAND_SITE), self.site_position(STRING_HAND_SITE)

    # -- the arrow ------------------------------------------------------------------------
    def arrow_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """(tip position (m), orientation quaternion w, x, y, z) of the arrow."""
        q = self.data.qpos[self._arrow_qpos : self._arrow_qpos + 7]
        return q[:3].copy(), q[3:].copy()

    def set_arrow_pose(self, tip: np.ndarray, quat: np.ndarray) -> None:
        """Place the arrow's tip at `tip` (m) with orientation `quat` (w, x, y, z)."""
        self.data.qpos[self._arrow_qpos : self._arrow_qpos + 3] = tip
        self.data.qpos[self._arrow_qpos + 3 : self._arrow_qpos + 7] = quat

    def stowed_arrow_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """(tip (m), quaternion) of the arrow's place off the bow: the model's initial pose."""
        q = self.model.qpos0[self._arrow_qpos : self._arrow_qpos + 7]
        return q[:3].copy(), q[3:].copy()

    def arrow_tip(self) -> np.ndarray:
        """The arrow tip's position (m): the free joint's translation, exact after any step."""
        return self._tip.copy()

    def arrow_velocity(self) -> np.ndarray:
        """The arrow's linear velocity (m/s)."""
        return self._velocity.copy()

    def set_arrow_velocity(self, linear: np.ndarray, angular: np.ndarray | None = None) -> None:
        """Set the arrow's linear (m/s, world) and angular (rad/s, body frame) velocity."""
        self.data.qvel[self._arrow_dof : self._arrow_dof + 3] = linear
        self.data.qvel[self._arrow_dof + 3 : self._arrow_dof + 6] = (
            0.0 if angular is None else angular
        )

    def set_arrow_force(self, force: np.ndarray) -> None:
        """Apply `force` (N, world frame) at the arrow's centre of mass until changed."""
        self._force[:3] = force
        self._force[3:] = 0.0

    # -- time and integration ---------------------------------------------------------------
    @property
    def time(self) -> float:
        """Simulated time (s)."""
        return float(self.data.time)

    @property
    def timestep(self) -> float:
        """Physics step (s)."""
        return float(self.model.opt.timestep)

    @property
    def gravity(self) -> np.ndarray:
        """Gravity (m/s², root frame)."""
        return self.model.opt.gravity.copy()

    def reset(self) -> None:
        """Reset the data to the model's initial state (time 0, qpos0, zero velocity)."""
        mujoco.mj_resetData(self.model, self.data)

    def kinematics(self) -> None:
        """Recompute body and site poses from qpos."""
        mujoco.mj_kinematics(self.model, self.data)

    def forward(self) -> None:
        """Recompute every derived quantity from the state (no integration)."""
        mujoco.mj_forward(self.model, self.data)

    def step(self) -> None:
        """Advance the physics by one timestep."""
        mujoco.mj_step(self.model, self.data)

    def qpos(self) -> np.ndarray:
        """A copy of the full generalised position vector (enough to render the scene)."""
        return self.data.qpos.copy()
