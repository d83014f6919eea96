"""The whole shot's movement for θ as one trajectory of the torso and both arms: the
demonstration's DMPs (`movement`) whose draw ends in the archery posture for θ (the
controller's IK, Eq. 9), from where the robot stands, with grasp and nock at their demonstrated
times, up to the release (the learner's to call). Times in s of simulated time from the
trajectory's start, angles in rad. Pure: no mesh.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from protocol.parts import PARTS
from protocol.robotspec import BOW_ARM, STRING_ARM, TORSO, home_of
from protocol.verbs.robot import MAX_TRAJECTORY_POINTS
from services.controller.movement import Movement

__all__ = ["LEAD_SPEED", "PARTS_MOVED", "ShotTrajectory", "whole_shot_trajectory"]

#: The parts the movement moves, in the order of a row's joints.
PARTS_MOVED = (TORSO, BOW_ARM, STRING_ARM)
#: rad/s: the fastest joint's speed from where the robot stands to the movement's start (a
#: robot at the demonstrated start goes straight on with it)
LEAD_SPEED = 0.8


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


def _smooth(s: np.ndarray) -> np.ndarray:
    """Minimum-jerk blend 0 → 1 over s ∈ [0, 1] (clipped outside)."""
    s = np.clip(s, 0.0, 1.0)
    blend: np.ndarray = s**3 * (10.0 - 15.0 * s + 6.0 * s**2)
    return blend


def whole_shot_trajectory(
    movement: Movement, posture: Mapping[str, float], standing: Mapping[str, float]
) -> ShotTrajectory:
    """The whole shot towards `posture` (the archery posture for θ, {joint: rad}) from
    `standing` (the robot's joints now, {joint: rad}).

    The arms follow the DMPs rolled out with the draw's goal the posture's arms; the torso
    stays at home as demonstrated until the nock, then turns to the posture's torso by the
    release (a minimum-jerk blend). A robot away from the demonstrated start first goes there,
    its fastest joint at `LEAD_SPEED`. At most `MAX_TRAJECTORY_POINTS` waypoints (the DMPs'
    samples thinned evenly when more).
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
