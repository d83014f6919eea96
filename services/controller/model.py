"""Pinocchio kinematics of iCub's torso and both arms (17 joints), hand frames in `root_link`.

The model name, the hand frames and the home posture come from `protocol.robotspec`, shared with
the simulator. Here the home posture only seeds the IK: it is the default for joints a caller
leaves out, the default warm start and the default rest posture q̂ of Eq. 9.
"""

from __future__ import annotations

import functools
import os
from collections.abc import Mapping
from types import MappingProxyType

import numpy as np
import pinocchio as pin

from archery.protocol.parts import PARTS
from archery.protocol.robotspec import HAND_FRAMES, HOME_POSTURE, model_file
from archery.services.controller.errors import JointError

__all__ = ["JOINT_NAMES", "ArmsModel", "load_arms_model"]

#: Every controlled joint, in YARP order: torso (yaw, roll, pitch), left arm, right arm.
JOINT_NAMES: tuple[str, ...] = PARTS["torso"] + PARTS["left_arm"] + PARTS["right_arm"]

JointValues = Mapping[str, float] | np.ndarray


class ArmsModel:
    """The `icub-models` URDF reduced to torso + both arms; everything else locked at zero.

    Public vectors are in `JOINT_NAMES` order (radians). Positions are metres in the `root_link`
    frame (x backward, y to the robot's right, z up; the robot faces −x). The helper methods
    share one `pinocchio.Data` and are not thread-safe; solvers make their own.
    """

    def __init__(self, urdf_path: str | os.PathLike[str] | None = None) -> None:
        path = model_file() if urdf_path is None else urdf_path
        full = pin.buildModelFromUrdf(str(path))
        missing = [name for name in JOINT_NAMES if not full.existJointName(name)]
        if missing:
            raise JointError(f"URDF {path} lacks joints {missing}; expected all of {JOINT_NAMES}")
        keep = set(JOINT_NAMES)
        lock = [full.getJointId(n) for n in list(full.names)[1:] if n not in keep]
        self.model: pin.Model = pin.buildReducedModel(full, lock, pin.neutral(full))
        self.data: pin.Data = self.model.createData()
        self.joint_names: tuple[str, ...] = JOINT_NAMES
        self.urdf_path: str = str(path)
        for frame in HAND_FRAMES.values():
            if not self.model.existFrame(frame):
                raise JointError(f"URDF {path} lacks frame {frame!r}")
        #: pin_index[i] is the position of JOINT_NAMES[i] in Pinocchio's configuration vector.
        self.pin_index = np.array(
            [self.model.joints[self.model.getJointId(n)].idx_q for n in JOINT_NAMES], dtype=np.intp
        )
        self.lower = np.asarray(self.model.lowerPositionLimit, dtype=float)[self.pin_index].copy()
        self.upper = np.asarray(self.model.upperPositionLimit, dtype=float)[self.pin_index].copy()
        self.lower.setflags(write=False)
        self.upper.setflags(write=False)
        self.frame_ids: Mapping[str, int] = MappingProxyType(
            {arm: self.model.getFrameId(frame) for arm, frame in HAND_FRAMES.items()}
        )
        self._index = {name: i for i, name in enumerate(JOINT_NAMES)}
        self._home = np.array([HOME_POSTURE[n] for n in JOINT_NAMES])
        self._home.setflags(write=False)

    @property
    def nq(self) -> int:
        """Number of controlled joints (17)."""
        return len(self.joint_names)

    def index(self, joint: str) -> int:
        """Position of `joint` in `JOINT_NAMES`.

        Raises:
            JointError: the joint is not controlled; the message lists the valid names.
        """
        try:
            return self._index[joint]
        except KeyError:
            raise JointError(
                f"unknown joint {joint!r}; valid joints: {', '.join(self.joint_names)}"
            ) from None

    def chain(self, arm: str, *, use_torso: bool = True) -> tuple[str, ...]:
        """Joint names moved when solving for `arm` ("left_arm"/"right_arm"), torso first.

        Raises:
            JointError: `arm` is not an arm part.
        """
        check_arm(arm)
        return (PARTS["torso"] if use_torso else ()) + PARTS[arm]

    def vector(
        self, q: JointValues | None = None, *, default: JointValues | None = None
    ) -> np.ndarray:
        """A joint vector (rad, `JOINT_NAMES` order) from a per-name mapping or a 17-vector.

        Joints missing from a mapping come from `default` (itself a mapping or vector; the home
        posture when None). Values are not clipped.

        Raises:
            JointError: an unknown name, a wrong-length vector or a non-finite angle.
        """
        base = self._home if default is None else self.vector(default)
        if q is None:
            return base.copy()
        if isinstance(q, Mapping):
            out = base.copy()
            for name, value in q.items():
                out[self.index(name)] = float(value)
        else:
            out = np.array(q, dtype=float)
            if out.shape != (self.nq,):
                raise JointError(
                    f"joint vector must have shape ({self.nq},) in JOINT_NAMES order, "
                    f"got shape {out.shape}"
                )
        bad = ~np.isfinite(out)
        if bad.any():
            names = [self.joint_names[i] for i in np.flatnonzero(bad)]
            raise JointError(f"joint angles must be finite radians; got NaN/inf for {names}")
        return out

    def mapping(self, q: np.ndarray) -> Mapping[str, float]:
        """A read-only {joint name: angle (rad)} mapping from a `JOINT_NAMES`-ordered vector."""
        return MappingProxyType({n: float(v) for n, v in zip(self.joint_names, q, strict=True)})

    def clip(self, q: np.ndarray) -> np.ndarray:
        """`q` (rad, `JOINT_NAMES` order) clipped into the URDF joint limits."""
        result: np.ndarray = np.clip(q, self.lower, self.upper)
        return result

    def to_pinocchio(self, q: np.ndarray) -> np.ndarray:
        """Reorder a `JOINT_NAMES` vector into Pinocchio's configuration order."""
        out = np.empty(self.model.nq)
        out[self.pin_index] = q
        return out

    def from_pinocchio(self, q_pin: np.ndarray) -> np.ndarray:
        """Reorder a Pinocchio configuration into a `JOINT_NAMES` vector."""
        return np.asarray(q_pin)[self.pin_index].copy()

    def hand_pose(self, q: JointValues, arm: str) -> tuple[np.ndarray, np.ndarray]:
        """Position (m) and rotation matrix of `arm`'s hand frame in `root_link` at posture `q`."""
        check_arm(arm)
        fid = self.frame_ids[arm]
        pin.forwardKinematics(self.model, self.data, self.to_pinocchio(self.vector(q)))
        placement = pin.updateFramePlacement(self.model, self.data, fid)
        return placement.translation.copy(), placement.rotation.copy()


def check_arm(arm: str) -> str:
    """Return `arm` if it is an arm part name, else raise `JointError` naming the valid ones."""
    if arm not in HAND_FRAMES:
        raise JointError(f"unknown arm {arm!r}; valid arms: {', '.join(HAND_FRAMES)}")
    return arm


@functools.lru_cache(maxsize=1)
def load_arms_model() -> ArmsModel:
    """The shared `ArmsModel` of the default `iCubGazeboV2_5` URDF (loaded once)."""
    return ArmsModel()
