"""The archery posture: both hands' poses from θ (string hand relative to bow hand), solved by IK.

θ = p_string − p_bow (m; root_link frame: x backward, y to the robot's right, z up; the robot
faces −x) is the right (string) hand's position relative to the left (bow) hand; the arrow flies
from the string hand through the bow hand, along a = −θ/‖θ‖, and the hands' orientations follow
from it (`hand_orientations`). The relative position is what the learner controls, so it is the
highest-priority constraint; the bow hand's absolute position comes next; orientations and a
rest posture are the Eq. 9 cost.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pinocchio as pin

from archery.protocol.errors import ConfigError
from archery.protocol.parts import PARTS
from archery.protocol.robotspec import BOW_ARM, BOW_HAND, NOMINAL_THETA, STRING_ARM
from archery.protocol.theta import THETA_BOX, ThetaBox
from archery.protocol.vectors import finite_vector
from archery.services.controller.errors import TargetError
from archery.services.controller.ik import IkSolver
from archery.services.controller.ik_types import (
    IkSettings,
    OrientationTarget,
    PositionTarget,
    TargetsResult,
)
from archery.services.controller.model import JointValues, load_arms_model

__all__ = [
    "ArcheryPosture",
    "PostureConfig",
    "PostureResult",
    "hand_orientations",
]

_UP = np.array([0.0, 0.0, 1.0])
#: An arrow closer to vertical than this leaves "bow vertical" without meaning: a posture box
#: must keep every θ farther from it (`PostureConfig`).
MIN_TILT_FROM_VERTICAL = math.radians(1.0)


def hand_orientations(theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Desired rotations (root frame) of the left and right hand frames for θ, a finite
    3-vector (m) of a posture box (`PostureConfig` keeps its arrows off vertical).

    Conventions (root_link frame):

    * The bow lies in the vertical plane that contains the arrow ("zero roll"); its axis is
      b = the unit vertical with its component along a = −θ/‖θ‖ removed.
    * Hand frames (`l_hand_dh_frame`, `r_hand_dh_frame`, found from the URDF's hand meshes): +x
      runs from the wrist towards the fingers, −y points to the thumb side, and z is normal to
      the palm: the palm faces −z on the left hand and +z on the right hand.
    * Bow (left) hand: palm perpendicular to the arrow and facing the target (z_L = −a), bow
      grip vertical across the palm with the thumb up (y_L = −b), so x_L = y_L × z_L.
    * String (right) hand: fingers along the arrow (x_R = a), thumb up (y_R = −b), so the palm
      faces the bow hand (z_R = x_R × y_R).

    θ is not checked: a posture box's θ are at least its low x (> 0 m) long.
    """
    a = _along(theta)
    b = _UP - (_UP @ a) * a
    b /= float(np.linalg.norm(b))
    y = -b
    z_left = -a
    left = np.column_stack((np.cross(y, z_left), y, z_left))
    right = np.column_stack((a, y, np.cross(a, y)))
    return left, right


def _along(theta: np.ndarray) -> np.ndarray:
    """−θ/‖θ‖, the arrow's direction (`protocol.direction`) of a θ that the posture box keeps
    long (‖θ‖ ≥ its low x > 0 m): not checked again."""
    direction: np.ndarray = -theta / float(np.linalg.norm(theta))
    return direction


@dataclass(frozen=True)
class PostureConfig:
    """Where the bow hand sits and which θ the posture accepts.

    Attributes:
        bow_hand: nominal left-hand position (m, root frame).
        theta_box: the θ the posture accepts (m); θ outside raises TargetError. The default is
            `protocol.theta.THETA_BOX`. Every θ in it must put the
            string hand behind the bow hand (low x > 0 m) and the arrow more than
            `MIN_TILT_FROM_VERTICAL` from vertical, so a θ inside has an arrow direction and
            hand orientations without another check.
        nominal_theta: θ (m) of the reference posture (rest posture and default warm start).
        use_torso: move the torso with the arms (True) or hold it at the start posture.
        reference_starts: start postures tried when searching the reference posture, ≥ 1.
        seed: seed of those start postures.
        ik: settings of the underlying Eq. 9 solver; the rest weight w2 = 0.1 (ten times the
            single-hand default) keeps neighbouring θ on neighbouring postures, at the price of
            a few hundredths of a radian of orientation error.
    """

    bow_hand: Any = BOW_HAND
    theta_box: ThetaBox = THETA_BOX
    nominal_theta: Any = NOMINAL_THETA
    use_torso: bool = True
    reference_starts: int = 24
    seed: int = 0
    ik: IkSettings = field(default_factory=lambda: IkSettings(rest_weight=0.1))

    def __post_init__(self) -> None:
        for name in ("bow_hand", "nominal_theta"):
            object.__setattr__(self, name, finite_vector(name, getattr(self, name), ConfigError))
        box = self.theta_box
        if not isinstance(box, ThetaBox):
            raise ConfigError(f"theta_box must be a ThetaBox, got {type(box).__name__}")
        if box.low[0] <= 0:
            raise ConfigError(
                f"theta_box low x must be > 0 m (string hand behind the bow hand, arrow towards "
                f"−x), got low={box.low}, high={box.high} m"
            )
        # The arrow nearest vertical in the box: the least horizontal reach (low x, the y
        # nearest 0) under the highest |z|.
        nearest_y = min(max(0.0, box.low[1]), box.high[1])
        tilt = math.atan2(math.hypot(box.low[0], nearest_y), max(-box.low[2], box.high[2]))
        if tilt <= MIN_TILT_FROM_VERTICAL:
            raise ConfigError(
                f"theta_box low={box.low}, high={box.high} m lets the arrow come within "
                f"{math.degrees(MIN_TILT_FROM_VERTICAL):g}° of vertical"
            )
        if not box.contains(self.nominal_theta):
            raise ConfigError(f"nominal_theta: {box.outside('θ', self.nominal_theta)}")
        if not isinstance(self.reference_starts, int) or self.reference_starts < 1:
            raise ConfigError(
                f"reference_starts must be an integer >= 1, got {self.reference_starts!r}"
            )
        if not isinstance(self.seed, int) or self.seed < 0:
            raise ConfigError(f"seed must be an integer >= 0, got {self.seed!r}")


@dataclass(frozen=True)
class PostureResult:
    """The archery posture reached for one θ.

    Attributes:
        q: posture {joint: rad} for the 17 joints (torso, left arm, right arm).
        theta: θ asked (m).
        theta_achieved: x_right − x_left at q (m), what the arrow will see.
        relative_error_m: ‖θ − θ_achieved‖ (m).
        bow_hand: left hand position reached (m, root frame).
        bow_hand_error_m: distance from the nominal bow-hand position (m).
        arrow_direction: −θ_achieved/‖θ_achieved‖ (unit, root frame).
        left_orientation, right_orientation: hand orientations reached, axis-angle (rad).
        left_orientation_error_rad, right_orientation_error_rad: angle to the desired ones (rad).
        reachable: both position constraints hold (relative and bow hand, within the IK
            tolerance); when False, q is the closest posture found.
        iterations: IK iterations used.
    """

    q: Mapping[str, float]
    theta: np.ndarray
    theta_achieved: np.ndarray
    relative_error_m: float
    bow_hand: np.ndarray
    bow_hand_error_m: float
    arrow_direction: np.ndarray
    left_orientation: np.ndarray
    right_orientation: np.ndarray
    left_orientation_error_rad: float
    right_orientation_error_rad: float
    reachable: bool
    iterations: int


class ArcheryPosture:
    """Turns θ into the two-hand archery posture (Section V-B of the paper).

    Construction searches, from `reference_starts` seeded postures, the lowest-cost posture for
    the nominal θ; it serves as rest posture q̂ and default warm start, so postures for nearby θ
    stay in the same family. Not thread-safe (owns an `IkSolver`).
    """

    def __init__(self, config: PostureConfig | None = None, solver: IkSolver | None = None) -> None:
        self.config = PostureConfig() if config is None else config
        self.solver = IkSolver(load_arms_model(), self.config.ik) if solver is None else solver
        self.model = self.solver.model
        self.joints: tuple[str, ...] = (
            (PARTS["torso"] if self.config.use_torso else ()) + PARTS[BOW_ARM] + PARTS[STRING_ARM]
        )
        self.reference: np.ndarray = self._search_reference()
        self.reference.setflags(write=False)

    def check_theta(self, theta: Sequence[float] | np.ndarray) -> np.ndarray:
        """θ, 3 finite numbers (m; as `PostureArgs` decodes them), as a read-only array inside
        the configured box: the controller's check of the box.

        Raises:
            TargetError: θ outside the configured box (the message names θ and the box).
        """
        th = np.array(theta, dtype=float)
        th.setflags(write=False)
        box = self.config.theta_box
        if not box.contains(th):
            raise TargetError(
                f"θ = {th.tolist()} m is outside the configured box {box.low}..{box.high} m"
            )
        return th

    def solve(
        self, theta: Sequence[float] | np.ndarray, *, q0: JointValues | None = None
    ) -> PostureResult:
        """The posture for θ, 3 finite numbers (m), warm-started from q0 (the current posture;
        default the reference posture).

        Raises:
            TargetError: θ outside the configured box. JointError: bad q0.
        """
        return self.solve_checked(self.check_theta(theta), q0=q0)

    def solve_checked(
        self,
        theta: np.ndarray,
        *,
        q0: JointValues | None = None,
        arrow: np.ndarray | None = None,
    ) -> PostureResult:
        """`solve` for a θ that `check_theta` returned (not checked again); the hands turned
        for the arrow's θ `arrow` (m; default θ: the arrow lies along the hands)."""
        start = self.reference if q0 is None else self.model.vector(q0, default=self.reference)
        res = self._solve(theta, start, arrow=arrow)
        return self._result(theta, res)

    def theta_at(self, q: JointValues | np.ndarray) -> np.ndarray:
        """θ = x_string − x_bow (m) of the hands at the posture q (forward kinematics)."""
        x_left, _ = self.solver.hand_pose(q, BOW_ARM)
        x_right, _ = self.solver.hand_pose(q, STRING_ARM)
        theta: np.ndarray = x_right - x_left
        return theta

    # ------------------------------------------------------------------------------- internals

    def _solve(
        self,
        theta: np.ndarray,
        start: np.ndarray,
        rest: np.ndarray | None = None,
        arrow: np.ndarray | None = None,
    ) -> TargetsResult:
        left_rot, right_rot = hand_orientations(theta if arrow is None else arrow)
        return self.solver.solve_targets(
            (
                PositionTarget(BOW_ARM, self.config.bow_hand, priority=0),
                PositionTarget(STRING_ARM, theta, relative_to=BOW_ARM, priority=1),
            ),
            (OrientationTarget(BOW_ARM, left_rot), OrientationTarget(STRING_ARM, right_rot)),
            joints=self.joints,
            q0=start,
            rest=self.reference if rest is None else rest,
        )

    def _search_reference(self) -> np.ndarray:
        cfg = self.config
        rng = np.random.default_rng(cfg.seed)
        idx = [self.model.index(j) for j in self.joints]
        home = self.model.vector(None)
        best: TargetsResult | None = None
        for k in range(cfg.reference_starts):
            start = home.copy()
            if k:
                start[idx] = rng.uniform(self.model.lower[idx], self.model.upper[idx])
            res = self._solve(cfg.nominal_theta, start, rest=home)
            if res.reachable and (best is None or res.cost < best.cost):
                best = res
        if best is None:
            raise ConfigError(
                f"no posture reaches bow hand {cfg.bow_hand.tolist()} m with θ "
                f"{cfg.nominal_theta.tolist()} m; move the bow hand towards the shoulders"
            )
        return best.q_vector.copy()

    def _result(self, theta: np.ndarray, res: TargetsResult) -> PostureResult:
        q = res.q_vector
        x_left, r_left = self.solver.hand_pose(q, BOW_ARM)
        x_right, r_right = self.solver.hand_pose(q, STRING_ARM)
        achieved = x_right - x_left
        arrays = [achieved, x_left]
        left_aa = np.asarray(pin.log3(r_left))
        right_aa = np.asarray(pin.log3(r_right))
        direction = _along(achieved)  # a solution's θ: within the IK's tolerance of a box's θ
        for arr in (*arrays, left_aa, right_aa, direction):
            arr.setflags(write=False)
        return PostureResult(
            q=res.q,
            theta=theta,
            theta_achieved=achieved,
            relative_error_m=float(np.linalg.norm(theta - achieved)),
            bow_hand=x_left,
            bow_hand_error_m=float(np.linalg.norm(self.config.bow_hand - x_left)),
            arrow_direction=direction,
            left_orientation=left_aa,
            right_orientation=right_aa,
            left_orientation_error_rad=res.orientation_errors_rad[0],
            right_orientation_error_rad=res.orientation_errors_rad[1],
            reachable=res.reachable,
            iterations=res.iterations,
        )
