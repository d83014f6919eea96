"""The whole shot's movement for θ as one trajectory of the torso and both arms: the
demonstration's DMPs (`movement`) whose draw ends in the archery posture for θ (the
controller's IK, Eq. 9), from where the robot stands, with grasp and nock at their demonstrated
times, up to the release (the learner's to call). Times in s of simulated time from the
trajectory's start, angles in rad. Pure: no mesh.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from archery.protocol.parts import PARTS
from archery.protocol.robotspec import BOW_ARM, STRING_ARM, TORSO, home_of
from archery.protocol.verbs.robot import MAX_TRAJECTORY_POINTS
from archery.services.controller.movement import Movement
from archery.services.controller.posture import ArcheryPosture, PostureResult, hand_orientations

__all__ = [
    "LEAD_SPEED",
    "PARTS_MOVED",
    "AimedShot",
    "ShotTrajectory",
    "aim_arrow",
    "plan_whole_shot",
    "whole_shot_trajectory",
]

#: The parts the movement moves, in the order of a row's joints.
PARTS_MOVED = (TORSO, BOW_ARM, STRING_ARM)
#: rad/s: the fastest joint's speed from where the robot stands to the movement's start (a
#: robot at the demonstrated start goes straight on with it)
LEAD_SPEED = 0.8
#: the most IK solves `aim_arrow` makes, and the offset's change (m) at which it stops
AIM_ITERATIONS = 4
AIM_TOLERANCE = 5e-4


@dataclass(frozen=True)
class ShotTrajectory:
    """The waypoints (`times` s, `rows` rad: the joints of `PARTS_MOVED` one part after the
    other) and the actions' times (s) of one whole shot; `lead` s lead from where the robot
    stood to the demonstrated start, `release` s is the last waypoint's time."""

    times: np.ndarray
    rows: np.ndarray
    grasp: float
    nock: float
    lead: float

    @property
    def release(self) -> float:
        """s from the start to the release (the last waypoint)."""
        return float(self.times[-1])


def aim_arrow(
    posture: ArcheryPosture, theta: np.ndarray, nock_in_hand: Sequence[float] | None
) -> tuple[PostureResult, np.ndarray]:
    """The archery posture whose nocked arrow lies along θ (m, a checked θ): the hands' θ is θ
    less the nock's offset from the string hand (m, root frame), `nock_in_hand` (m, the string
    hand's frame, as the robot tells it) turned by the hand's solved orientation, found by
    fixed-point iteration (≤ `AIM_ITERATIONS` solves, to `AIM_TOLERANCE`); the hands at θ when
    the robot tells none. Returns (the posture, the offset)."""
    if nock_in_hand is None:
        return posture.solve_checked(theta), np.zeros(3)
    local = np.asarray(nock_in_hand, dtype=float)
    _, string_hand = hand_orientations(theta)
    offset: np.ndarray = string_hand @ local
    for _ in range(AIM_ITERATIONS):
        result = posture.solve_checked(theta - offset, arrow=theta)
        _, string_hand = posture.solver.hand_pose(result.q, STRING_ARM)
        moved = string_hand @ local
        if float(np.linalg.norm(moved - offset)) < AIM_TOLERANCE:
            break
        offset = moved
    return result, offset


def _smooth(s: np.ndarray) -> np.ndarray:
    """Minimum-jerk blend 0 → 1 over s ∈ [0, 1] (clipped outside)."""
    s = np.clip(s, 0.0, 1.0)
    blend: np.ndarray = s**3 * (10.0 - 15.0 * s + 6.0 * s**2)
    return blend


def whole_shot_trajectory(
    movement: Movement,
    posture: Mapping[str, float],
    standing: Mapping[str, float],
    limits: tuple[np.ndarray, np.ndarray] | None = None,
) -> ShotTrajectory:
    """The whole shot towards `posture` (the archery posture for θ, {joint: rad}) from
    `standing` (the robot's joints now, {joint: rad}).

    The arms follow the DMPs rolled out with the draw's goal the posture's arms; the torso
    stays at home as demonstrated until the nock, then turns to the posture's torso by the
    release (a minimum-jerk blend). A robot away from the demonstrated start first goes there,
    its fastest joint at `LEAD_SPEED`. At most `MAX_TRAJECTORY_POINTS` waypoints (the DMPs'
    samples thinned evenly when more), clipped to `limits` (rad: lower and upper, the rows'
    joints) where given: a DMP drawn to a goal at a joint's limit overshoots it a little.
    """
    goal = np.array([posture[j] for part in (BOW_ARM, STRING_ARM) for j in PARTS[part]])
    rollout = movement.reproduce(goal)
    keep = rollout.t <= rollout.release + 1e-9
    t = rollout.t[keep]
    arms = np.hstack([rollout.left_arm[keep], rollout.right_arm[keep]])
    home = np.array(home_of(TORSO))
    turned = np.array([posture[j] for j in PARTS[TORSO]])
    span = max(rollout.release - rollout.nock, 1e-6)
    blend = _smooth((t - rollout.nock) / span)[:, None]
    torso = home + blend * (turned - home)
    rows = np.hstack([torso, arms])
    if limits is not None:
        rows = np.clip(rows, *limits)
    here = np.array([standing[j] for part in PARTS_MOVED for j in PARTS[part]])
    step = float(np.median(np.diff(t))) if t.size > 1 else 0.01
    lead = max(step, float(np.max(np.abs(rows[0] - here))) / LEAD_SPEED)
    times = t + lead
    if times.size > MAX_TRAJECTORY_POINTS:
        pick = np.unique(np.linspace(0, times.size - 1, MAX_TRAJECTORY_POINTS).round().astype(int))
        times, rows = times[pick], rows[pick]
    return ShotTrajectory(
        times=times,
        rows=rows,
        grasp=lead + rollout.grasp,
        nock=lead + rollout.nock,
        lead=lead,
    )


@dataclass(frozen=True)
class AimedShot:
    """The whole shot for θ: its posture (`posture.theta_achieved` the hands'), the nock's
    offset from the string hand (m, root frame) and the trajectory there."""

    posture: PostureResult
    nock: np.ndarray
    plan: ShotTrajectory


def plan_whole_shot(
    movement: Movement,
    posture: ArcheryPosture,
    theta: np.ndarray,
    nock_in_hand: Sequence[float] | None,
    standing: Mapping[str, float],
) -> AimedShot:
    """The whole shot for θ (m, checked) from `standing` ({joint: rad}): the posture that aims
    the arrow (`aim_arrow`), the movement drawn there within the model's joint limits."""
    result, nock = aim_arrow(posture, theta, nock_in_hand)
    model = posture.model
    moved = [model.index(j) for part in PARTS_MOVED for j in PARTS[part]]
    limits = (model.lower[moved], model.upper[moved])
    return AimedShot(result, nock, whole_shot_trajectory(movement, result.q, standing, limits))
