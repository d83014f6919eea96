"""The controller's side of the robot's controlboards: joint states in, targets out, over the mesh.

`RobotLink.move` moves the parts under a lease each and waits until the whole robot rests at
the targets (its docstring tells a move step by step); `RobotLink.state` reads the
joint states and never hands out a stale one: a state that arrived more than `state_max_age`
wall seconds ago raises `StaleState` (code `stale_state`), which the RPC verbs reply as their
error (the robot is frozen or lost).
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from archery.mesh.node import Node
from archery.protocol.errors import ArcheryError, RpcError, RpcTimeout, StaleState
from archery.protocol.messages import JointCommand, JointState
from archery.protocol.parts import PARTS
from archery.protocol.robotspec import CONTROLLER, LEASE_TTL, LEASE_TTL_RANGE, STATE_MAX_AGE
from archery.protocol.verbs import robot as rv
from archery.protocol.verbs.robot import (
    CLAIM,
    DROP_CLAIM,
    GET_LIMITS,
    RENEW_CLAIM,
    SET_REF_SPEEDS,
    ClaimArgs,
    LeaseArgs,
    SetRefSpeedsArgs,
)
from archery.services.controller.cartesian import reference_speeds

__all__ = ["REST_WAIT", "MoveResult", "RobotLink"]

REST_WAIT = 1.0  # wall s a move waits for the robot to rest before it starts from its posture


def _at_rest(
    states: Mapping[str, JointState | None], goals: Mapping[str, np.ndarray], tol: float
) -> bool:
    """Every part's state shows motion done, all of one simulated time, each part of `goals`
    within `tol` rad of its targets: the whole robot at rest (there)."""
    if any(m is None or not m.motion_done for m in states.values()):
        return False
    if len({m.sim_time for m in states.values() if m is not None}) != 1:
        return False
    return all(
        np.max(np.abs(np.asarray(m.position) - goals[p])) <= tol
        for p, m in states.items()
        if m is not None and p in goals
    )


@dataclass(frozen=True)
class MoveResult:
    """How a move ended.

    Attributes:
        reached: every part reported motion done at its targets before the timeout.
        targets: the joint targets sent {joint: rad} (after clipping into the limits).
        measured: the latest measured posture {joint: rad} of every part.
        wall_s: wall time from sending the commands to the end of the wait (s).
        sim_time: the robot's simulated time (s) of the state that showed the move done (of
            the latest state when it was not).
        reason: why the move was not reached ("" when reached).
    """

    reached: bool
    targets: Mapping[str, float]
    measured: Mapping[str, float]
    wall_s: float
    sim_time: float
    reason: str


class RobotLink:
    """Joint states, commands and controlboard RPC of one robot, for the controller's threads.

    Args:
        node: the controller's node (subscriptions and publishers are declared here).
        robot_timeout: how long to wait for a joint state or an RPC reply (wall s).
        joint_tolerance: a part counts as there when motion is done and every joint is within
            this of its target (rad).
        state_max_age: a joint state that arrived longer ago than this (wall s) is stale.
        lease_ttl: the lease a move takes on each part it commands lasts this long unless
            renewed (wall s); renewed every quarter of it.
        owner: the name the leases are claimed under.
    """

    def __init__(
        self,
        node: Node,
        robot_timeout: float,
        joint_tolerance: float,
        state_max_age: float = STATE_MAX_AGE,
        lease_ttl: float = LEASE_TTL,
        owner: str = CONTROLLER,
    ) -> None:
        keys = node.keys
        self._node = node
        self._keys = keys
        self.robot_timeout = robot_timeout
        self.joint_tolerance = joint_tolerance
        self.state_max_age = state_max_age
        self.lease_ttl = lease_ttl
        self.owner = owner
        self.states = {p: node.subscribe(keys.state(p), JointState) for p in PARTS}
        self._commands = {p: node.publisher(keys.command(p), JointCommand) for p in PARTS}
        self._limits: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        self._lock = threading.Lock()
        self._drops = ThreadPoolExecutor(max_workers=1, thread_name_prefix="lease-drop")

    def state(self, part: str) -> JointState:
        """The newest joint state of `part` if fresh, else the next within `state_max_age`; the
        first state up to `robot_timeout`.

        A joint state that arrived more than `state_max_age` wall seconds ago (0.5 by default;
        its arrival age on this host, immune to clock differences between hosts) is never used:
        not as the measured posture, not as an IK seed, not for a motion-done check. Reading one
        waits at most `state_max_age` more for a newer state, then raises `StaleState`.

        Raises:
            StaleState: the newest state is stale and no newer one came (names key and age).
            RpcTimeout: no state ever arrived within `robot_timeout` s; the message names the key.
        """
        sub = self.states[part]
        if sub.latest() is not None:
            return sub.fresh(self.state_max_age, wait=self.state_max_age)
        try:
            return sub.wait_newer(self.robot_timeout)
        except RpcTimeout:
            raise RpcTimeout(
                f"the robot is not answering: no joint state on {sub.key} within "
                f"{self.robot_timeout:g} s; is `archery robot --robot {self._keys.robot}` running?"
            ) from None

    def joint_angles(self, parts: tuple[str, ...] = tuple(PARTS)) -> dict[str, float]:
        """The measured joint angles {joint: rad} of `parts` (fresh states, see `state`)."""
        out: dict[str, float] = {}
        for part in parts:
            msg = self.state(part)
            out.update(zip(msg.names, msg.position, strict=True))
        return out

    def rested_joints(self, wait: float) -> dict[str, float] | None:
        """The measured posture of every part once the whole robot rests: fresh states of one
        simulated time, each showing motion done (waiting up to `wait` s for them); None if it
        does not rest by then (a move then starts from the newest states, `posture`).

        A simulated robot that still settles (after a landing, say) steps on until it rests;
        a move started from a state before that would start at a simulated time, and from a
        posture, that depend on the wall clock."""
        deadline = time.monotonic() + wait
        while True:
            latest = {p: self.states[p].latest() for p in PARTS}
            fresh = all(self.states[p].age() <= self.state_max_age for p in PARTS)
            if fresh and _at_rest(latest, {}, self.joint_tolerance):
                return {
                    name: value
                    for m in latest.values()
                    if m is not None
                    for name, value in zip(m.names, m.position, strict=True)
                }
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return None
            # the first part not shown at rest (or not at the others' time): its next state
            part = next(
                (p for p, m in latest.items() if m is None or not m.motion_done), next(iter(PARTS))
            )
            mark = latest[part]
            try:
                self.states[part].wait_newer(
                    min(remaining, self.state_max_age), after_seq=mark.seq if mark else -1
                )
            except RpcTimeout:
                return None

    def fresh_joints(self) -> dict[str, float] | None:
        """The measured posture of every part if all their states are fresh (see
        `state_max_age`), else None."""
        out: dict[str, float] = {}
        try:
            for sub in self.states.values():
                msg = sub.fresh(self.state_max_age)
                out.update(zip(msg.names, msg.position, strict=True))
        except StaleState:
            return None
        return out

    def limits(self, part: str) -> tuple[np.ndarray, np.ndarray]:
        """(lower, upper) software limits of `part` (rad, YARP order), asked once per part."""
        with self._lock:
            if part not in self._limits:
                reply = self._node.call_typed(
                    self._keys.part_rpc(part), GET_LIMITS, timeout=self.robot_timeout
                )
                if list(reply.names) != list(PARTS[part]):
                    raise RpcError(
                        f"{self._keys.part_rpc(part)} getLimits names {reply.names} are not "
                        f"the {part} joints {list(PARTS[part])}"
                    )
                self._limits[part] = (np.asarray(reply.min), np.asarray(reply.max))
            return self._limits[part]

    def robot_status(self) -> rv.ArcheryStatusReply:
        """The robot's archery `status` (its scene's shot, its rtf)."""
        return self._node.call_typed(
            self._keys.archery_rpc(), rv.ARCHERY_STATUS, timeout=self.robot_timeout
        )

    def follow(
        self,
        parts: tuple[str, ...],
        times: np.ndarray,
        rows: np.ndarray,
        actions: Mapping[str, float],
        rtf: float,
    ) -> rv.TrajectoryReply:
        """Play one trajectory of `parts` (`rows`: their joints one part after the other, rad,
        at `times`, s of sim time from its start) with the archery `actions` {verb: s} on the
        robot's `archery/rpc:i followTrajectory`, under a lease of each part that lasts the
        movement in wall time (at the robot's `rtf`; 0: as fast as it runs) and `lease_ttl`
        more; the reply once it has ended. The leases are dropped after it.

        Raises:
            ArcheryError (code `not_owner`): another client holds a part. RpcError: the robot
                refused or aborted it (its code: `path_tolerance`, `grasp_missed`, …).
            RpcTimeout: no reply in time.
        """
        duration = float(times[-1])
        wall = duration / rtf if rtf > 0 else duration
        ttl = min(LEASE_TTL_RANGE[1], self.lease_ttl + wall)
        leases: dict[str, str] = {}
        try:
            for part in parts:
                leases[part] = self._claim(part, ttl)
            args = rv.TrajectoryArgs(
                parts=[rv.TrajectoryPart(part=p, lease=leases[p]) for p in parts],
                times=[float(t) for t in times],
                positions=rows.tolist(),
                actions=tuple(
                    rv.TrajectoryAction(t=at, verb=verb)  # type: ignore[arg-type]
                    for verb, at in actions.items()
                ),
            )
            return self._node.call_typed(
                self._keys.archery_rpc(),
                rv.FOLLOW_TRAJECTORY,
                args,
                timeout=self.robot_timeout + wall + args.goal_time / (rtf if rtf > 0 else 1.0),
            )
        finally:
            self._drop(leases)

    # -- leases -------------------------------------------------------------------------------
    def _claim(self, part: str, ttl: float, speeds: np.ndarray | None = None) -> str:
        """Claim `part` for this controller for `ttl` wall s, setting its reference speeds
        (rad/s) in the same round trip when given (`setRefSpeeds` with a claim, else `claim`);
        the lease id ("" from a robot that keeps no leases: it takes anyone's commands).

        Raises:
            ArcheryError (code `not_owner`): another client holds the part (a move drops the
                leases it took so far).
        """
        claim = ClaimArgs(owner=self.owner, ttl=ttl)
        key = self._keys.part_rpc(part)
        try:
            if speeds is None:
                return self._node.call_typed(key, CLAIM, claim, timeout=self.robot_timeout).lease
            args = SetRefSpeedsArgs(speeds=speeds.tolist(), claim=claim)
            reply = self._node.call_typed(key, SET_REF_SPEEDS, args, timeout=self.robot_timeout)
        except RpcError as exc:
            if exc.code == "not_owner":
                raise ArcheryError(f"cannot move {part}: {exc.message}", code="not_owner") from None
            raise
        return reply.lease

    def _renew(self, leases: dict[str, str]) -> str:
        """Renew the leases (a lease that ran out meanwhile is claimed again, unless another
        client took the part); "" if all are held, else why not. A renewal the robot does not
        answer in time is tried again at the next renewal (its state streams tell if it is
        lost)."""
        for part, lease in leases.items():
            if not lease:
                continue
            rpc = self._keys.part_rpc(part)
            try:
                self._node.call_typed(
                    rpc,
                    RENEW_CLAIM,
                    LeaseArgs(lease=lease),
                    timeout=self.robot_timeout,
                )
            except RpcTimeout:
                continue
            except RpcError as exc:
                if exc.code != "not_owner":
                    raise
                try:
                    reply = self._node.call_typed(
                        rpc,
                        CLAIM,
                        ClaimArgs(owner=self.owner, ttl=self.lease_ttl),
                        timeout=self.robot_timeout,
                    )
                except RpcError as again:
                    if again.code == "not_owner":
                        return f"{part} was taken over during the move: {again.message}"
                    raise
                leases[part] = reply.lease
        return ""

    def _drop(self, leases: dict[str, str]) -> None:
        """Drop the leases on the dropping thread, without waiting (best effort: one the robot
        does not drop runs out by itself, and this controller's next claim replaces its own):
        the posture's reply does not wait for three more round trips."""
        held = {part: lease for part, lease in leases.items() if lease}
        if held:
            self._drops.submit(self._drop_now, held)

    def _drop_now(self, leases: dict[str, str]) -> None:
        for part, lease in leases.items():
            with contextlib.suppress(RpcError):  # taken over, or the robot is gone
                self._node.call_typed(
                    self._keys.part_rpc(part),
                    DROP_CLAIM,
                    LeaseArgs(lease=lease),
                    timeout=self.robot_timeout,
                )

    def move(self, targets: Mapping[str, float], traj_time: float, timeout: float) -> MoveResult:
        """Move the joints named in `targets` {joint: rad}; only their parts are commanded, under
        a lease each.

        A move: start from the robot at rest (waiting up to `REST_WAIT` s for it), clip the
        targets into the robot's software limits (from each part's `getLimits`), claim each part
        it moves and set its reference speeds so every joint covers its distance in the
        trajectory time `traj_time`, in one round trip per part (`setRefSpeeds` with `claim` on
        `{part}/rpc:i`: a lease of `lease_ttl` wall s, so that the part obeys no other client
        during the move), publish one `JointCommand` per part back to back on `command:i` as
        one batch carrying its lease (the robot starts them at one simulated time), then wait
        until every part's `state:o` reports motion done, the moved ones within
        `joint_tolerance` of their targets, in states of one simulated time (the whole robot at
        rest: at rtf 0 the robot steps until then, and the next job, a nock or a release, must
        not land while it still settles), renewing the leases every quarter of their ttl, and
        drop the leases at the end (in the background: the posture's reply does not wait for
        it; a robot lost or frozen lets them run out by themselves).

        A part held by another client (the operator's takeover) fails the move at once with
        `not_owner` (the parts claimed before it are let go; their reference speeds stay set,
        nothing moved); one taken over during the move ends it unreached, naming the new owner;
        the part keeps the targets it was last given. A robot that keeps no leases (its
        `setRefSpeeds` returns no lease) is moved without them. A part whose state stream goes
        silent for longer than `state_max_age` raises `StaleState` at once instead of waiting
        for the timeout.

        Raises:
            RpcTimeout / RpcError: the robot's state or RPC does not answer (names the key).
            StaleState: a part's state stream went silent for longer than `state_max_age`.
            ArcheryError (code `not_owner`): another client holds a part to be moved.
        """
        parts = tuple(p for p in PARTS if any(j in targets for j in PARTS[p]))
        current = self.rested_joints(REST_WAIT) or self.joint_angles(tuple(PARTS))
        leases: dict[str, str] = {}
        try:
            result = self._move(targets, traj_time, timeout, parts, current, leases)
        except (StaleState, RpcTimeout):
            raise  # the robot is lost or frozen: its leases run out by themselves
        except BaseException:
            self._drop(leases)
            raise
        self._drop(leases)
        return result

    def _move(
        self,
        targets: Mapping[str, float],
        traj_time: float,
        timeout: float,
        parts: tuple[str, ...],
        current: Mapping[str, float],
        leases: dict[str, str],
    ) -> MoveResult:
        sent: dict[str, np.ndarray] = {}
        for part in parts:
            lower, upper = self.limits(part)
            wanted = np.array([targets.get(j, current[j]) for j in PARTS[part]])
            sent[part] = np.clip(wanted, lower, upper)
            delta = sent[part] - np.array([current[j] for j in PARTS[part]])
            leases[part] = self._claim(part, self.lease_ttl, reference_speeds(delta, traj_time))
        marks = {p: (s.seq if (s := self.states[p].latest()) else 0) for p in PARTS}
        # a simulated robot's states from before it took the commands show its old rest, which
        # may lie within the tolerance of targets a small step away: only states of a later
        # simulated time count (it steps at least once for any command; a real robot's states
        # carry no simulated time)
        before = max(
            (s.sim_time for p in PARTS if (s := self.states[p].latest()) and s.sim_time),
            default=None,
        )
        start = time.monotonic()
        for part in parts:
            self._commands[part].put(
                JointCommand(
                    part=part,
                    position=sent[part].tolist(),
                    batch=len(parts),
                    lease=leases[part],
                )
            )
        reason = ""
        tol = self.joint_tolerance
        done_at = 0.0  # sim s of the states that showed the robot there (load-independent)
        renew_every = self.lease_ttl / 4
        renew_at = time.monotonic() + renew_every
        while not reason:
            # every part, moved or not, at rest (the moved ones at their targets) ...
            for part in PARTS:
                goal = sent.get(part)

                def there(msg: JointState, goal: np.ndarray | None = goal) -> bool:
                    if before is not None and msg.sim_time is not None and msg.sim_time <= before:
                        return False
                    if goal is None:
                        return msg.motion_done
                    error = np.max(np.abs(np.asarray(msg.position) - goal))
                    return msg.motion_done and bool(error <= tol)

                while not reason:
                    now = time.monotonic()
                    remaining = max(0.0, start + timeout - now)
                    wait = (
                        min(remaining, max(0.0, renew_at - now))
                        if any(leases.values())
                        else remaining
                    )
                    try:
                        self.states[part].wait_newer(
                            wait, there, after_seq=marks[part], max_age=self.state_max_age
                        )
                        break
                    except RpcTimeout:
                        if time.monotonic() >= start + timeout:
                            reason = (
                                f"{self.states[part].key} did not show motion done within "
                                f"{tol:g} rad of the targets within {timeout:g} s"
                                if goal is not None
                                else f"{self.states[part].key} (not moved) did not come to "
                                f"rest within {timeout:g} s"
                            )
                        else:
                            reason = self._renew(leases)
                            renew_at = time.monotonic() + renew_every
            # ... in states of one simulated time: the whole robot at rest at once (a part
            # shown done before another settled may move again; at rtf 0 the robot steps on
            # until all rest, so a reply sooner would race its settling)
            if not reason:
                now_states = {p: self.states[p].latest() for p in PARTS}
                if _at_rest(now_states, sent, tol):
                    done_at = max((m.sim_time or 0.0) for m in now_states.values() if m)
                    break
                marks = {p: (m.seq if m is not None else 0) for p, m in now_states.items()}
        wall = time.monotonic() - start
        latest = {p: self.state(p) for p in PARTS}
        measured = {
            name: value
            for msg in latest.values()
            for name, value in zip(msg.names, msg.position, strict=True)
        }
        sim_time = done_at if not reason else max((m.sim_time or 0.0) for m in latest.values())
        return MoveResult(
            reached=not reason,
            targets={j: float(v) for p in parts for j, v in zip(PARTS[p], sent[p], strict=True)},
            measured=measured,
            wall_s=wall,
            sim_time=sim_time,
            reason=reason,
        )
