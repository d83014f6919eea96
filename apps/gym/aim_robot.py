"""`archery/AimRobot-v0`: the MuJoCo iCub over a running mesh as a Gymnasium environment.

The details: `AimRobotEnv`'s docstring."""

from __future__ import annotations

import contextlib
import dataclasses
import os
import sys
import threading
from collections.abc import Sequence
from typing import Any

import gymnasium as gym
import numpy as np

from archery.apps.gym import keywords
from archery.apps.gym.aim import DEFAULT_BUDGET, episode_budget, session_of
from archery.apps.gym.registration import AIM_ROBOT_ID
from archery.apps.gym.robot_claim import claim_robot, robot_names
from archery.apps.gym.spaces import action_space, checked_action, observation, observation_space
from archery.apps.waits import waiting_for
from archery.mesh.netflags import DEFAULT_ROUTER, NetConfig
from archery.mesh.node import open_node
from archery.protocol.errors import ArcheryError, ConfigError, Unreachable
from archery.protocol.keys import DEFAULT_ROBOT
from archery.protocol.robotspec import HIT_RADIUS, THETA0
from archery.protocol.text import shown
from archery.protocol.vectors import finite_vector
from archery.services.learner.abort_policy import NO_ARROW, SERVICE_LOST
from archery.services.learner.errors import RigError, ServiceLost
from archery.services.learner.rig import SERVICES, MeshRig
from archery.services.learner.rollout_step import Failed, planar_distance, shoot
from archery.sim.geometry import TARGET_DIAMETER

__all__ = ["KEYWORDS", "AimRobotEnv", "RobotUnavailable", "ServiceLostError", "ShotNotMeasured"]


class RobotUnavailable(ConnectionError):
    """No router, or not the robot's stack, on the mesh within the environment's wait."""


class ServiceLostError(ConnectionError):
    """A service of the robot's stack was lost during a step (`service` names it)."""

    def __init__(self, message: str, service: str) -> None:
        super().__init__(message)
        self.service = service


class ShotNotMeasured(RuntimeError):
    """A shot that ended without a measurement for a reason other than a miss (`code`: the
    learner's abort code, e.g. `not_reached`, `no_target`)."""

    def __init__(self, message: str, code: str) -> None:
        super().__init__(message)
        self.code = code


#: Whether this process was forked from one in which an `AimRobotEnv` had opened a Zenoh
#: session: Zenoh's runtime does not survive `fork`, so a session opened here would hang.
_forked_after_zenoh = False
_zenoh_opened = False


def _after_fork_in_child() -> None:
    global _forked_after_zenoh
    _forked_after_zenoh = _forked_after_zenoh or _zenoh_opened


os.register_at_fork(after_in_child=_after_fork_in_child)


def _positive(name: str, value: object, unit: str) -> float:
    result = keywords.number(name, value, unit)
    if not result > 0:
        raise ValueError(f"{name} must be a number > 0 ({unit}), got {shown(value)}")
    return result


class AimRobotEnv(gym.Env[np.ndarray, np.ndarray]):
    """The iCub over the mesh: shoot θ (m), observe the detector's r (m).

    Raises:
        ValueError: a bad or unknown keyword, named (`protocol.errors.ConfigError` for a network
            setting), in at most `apps.gym.keywords.MESSAGE_LIMIT` characters.
        RobotUnavailable: no router or robot within `wait` s, or a router that refuses the
            session.

    One step is one shot through the rig the learner service uses (`services.learner.rig`: the
    controller's `posture` for θ, the robot's `nock` and `release`, the detector's `measure`; the
    steps of `services.learner.rollout_step.shoot`), so the observation's r is the detector's,
    never the robot's ground truth, which goes in `info` only (`r_true`). The action box is the
    controller's θ box, read from its `status` when the environment is made; the spaces are
    `apps.gym.spaces`'. The reward is −‖r‖ (m).

    Keywords:

    * `endpoint`: the router (default `tcp/127.0.0.1:7447`); `secure`: a deployment's folder
      (`archery keys init`) and `identity` (default `operator`);
    * `robot`: the prefix (default `icubSim`), or several, as a list or separated by commas (the
      `icubSim1` … of `archery up --robots N`): the environment drives the first one no other
      environment on this machine drives (`apps.gym.robot_claim`), so `make_vec(...,
      vectorization_mode="async", vector_kwargs={"context": "spawn"})` gives each process its own
      robot (Zenoh does not survive `fork`: the processes are spawned, and a forked one says so);
    * `start`: θ at the start (m; default the sessions' θ0); `budget`: shots per episode (default
      60); `until_hit`; `hit_radius` (m, default 5 cm: a measured ‖r‖ below it is a hit, as
      `archery learn` counts it);
    * `wait`: s to wait for the router, then as long for the robot's services (default 10);
      `rpc_timeout`: s per call (default 20);
    * `miss_distance`: m, the reward's distance for a shot whose arrow the detector does not see on
      the face (default the face's radius, 25 cm).

    `reset(seed=S)` moves the robot home and reseeds its shot noise with S (as `archery learn
    --seed S` does), after waiting up to `wait` s for every service to be alive. `info` after a
    step: `r` (m, measured; None when the detector saw no arrow), `distance` (m; `miss_distance`
    then), `hit`, `theta` (the θ sent, m), `theta_measured` (the θ the arrow was launched with,
    from the hands, m), `confidence` (the detection's: the lower of the target's and the arrow's),
    `clipped`, `shots`, `status` (`ok` or `no_arrow`), `robot`, and the robot's ground truth
    `r_true` (m, None if unknown).

    Errors: no router or no robot within `wait` s: the waiting line on stderr when the wait begins,
    then `RobotUnavailable` naming the endpoint and robot; a service lost during a step:
    `ServiceLostError` naming it (after `rpc_timeout` s), and the next `reset` works once it is
    back; a posture not reached or a frame without the target: `ShotNotMeasured` with the
    learner's abort code.
    """

    metadata: dict[str, Any] = {"render_modes": []}  # noqa: RUF012 (Gymnasium's class attribute)

    def __init__(
        self,
        *,
        endpoint: str = DEFAULT_ROUTER,
        robot: str | Sequence[str] = DEFAULT_ROBOT,
        secure: str | None = None,
        identity: str | None = None,
        start: Sequence[float] = THETA0,
        budget: int = DEFAULT_BUDGET,
        until_hit: bool = True,
        hit_radius: float = HIT_RADIUS,
        wait: float = 10.0,
        rpc_timeout: float = 20.0,
        miss_distance: float = TARGET_DIAMETER / 2,
        render_mode: str | None = None,
        **unknown: object,
    ) -> None:
        with keywords.keyword_errors():
            keywords.refuse_unknown(AIM_ROBOT_ID, unknown, KEYWORDS)
            if render_mode is not None:
                raise ValueError(f"{AIM_ROBOT_ID} renders nothing: render_mode must be None")
            self.budget = episode_budget(budget)
            self.until_hit = keywords.flag("until_hit", until_hit)
            self.hit_radius = _positive("hit_radius", hit_radius, "m")
            self.wait = _positive("wait", wait, "s")
            self.rpc_timeout = _positive("rpc_timeout", rpc_timeout, "s")
            self.miss_distance = _positive("miss_distance", miss_distance, "m")
            self._start = np.array(finite_vector("start", start, ValueError), dtype=np.float64)
            names = robot_names(robot)
            net = NetConfig(connect=(endpoint,), robot=names[0], secure=secure, identity=identity)
        if _forked_after_zenoh:
            raise RuntimeError(
                f"{AIM_ROBOT_ID} cannot join the mesh from a process forked after Zenoh ran in "
                "its parent (Zenoh does not survive fork); start the processes by spawning: "
                "make_vec(..., vectorization_mode='async', vector_kwargs={'context': 'spawn'})"
            )
        global _zenoh_opened
        _zenoh_opened = True
        self._claim = claim_robot(names)
        self.robot = self._claim.robot
        self._stack = contextlib.ExitStack()
        self._stack.callback(self._claim.release)
        net = dataclasses.replace(net, robot=self.robot)
        try:
            node = open_node(net.with_identity("operator"), self.wait, on_wait=self._on_wait)
            self._stack.callback(node.close)
            node.wait_alive(SERVICES, self.wait, on_wait=self._on_wait)
            self.rig = MeshRig(node, self.rpc_timeout)
            self._stack.callback(self.rig.close)
            # a whole-shot robot: every step is the controller's whole movement
            self.rig.follow_shot()
            self.bounds = self.rig.theta_box()
        except (ArcheryError, RigError) as exc:
            self._stack.close()
            if isinstance(exc, ConfigError) and not isinstance(exc, Unreachable):
                raise  # a bad setting (say, a deployment's missing file): bad input
            raise RobotUnavailable(
                f"{AIM_ROBOT_ID}: no robot {self.robot!r} ready at {endpoint} ({exc}); start "
                "one with `archery up`"
            ) from None
        except BaseException:
            self._stack.close()
            raise
        if not self.bounds.contains(self._start):
            self._stack.close()
            raise ValueError(f"{self.bounds.outside('start θ', self._start)} (the controller's)")
        self.action_space: gym.spaces.Box = action_space(self.bounds)
        self.observation_space: gym.spaces.Box = observation_space(self.bounds)
        self.render_mode = render_mode
        self._stop = threading.Event()
        self._shots = 0
        self._obs = observation(np.zeros(2), self._start)

    @staticmethod
    def _on_wait(what: str, limit: float) -> None:
        print(f"{AIM_ROBOT_ID}: {waiting_for(what, limit)}", file=sys.stderr, flush=True)

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """A new episode: every service alive (waiting up to `wait` s), the robot home, its
        shot noise seeded with `seed` (else a draw of the environment's generator). The one
        option, `{"session": K}` (an integer >= 0, as `Aim-v0` takes it), is checked and
        changes nothing here: the robot's noise follows `seed` alone.

        Raises:
            ValueError: options other than None or `{"session": K}`.
            ServiceLostError: a service is still missing after `wait` s, or lost in the reset.
        """
        session_of(keywords.reset_options(AIM_ROBOT_ID, options, ("session",)))  # checked only
        super().reset(seed=seed)
        robot_seed = int(seed) if seed is not None else int(self.np_random.integers(2**31))
        try:
            if self.rig.missing():
                self._on_wait(f"the services: {', '.join(self.rig.missing())}", self.wait)
            self.rig.wait_services(self.wait, self._stop)
            self.rig.reset(robot_seed)
        except ServiceLost as exc:
            raise ServiceLostError(
                f"{AIM_ROBOT_ID} reset: {exc.service} lost: {exc.message}", exc.service
            ) from None
        except RigError as exc:
            raise ShotNotMeasured(f"{AIM_ROBOT_ID} reset: {exc.message}", exc.code) from None
        self._shots = 0
        self._obs = observation(np.zeros(2), self._start)
        return self._obs.copy(), {"shots": 0, "theta": self._start.copy(), "robot": self.robot}

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """Shoot θ = `action` (m, clipped into the controller's box) on the robot.

        Raises:
            BadAction: the action holds a NaN or an infinity, or is not 3 numbers (Gymnasium's
                `InvalidAction`, a ValueError; nothing moves).
            ServiceLostError: a service was lost during the shot (named).
            ShotNotMeasured: the posture was not reached, or the detector saw no target.
        """
        theta, clipped = checked_action(action, self.action_space)
        result = shoot(self.rig, theta)
        if isinstance(result, Failed) and result.code != NO_ARROW:
            if result.code == SERVICE_LOST:
                service = result.cause.split(":", 1)[0]
                raise ServiceLostError(f"{AIM_ROBOT_ID} step: {result.cause}", service)
            raise ShotNotMeasured(
                f"{AIM_ROBOT_ID} step: {result.code}: {result.cause}", result.code
            )
        self._shots += 1
        info: dict[str, Any] = {"theta": theta.copy(), "clipped": clipped, "shots": self._shots}
        info["robot"] = self.robot
        if isinstance(result, Failed):  # no arrow on the face: nothing measured
            truth = result.truth_r_m if isinstance(result.truth_r_m, list) else None
            info |= {
                "r": None,
                "distance": self.miss_distance,
                "hit": False,
                "theta_measured": None,
                "confidence": 0.0,
                "status": NO_ARROW,
                "r_true": None if truth is None else np.array(truth),
            }
            self._obs = observation(self._obs[:2], theta)
        else:
            r = np.array(result.r_m, dtype=np.float64)
            distance = planar_distance(result.r_m)
            detection = result.measurement.detection
            launched = result.shot.theta_launched
            info |= {
                "r": r,
                "distance": distance,
                "hit": distance < self.hit_radius,
                "theta_measured": None if launched is None else np.array(launched),
                "confidence": float(
                    min(detection["target_confidence"], detection["arrow_confidence"])
                ),
                "status": "ok",
                "r_true": None if result.truth_r_m is None else np.array(result.truth_r_m),
            }
            self._obs = observation(r, theta)
        terminated = self.until_hit and bool(info["hit"])
        truncated = not terminated and self._shots >= self.budget
        return self._obs.copy(), -float(info["distance"]), terminated, truncated, info

    def close(self) -> None:
        """Leave the mesh and give the robot back."""
        self._stop.set()
        self._stack.close()
        super().close()


#: `AimRobotEnv`'s `make` keywords: its constructor's.
KEYWORDS = keywords.make_keywords(AimRobotEnv)
