"""The other services as one session sees them, over the mesh: the session's `Rig` on a Node.

`MeshRig` makes the calls of a rollout (ARCHITECTURE.md, 'The life of one rollout'), every one
typed (`protocol.verbs`), and maps what goes wrong to `ServiceLost` (a service, or the service
it calls, is lost) or `RigError` (`MeshRig._call` says which). Each reply belongs to its own
Zenoh query: a reply that comes after its call gave up is dropped, never handed to a later
call. Liveliness is watched all along, so `lost_ago` tells how long ago a service vanished.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from typing import Any, Literal, TypeVar

import msgspec
import numpy as np

from archery.mesh.node import Node
from archery.mesh.robot_client import RobotClient
from archery.mesh.tokens import TokenSet
from archery.protocol.errors import (
    ArcheryError,
    OperatorNeeded,
    PartLost,
    RpcError,
    RpcTimeout,
    StaleState,
    UpstreamLost,
    WrongReplier,
)
from archery.protocol.messages import WorldEvent
from archery.protocol.robotspec import CAMERA, CONTROLLER, DETECTOR, ROBOT
from archery.protocol.theta import ThetaBox
from archery.protocol.verbs import Verb
from archery.protocol.verbs import controller as cv
from archery.protocol.verbs import detector as dv
from archery.protocol.verbs import robot as rv
from archery.services.learner.errors import RigError, ServiceLost
from archery.services.learner.operator_desk import OPERATOR_LIMIT, OperatorDesk
from archery.services.learner.rig_protocol import Measurement, PostureResult, Shot

__all__ = ["SERVICES", "UPSTREAM", "MeshRig"]

SERVICES = (ROBOT, CAMERA, DETECTOR, CONTROLLER)  # the services a session needs
#: The service each service calls to do its work: its `timeout` error means that one is lost.
UPSTREAM = {DETECTOR: CAMERA, CONTROLLER: ROBOT}
#: Error codes that mean the upstream service is lost: its call timed out, its state stream is
#: stale (a robot frozen mid-motion is as lost as a dead one), or a part of a YARP robot is gone.
_UPSTREAM_CODES = (RpcTimeout.code, StaleState.code, PartLost.code)
log = logging.getLogger("archery.learner")
_TRUTH_KEPT = 256  # shots whose ground truth is remembered
_ASKS = 3  # times a verb may ask for the operator's hand in a row
R = TypeVar("R", bound=msgspec.Struct)
T = TypeVar("T")


class MeshRig:
    """The robot, camera, detector and controller over `node`'s session.

    Calls, in a rollout's order (ROBOT = the robot prefix):

    * `ROBOT/cartesianController/archery/rpc:i posture {theta, shot}` (and `status` for the θ
      box; on a whole-shot robot the controller plays the whole movement, its nock included);
    * `ROBOT/archery/rpc:i status` (the robot's shot), `nock` (posture shot), then `release`
      (replies once the arrow has landed), `reset {seed}`, through the one `RobotClient`;
    * `ROBOT/detector/rpc:i measure` for a frame newer than the landing, and `frame {overlay}`
      for the picture of a hit with the detection drawn on it; on a robot that does not see
      the arrow land (its status: `world.landing` "camera"), `baseline` before the release and
      `measure {baseline}`, which waits for the new arrow and a still picture;
    * a verb the robot answers `operator_needed` (a real robot's nock by hand) is the
      operator's: asked on the `desk` and waited for until confirmed (`OperatorDesk.ask`);
    * `ROBOT/world/events:o` is read for the ground-truth impact, which goes to the log only.

    Args:
        node: the learner's node.
        timeout: longest wait for a reply (wall s).
    """

    services: tuple[str, ...] = SERVICES

    def __init__(self, node: Node, timeout: float = 20.0) -> None:
        self.node = node
        self.keys = node.keys
        self.timeout = timeout
        self.robot = RobotClient(node, timeout=timeout, expect_service=True)
        self._truth: OrderedDict[int, tuple[float, WorldEvent]] = OrderedDict()
        self._truth_cond = threading.Condition()
        node.subscribe(self.keys.world_events(), WorldEvent, mode="fifo", callback=self._on_event)
        # Who is alive and since when one went, kept from liveliness events: a query per check
        # would time out on a loaded machine and report every service missing.
        self._tokens = TokenSet(node.session, self.keys.alive_all())
        #: The robot's shot, which every posture asks the controller for (`follow_shot`)
        self.shot: Literal["posture", "whole"] = "posture"
        self._rtf = 0.0  # the robot's real-time factor (its `status`)
        #: who tells the landing: the robot ("events": its release replies once landed) or the
        #: camera (the detector, from frames: a robot that does not see the arrow)
        self.landing = "events"
        self.desk = OperatorDesk(OPERATOR_LIMIT)  # the learner's own, where it has one
        #: the running session's stop, which ends a wait for the operator
        self.stop = threading.Event()

    def _on_event(self, event: WorldEvent) -> None:
        if event.kind not in ("landed", "missed"):
            return
        with self._truth_cond:
            self._truth[event.shot] = (time.time(), event)
            self._truth.move_to_end(event.shot)
            while len(self._truth) > _TRUTH_KEPT:
                self._truth.popitem(last=False)
            self._truth_cond.notify_all()

    def _call(
        self,
        service: str,
        key: str,
        verb: Verb[Any, R],
        args: msgspec.Struct | None = None,
        timeout: float | None = None,
    ) -> tuple[R, float]:
        """(typed reply, wall s) of one call; ServiceLost or RigError when it fails.

        A call that gets no reply becomes `ServiceLost` naming the service; an error reply, or a
        reply that does not match its type, `RigError` with the service's code (`bad_reply`)
        and message; a reply from any session but the service's live instance `RigError` with
        code `wrong_replier` (`Node.call_typed(expect_service=...)`).

        A service that replies it could not do its work because a service it calls is lost is
        not an error of its own: `upstream_lost` (the detector when the camera does not answer)
        becomes `ServiceLost` naming the upstream service, and so does a `timeout` error reply
        (the service's own call timed out: the controller's robot, the detector's camera;
        `UPSTREAM`), a `stale_state` reply (the controller's robot states stopped: the robot is
        frozen or lost), or any error reply while some service is not alive (that one is
        named; `_lost_behind`).
        """
        return self._timed(
            service,
            lambda: self.node.call_typed(
                key,
                verb,
                args,
                timeout=self.timeout if timeout is None else timeout,
                expect_service=service,
            ),
        )

    def _timed(self, service: str, work: Callable[[], T]) -> tuple[T, float]:
        """(`work()`, wall s), its errors mapped as `_call` says (the robot's calls: its client's
        `RobotLost` is an `RpcTimeout`, so `ServiceLost`)."""
        start = time.perf_counter()
        result = self._mapped(service, work)
        return result, time.perf_counter() - start

    def _mapped(self, service: str, work: Callable[[], T]) -> T:
        """`work()`, its errors mapped as `_call` says, `service` the one it talks to."""
        try:
            return work()
        except RpcTimeout as exc:
            raise ServiceLost(service, exc.message) from None
        except UpstreamLost as exc:
            raise ServiceLost(exc.service, exc.message) from None
        except RpcError as exc:
            lost = self._lost_behind(service, exc)
            if lost is not None:
                raise ServiceLost(lost, exc.message) from None
            raise RigError(exc.message, code=exc.code) from None
        except ArcheryError as exc:  # a movement's own errors (θ out of reach, no robot)
            raise RigError(exc.message, code=exc.code) from None

    def _lost_behind(self, service: str, exc: RpcError) -> str | None:
        """The lost service behind `service`'s error reply `exc`, if any: a service not alive
        now, else (for its `timeout` code) the service it calls."""
        if exc.code == WrongReplier.code:
            return None
        missing = self.missing()
        if missing:
            return ", ".join(missing)
        return UPSTREAM.get(service) if exc.code in _UPSTREAM_CODES else None

    # -- liveliness -----------------------------------------------------------------------------
    def close(self) -> None:
        """Stop following the liveliness tokens (the rest goes with the node's session)."""
        self._tokens.close()

    def missing(self) -> list[str]:
        """Services whose liveliness token is down now."""
        return sorted(set(self.services) - self._tokens.present())

    def lost_ago(self, service: str) -> float | None:
        """Seconds since `service`'s liveliness token went (None: not seen going)."""
        return self._tokens.gone_for(service)

    def wait_services(self, timeout: float, stop: threading.Event) -> bool:
        """Wait until every service is alive (True) or `stop` is set (False).

        Raises:
            ServiceLost: some are still missing after `timeout` s.
        """
        deadline = time.monotonic() + timeout
        wanted = set(self.services)
        while not stop.is_set():
            if self._tokens.wait_for(wanted.issubset, timeout=min(1.0, timeout)):
                return True
            if time.monotonic() > deadline:
                missing = self.missing()
                raise ServiceLost(
                    ", ".join(missing) or "?",
                    f"{', '.join(missing)} still not alive after {timeout:g} s "
                    f"(robot {self.keys.robot!r}); restart them and resume the session",
                )
        return False

    # -- the shot ------------------------------------------------------------------------------
    def follow_shot(self) -> str:
        """Learn the robot's shot (its `status`), which every posture asks for: on a `--shot
        whole` robot the controller plays the whole movement towards the posture for θ. The
        robot's shot: posture or whole.

        Raises:
            ServiceLost, RigError: the robot does not answer.
        """
        status, _ = self._timed("robot", self.robot.status)
        if status.scene.shot == "whole" and self.shot != "whole":
            log.info("the robot runs the whole shot: the controller plays it in every rollout")
        self.shot = status.scene.shot
        self._rtf = status.rtf
        self.landing = "camera" if status.world.get("landing") == "camera" else "events"
        return self.shot

    # -- the rollout ----------------------------------------------------------------------------
    def theta_box(self) -> ThetaBox:
        """The controller's θ box (m), from its `status` (checked as the reply is decoded: a
        status without a valid box is `RigError` with code `bad_reply`)."""
        key = self.keys.cartesian_rpc("archery")
        status, _ = self._call("controller", key, cv.STATUS)
        return status.theta_box

    def setup(self) -> dict[str, Any]:
        """What replaying a shot needs of the rig: the robot's world (`WorldConfig.to_dict`),
        its shot count before the session and the controller's trajectory time (s)."""
        robot, _ = self._timed("robot", self.robot.status)
        key = self.keys.cartesian_rpc("archery")
        controller, _ = self._call("controller", key, cv.STATUS)
        return {"world": robot.world, "shot": robot.shot, "traj_time": controller.traj_time}

    def reset(self, seed: int) -> None:
        """Robot to the home posture, shot noise reseeded with `seed` (the operator's, where
        the robot cannot: `_by_hand`)."""
        self._by_hand("reset", lambda: self.robot.reset(int(seed)))

    def _by_hand(self, verb: str, work: Callable[[], T]) -> tuple[T, float]:
        """(`work()`, wall s); where the robot answers that the operator's hand is needed
        first (`operator_needed`), the operator is asked, waited for, and `work` called again
        (the robot then does its part: a posture, or nothing), at most `_ASKS` times.

        Raises:
            OperatorAbsent: no confirmation within the desk's limit, or the session stopped.
            RigError: the robot still asks after `_ASKS` confirmations.
        """
        for _ in range(_ASKS):
            try:
                return self._timed("robot", work)
            except RigError as exc:
                if exc.code != OperatorNeeded.code:
                    raise
                self.desk.ask(verb, exc.message, self.stop)
        raise RigError(
            f"the robot asked the operator for its {verb} {_ASKS} times", code="bad_state"
        )

    def move_to(self, theta: np.ndarray) -> PostureResult:
        """The archery posture for θ (m), once the robot reports the motion done; on a
        whole-shot robot (`shot`) at the end of the whole movement towards it (reach, grasp,
        carry, nock, draw), which the controller plays; its reply waits for the movement too
        (at most `MAX_TRAJECTORY_DURATION` s of simulated time at the robot's rtf). A whole
        movement that fails leaves the robot reset (`_reset_after_failure`), so the next
        attempt starts clean."""
        key = self.keys.cartesian_rpc("archery")
        args = cv.PostureArgs(theta=theta.tolist(), shot=self.shot)
        timeout = self.timeout
        if self.shot == "whole":
            timeout += rv.MAX_TRAJECTORY_DURATION / (self._rtf if self._rtf > 0 else 1.0)
        try:
            result, wall = self._call("controller", key, cv.POSTURE, args, timeout=timeout)
        except RigError:
            if self.shot == "whole":  # the next movement grasps the holder's next arrow
                self._reset_after_failure()
            raise
        movement = (
            {"movement_sim_s": result.movement_sim_s, "lead_sim_s": result.lead_sim_s}
            if self.shot == "whole"
            else {}
        )
        return PostureResult(
            reached=result.reached,
            reason=result.reason,
            theta_measured=result.theta_measured,
            timing=movement
            | {
                "posture_s": wall,
                "move_s": result.wall_s,
                "ik_and_transport_s": wall - result.wall_s,
            },
        )

    def _reset_after_failure(self) -> None:
        """Best effort after a whole movement that failed (a grasp or nock missed, a part that
        fell behind): the robot home with a fresh arrow in the holder, its shot noise going on
        (a lost robot is the caller's)."""
        with contextlib.suppress(ArcheryError):
            self.robot.reset()

    def shoot(self) -> Shot:
        """Nock (the whole shot's movement nocked already) and release; returns when the arrow
        has landed, with the θ it was launched with (the release reply's)."""
        before = time.time()
        timing = {}
        if self.shot != "whole":
            _, timing["nock_s"] = self._by_hand("nock", self.robot.nock)
        baseline = None
        if self.landing == "camera":  # the scene before the release, the new arrow's reference
            args = dv.BaselineArgs(timeout=max(0.5, self.timeout - 2.0))
            taken, timing["baseline_s"] = self._call(
                "detector", self.keys.detector_rpc(), dv.BASELINE, args
            )
            baseline, before = taken.baseline, time.time()
        result, release = self._timed("robot", self.robot.release)
        return Shot(
            shot=result.shot,
            sim_time=result.sim_time,
            stamp=before,
            outcome=result.outcome,
            timing=timing | {"release_s": release, "flight_sim_s": result.flight_time},
            theta_launched=result.theta,
            baseline=baseline,
        )

    def measure(self, shot: Shot) -> Measurement:
        """The detector's measurement of a frame rendered at or after the landing and captured
        after the nock (so never a frame from before a reset or of an earlier arrow)."""
        key = self.keys.detector_rpc()
        args = dv.MeasureArgs(
            after_sim_time=None if shot.baseline is not None else shot.sim_time,
            after_stamp=shot.stamp,
            timeout=max(0.5, self.timeout - 2.0),  # the detector answers before we give up
            baseline=shot.baseline,
        )
        result, wall = self._call("detector", key, dv.MEASURE, args)
        if result.status == "ok" and result.r_m is None:
            raise RigError(f"{key} measure replied ok without r_m", code="bad_reply")
        timing = {"measure_s": wall} | {f"detector_{k}": v for k, v in result.timing.items()}
        r = result.r_m if result.status == "ok" else None
        return Measurement(result.status, r, msgspec.to_builtins(result), timing)

    def truth(self, shot: Shot) -> list[float] | None:
        """The robot's true r (m) of `shot` (waits up to 1 s for its event; None if none): only
        an event received after the shot's nock, so a restarted robot's shot numbers never pick
        up an old event of an earlier instance's shot of the same number."""

        if shot.baseline is not None:  # the robot does not see its arrows: no truth to wait for
            return None

        def event() -> WorldEvent | None:
            received, found = self._truth.get(shot.shot, (0.0, None))
            return found if received >= shot.stamp else None

        with self._truth_cond:
            self._truth_cond.wait_for(lambda: event() is not None, timeout=1.0)
            found = event()
        return None if found is None or found.impact_m is None else list(found.impact_m)

    def hit_frame(self, shot: Shot, measurement: Measurement) -> bytes | None:
        """The frame `measurement` measured, with its overlay (PNG): one of the detector's last
        `KEPT_FRAMES` measurements (by its seq; the last one when the reply names none)."""
        key = self.keys.detector_rpc()
        seq = measurement.detection.get("seq")
        args = dv.FrameArgs(seq=seq if isinstance(seq, int) and seq >= 1 else None)
        result, _ = self._call("detector", key, dv.FRAME, args)
        png = result.png
        if not png.startswith(b"\x89PNG"):
            log.warning("the detector's frame reply holds no PNG")
            return None
        return png
