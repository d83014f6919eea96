"""The whole shot of one rollout, from a demonstration's DMPs (`services.learner.movement`), on
a robot that runs `--shot whole`: reach, grasp, carry, nock and draw towards the archery
posture for θ, played on the arms' `command:i` ports (`services.learner.arms`) as waypoints
`WAYPOINT_STEP` s of the movement apart, with grasp and nock at their demonstrated times. The
release is the caller's. Joint angles in rad, θ in m, times in s.
"""

from __future__ import annotations

import contextlib
import time

import numpy as np

from mesh.node import Node
from protocol.errors import ArcheryError, RpcError, RpcTimeout
from protocol.robotspec import BOW_ARM, STRING_ARM, TORSO, home_of
from protocol.verbs import robot as rv
from services.learner.abort_policy import NOT_REACHED
from services.learner.arms import ArmDriver
from services.learner.movement import Movement, Reproduction
from sim.errors import CommandError
from sim.scene_config import SceneConfig
from sim.shot_script import ShotStep, plan_string_hand
from sim.world import ArcheryWorld

__all__ = ["DRAW_TOLERANCE", "LEASE_OWNER", "WAYPOINT_STEP", "WholeMovement", "plan", "play"]

WAYPOINT_STEP = 0.1  # s of the movement between two waypoints
DRAW_TOLERANCE = 0.04  # m: the draw's goal may end this far from θ (see `plan`)
LEASE_OWNER = "learner.whole-shot"  # the arms' leases while the movement plays
_LEASE_TTL = 120.0  # wall s: a learner that dies mid-movement frees the arms this long after


def plan(world: ArcheryWorld, movement: Movement, theta: np.ndarray) -> Reproduction:
    """`movement` with its draw's goal the archery posture for θ (m): the string hand at the
    bow hand + θ, the bow arm as demonstrated (`sim.shot_script.plan_string_hand` on `world`,
    which stands as the robot does). A θ the string arm alone cannot reach with the bow arm
    so (the controller's posture also turns the torso) is drawn to within `DRAW_TOLERANCE` of
    it: the controller's posture for θ, after the movement, takes the hands the rest of the
    way.

    Raises:
        CommandError: θ farther than `DRAW_TOLERANCE` from the string arm's reach.
    """
    bow_arm = movement.goal[:7]
    try:
        hold = plan_string_hand(world, theta, bow_arm)
    except CommandError:
        hold = plan_string_hand(world, theta, bow_arm, tolerance=DRAW_TOLERANCE)
    return movement.reproduce(np.concatenate([bow_arm, hold.right_arm]))


def play(arms: ArmDriver, world: ArcheryWorld, rollout: Reproduction) -> None:
    """Play `rollout` up to its release's time (the release is the caller's): the first
    waypoint is its start, with the torso at home as it was demonstrated (the controller's
    posture for θ may have turned it); every waypoint is clipped into `world`'s joint limits;
    the arms come to rest at the start, the grasp, the nock and the end, and pass through the
    waypoints between (`ArmDriver.move`'s `settle`); grasp and nock are called at their
    times.

    Raises:
        RpcError: an arm did not get to a waypoint in time (code `not_reached`, the abort code
            of a posture not reached), or the robot refused the grasp or the nock.
    """
    low = {part: world.joint_limits(part)[0] for part in (BOW_ARM, STRING_ARM)}
    high = {part: world.joint_limits(part)[1] for part in (BOW_ARM, STRING_ARM)}
    marks = {"grasp": rollout.grasp, "nock": rollout.nock}
    times = np.arange(0.0, rollout.release, WAYPOINT_STEP)
    torso: np.ndarray | None = np.asarray(home_of(TORSO))
    waypoints = np.union1d(times, [*marks.values(), rollout.release])
    stops = {float(waypoints[0]), *marks.values(), float(waypoints[-1])}
    for when in waypoints:
        left, right = rollout.at(float(when))
        step = ShotStep(
            "imitate",
            np.clip(right, low[STRING_ARM], high[STRING_ARM]),
            np.clip(left, low[BOW_ARM], high[BOW_ARM]),
        )
        try:
            arms.move(step, torso, settle=float(when) in stops)
        except RpcTimeout as exc:  # a robot alive but its arm stuck: not a lost service
            raise RpcError(
                f"the arms did not reach the movement's waypoint at {when:.2f} s: {exc.message}",
                code=NOT_REACHED,
            ) from None
        torso = None  # home from the first waypoint on
        for action, at in marks.items():
            if when == at:
                arms.act(action)


class WholeMovement:
    """The whole shot's movement before each release of a learning session.

    Args:
        node: the learner's node.
        timeout: wall s to wait for each waypoint and each verb.
        movement: the demonstration's DMPs.
        scene: the robot's scene (its `status`; shot "whole").
        speed: the joints' reference speed the movement plays at (rad/s; the robot's default,
            at which the demonstration was recorded).
    """

    def __init__(
        self, node: Node, timeout: float, movement: Movement, scene: SceneConfig, speed: float
    ):
        self._node = node
        self._speed = speed
        self.arms = ArmDriver(node, timeout)
        self.movement = movement
        self._world = self.arms.world(scene)

    def perform(self, theta: np.ndarray) -> dict[str, float]:
        """Reach, grasp, carry, nock and draw for θ (m) under the arms' and the torso's leases,
        at the reference speed; the wall time it took (s). A grasp or nock that fails leaves
        the robot reset (home posture, a fresh arrow in the holder, the shot noise's stream
        going on), so the next attempt starts clean.

        Raises:
            CommandError: θ out of reach (nothing moved). RpcError: as `play`, or another
                client holds a part (`not_owner`). RpcTimeout: the robot does not answer.
        """
        started = time.perf_counter()
        self.arms.stand(self._world)
        rollout = plan(self._world, self.movement, theta)
        self.arms.claim(LEASE_OWNER, _LEASE_TTL, self._speed)
        try:
            play(self.arms, self._world, rollout)
        except Exception:
            self._reset()
            raise
        finally:
            self.arms.drop()
        return {"movement_s": time.perf_counter() - started}

    def _reset(self) -> None:
        """Best effort: the robot home with a fresh arrow (a lost robot is the caller's)."""
        node = self._node
        with contextlib.suppress(ArcheryError):
            node.call_typed(node.keys.archery_rpc(), rv.RESET, rv.ResetArgs())

    def close(self) -> None:
        """Drop the leases and stop following the arms."""
        self.arms.close()
