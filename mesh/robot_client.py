"""One client of one robot: every program and service that reads or moves the robot does so here.

`RobotClient(node)` names the robot's ports (`protocol/keys.py`) and calls its verbs through the
contract's tables (`protocol/verbs/robot.py`); nobody else takes a lease or names them, but the
robot itself and the tools whose job is the raw port. "Reached" means `TOLERANCES`
(`protocol/robotspec.py`). Every failure is a `RobotError` (`kind` not_owner, busy, not_reached
or lost) with the robot's own code and reason; a lease lost mid-move ends it with `not_owner`,
never a hang. Angles in rad, times in s (wall clock unless said otherwise).
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, Literal, TypeVar

import numpy as np

from archery.mesh.node import Node
from archery.mesh.publisher import Publisher
from archery.mesh.robot_leases import Claim
from archery.mesh.subscription import Subscription
from archery.protocol.errors import RobotError, RobotLost, RpcError, StaleState, UpstreamLost
from archery.protocol.messages import JointCommand, JointState
from archery.protocol.parts import PARTS
from archery.protocol.robotspec import (
    LEASE_TTL,
    LEASE_TTL_RANGE,
    ROBOT,
    ROBOT_TIMEOUT,
    STATE_MAX_AGE,
    TOLERANCES,
)
from archery.protocol.verbs import robot as rv
from archery.protocol.verbs.base import Args, Reply, Verb

__all__ = ["Moved", "RobotClient"]

R = TypeVar("R", bound=Reply)
Until = Literal["rest", "passing"]
#: the robot's codes a client meets as a `RobotError` of that kind
_KINDS = {"not_owner": "not_owner", "busy": "busy"}


@dataclass(frozen=True)
class Moved:
    """How a move ended: `reached` its `targets` {joint: rad}, the `measured` posture {joint: rad}
    at the end, `wall_s` from the commands to the end, the robot's `sim_time` (s) of the states
    that showed it there (the latest when not) and why not (`reason`, "" when reached)."""

    reached: bool
    targets: Mapping[str, float]
    measured: Mapping[str, float]
    wall_s: float
    sim_time: float
    reason: str


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
        float(np.max(np.abs(np.asarray(m.position) - goals[p]))) <= tol
        for p, m in states.items()
        if m is not None and p in goals
    )


def _posture_of(states: Iterable[JointState | None]) -> dict[str, float]:
    return {n: x for m in states if m for n, x in zip(m.names, m.position, strict=True)}


class RobotClient:
    """Reads and moves one robot over the mesh.

    Args:
        node: a node on the robot's mesh (its `keys` name the robot).
        timeout: the longest wait for a reply or a first joint state (wall s).
        reached: a joint within this of its target is there (rad); the table's by default.
        state_max_age: a joint state that arrived longer ago than this is stale (wall s).
        expect_service: accept replies only from the robot's live instance.
        lease_ttl: a move's leases last this long unless renewed (wall s).
    """

    def __init__(
        self,
        node: Node,
        *,
        timeout: float = ROBOT_TIMEOUT,
        reached: float = TOLERANCES["rest"],
        state_max_age: float = STATE_MAX_AGE,
        expect_service: bool = False,
        lease_ttl: float = LEASE_TTL,
    ) -> None:
        self.node, self.keys, self.lease_ttl = node, node.keys, lease_ttl
        self.timeout, self.reached, self.state_max_age = timeout, reached, state_max_age
        self._expect = ROBOT if expect_service else None
        self._states: dict[str, Subscription[JointState]] = {}
        self._commands: dict[str, Publisher[JointCommand]] = {}
        self._limits: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        self._lock = threading.Lock()
        self._drops = ThreadPoolExecutor(max_workers=1, thread_name_prefix="lease-drop")
        self._sent_at = -float("inf")

    def _call(self, key: str, verb: Verb[Any, R], args: Args | None, timeout: float | None) -> R:
        wait = self.timeout if timeout is None else timeout
        try:
            if args is None:
                return self.node.call_typed(key, verb, timeout=wait, expect_service=self._expect)
            return self.node.call_typed(key, verb, args, timeout=wait, expect_service=self._expect)
        except RobotError:
            raise
        except (TimeoutError, UpstreamLost) as exc:
            raise RobotLost(str(exc), code=getattr(exc, "code", "timeout")) from exc
        except RpcError as exc:
            if exc.code in _KINDS:
                raise RobotError(exc.message, kind=_KINDS[exc.code], code=exc.code) from exc
            raise

    def part_call(
        self, part: str, verb: Verb[Any, R], args: Args | None = None, timeout: float | None = None
    ) -> R:
        """A verb of `part`'s control board (`PART_VERBS`) and its typed reply."""
        return self._call(self.keys.part_rpc(part), verb, args, timeout)

    def call(self, verb: Verb[Any, R], args: Args | None = None, timeout: float | None = None) -> R:
        """An archery verb of the robot (`ARCHERY_VERBS`) and its typed reply."""
        return self._call(self.keys.archery_rpc(), verb, args, timeout)

    def status(self, timeout: float | None = None) -> rv.ArcheryStatusReply:
        """The robot's archery `status`: its scene, shot count, rtf, arrow."""
        return self.call(rv.ARCHERY_STATUS, timeout=timeout)

    def scene(self, timeout: float | None = None) -> rv.Scene:
        """The robot's scene as its status tells it (the contract's typed `Scene`)."""
        return self.status(timeout).scene

    def grasp(self) -> rv.GraspReply:
        return self.call(rv.GRASP)

    def nock(self, timeout: float | None = None) -> rv.NockReply:
        return self.call(rv.NOCK, timeout=timeout)

    def release(self, timeout: float | None = None) -> rv.ReleaseReply:
        """Let the arrow go; the reply once it has landed."""
        return self.call(rv.RELEASE, timeout=timeout)

    def reset(self, seed: int | None = None, timeout: float | None = None) -> rv.ResetReply:
        """Home posture at sim time 0, a fresh arrow; shot noise reseeded with `seed`."""
        args = rv.ResetArgs() if seed is None else rv.ResetArgs(seed=int(seed))
        return self.call(rv.RESET, args, timeout)

    def positions(self, part: str, timeout: float | None = None) -> np.ndarray:
        """`part`'s encoders now (rad, `getPositions`)."""
        return np.asarray(self.part_call(part, rv.GET_POSITIONS, timeout=timeout).position)

    def history(self, part: str, since: float, timeout: float | None = None) -> rv.HistoryReply:
        """`part`'s joint states since sim time `since` (s), at the robot's state rate."""
        return self.part_call(part, rv.GET_HISTORY, rv.HistoryArgs(since=since), timeout)

    def limits(self, part: str) -> tuple[np.ndarray, np.ndarray]:
        """(lower, upper) software limits of `part` (rad), asked once; RpcError if not `PARTS`'."""
        with self._lock:
            if part not in self._limits:
                reply = self.part_call(part, rv.GET_LIMITS)
                if list(reply.names) != list(PARTS[part]):
                    raise RpcError(
                        f"{self.keys.part_rpc(part)} getLimits names {reply.names} are not the "
                        f"{part} joints {list(PARTS[part])}"
                    )
                self._limits[part] = (np.asarray(reply.min), np.asarray(reply.max))
            return self._limits[part]

    def stream(self, part: str) -> Subscription[JointState]:
        """`part`'s joint-state subscription (declared at the first use)."""
        with self._lock:
            if part not in self._states:
                self._states[part] = self.node.subscribe(self.keys.state(part), JointState)
            return self._states[part]

    def follow_joints(self, part: str, call: Callable[[JointState], None]) -> Subscription[Any]:
        """Call `call` with each joint state of `part` (the caller closes the subscription)."""
        return self.node.subscribe(self.keys.state(part), JointState, callback=call)

    def joints(self, part: str) -> JointState:
        """The newest joint state of `part` if fresh, else the next within `state_max_age` (the
        first within `timeout`), never a stale one; else RobotLost (`timeout`, `stale_state`)."""
        sub = self.stream(part)
        try:
            if sub.latest() is not None:
                return sub.fresh(self.state_max_age, wait=self.state_max_age)
            return sub.wait_newer(self.timeout)
        except StaleState as exc:
            raise RobotLost(str(exc), code="stale_state") from None
        except TimeoutError:
            raise RobotLost(
                f"the robot is not answering: no joint state on {sub.key} within "
                f"{self.timeout:g} s; is `archery robot --robot {self.keys.robot}` running?"
            ) from None

    def posture(self, parts: Sequence[str] = tuple(PARTS)) -> dict[str, float]:
        """The measured joint angles {joint: rad} of `parts` (fresh states, see `joints`)."""
        out: dict[str, float] = {}
        for part in parts:
            msg = self.joints(part)
            out.update(zip(msg.names, msg.position, strict=True))
        return out

    def fresh_posture(self) -> dict[str, float] | None:
        """The measured posture of every part if all its states are fresh, else None."""
        with contextlib.suppress(RobotLost):
            if all(self.stream(p).age() <= self.state_max_age for p in PARTS):
                return self.posture()
        return None

    def rested(self, wait: float) -> dict[str, float] | None:
        """The measured posture once the whole robot rests (fresh states of one simulated time,
        each showing motion done), waiting up to `wait` s; None if it does not rest by then."""
        deadline = time.monotonic() + wait
        while True:
            latest = {p: self.stream(p).latest() for p in PARTS}
            fresh = all(self.stream(p).age() <= self.state_max_age for p in PARTS)
            if fresh and _at_rest(latest, {}, self.reached):
                return _posture_of(latest.values())
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return None
            part = next(
                (p for p, m in latest.items() if m is None or not m.motion_done), next(iter(PARTS))
            )
            mark = latest[part]
            try:
                self.stream(part).wait_newer(
                    min(remaining, self.state_max_age), after_seq=mark.seq if mark else -1
                )
            except TimeoutError:
                return None

    @contextlib.contextmanager
    def claim(
        self, parts: Sequence[str], owner: str, ttl: float = LEASE_TTL, speeds: float | None = None
    ) -> Iterator[Claim]:
        """Hold `parts` under `owner` (their reference `speeds` set, rad/s, when given) until the
        exit; RobotError `not_owner` (those taken so far dropped) when another holds a part."""
        held = Claim(self.part_call, self._drops, owner, ttl)
        try:
            for part in parts:
                held.take(part, speeds)
            yield held
        finally:
            held.drop()

    def command(self, part: str, position: Sequence[float], **fields: Any) -> None:
        """Publish one `JointCommand` of `part` (rad) on its `command:i` (the streamed path) with
        its other `fields` (`lease`, `batch`, `names`); no `position`: its publisher declared."""
        with self._lock:
            if part not in self._commands:
                self._commands[part] = self.node.publisher(self.keys.command(part), JointCommand)
            pub = self._commands[part]
        if len(position):
            pub.put(JointCommand(part=part, position=[float(x) for x in position], **fields))

    def move(
        self,
        targets: Mapping[str, float],
        *,
        until: Until = "rest",
        claim: Claim | None = None,
        owner: str = "",
        speeds: Mapping[str, np.ndarray] | None = None,
        timeout: float | None = None,
        pace: float = 0.0,
    ) -> Moved:
        """Move the joints of `targets` {joint: rad} (their parts' other joints kept where they
        are) as one batch the robot starts at one simulated time, under `claim`'s leases, else
        leases of `lease_ttl` taken under `owner` (`speeds` {part: rad/s} set in the same round
        trip), renewed while it waits and dropped after it without waiting. `until="rest"`: the
        whole robot rests, the moved joints within `reached`, in states of a later simulated time
        than the commands; `"passing"`: each moved joint within `TOLERANCES["passing"]`. `pace`:
        wall s at least between two moves' commands (a robot drops commands above its rate).

        Raises:
            RobotError: kind `not_owner` (a part held by another client at the start, or taken
                over meanwhile), `not_reached` (not there within `timeout`) or `lost` (a part's
                states went silent for `state_max_age`, or no reply); `moved` tells where a move
                taken over or not reached ended.
        """
        parts = tuple(p for p in PARTS if any(j in targets for j in PARTS[p]))
        own = claim is None
        held = claim or Claim(self.part_call, self._drops, owner, self.lease_ttl)
        try:
            return self._move(targets, parts, held, own, until, speeds, timeout, pace)
        except RobotLost:
            if own:  # the robot is lost or frozen: its leases run out by themselves
                held.leases.clear()
            raise
        finally:
            if own:
                held.drop(wait=False)

    def _move(
        self,
        targets: Mapping[str, float],
        parts: tuple[str, ...],
        held: Claim,
        own: bool,
        until: Until,
        speeds: Mapping[str, np.ndarray] | None,
        timeout: float | None,
        pace: float,
    ) -> Moved:
        wait_for = self.timeout if timeout is None else timeout
        streams = {p: self.stream(p) for p in PARTS}
        now = self.posture(parts) if any(j not in targets for p in parts for j in PARTS[p]) else {}
        sent = {p: np.array([targets.get(j, now.get(j, 0.0)) for j in PARTS[p]]) for p in parts}
        if own:
            for part in parts:
                held.take(part, None if speeds is None else speeds[part])
        marks = {p: (s.seq if (s := streams[p].latest()) else 0) for p in PARTS}
        # states from before the robot took the commands show its old rest, which may lie
        # within the tolerance of a small step: only a later simulated time counts
        before = max(
            (s.sim_time for p in PARTS if (s := streams[p].latest()) and s.sim_time), default=None
        )
        if pace and (rest := self._sent_at + pace - time.monotonic()) > 0:
            time.sleep(rest)
        start = self._sent_at = time.monotonic()
        for part in parts:
            self.command(
                part, sent[part].tolist(), lease=held.leases.get(part, ""), batch=len(parts)
            )
        tol = self.reached if until == "rest" else TOLERANCES["passing"]
        waited = tuple(PARTS) if until == "rest" else parts
        reason, done_at, kind = "", 0.0, "not_reached"
        while not reason:
            for part in waited:
                goal = sent.get(part)

                def there(msg: JointState, goal: np.ndarray | None = goal) -> bool:
                    if before is not None and msg.sim_time is not None and msg.sim_time <= before:
                        return False
                    if (
                        goal is not None
                        and float(np.max(np.abs(np.asarray(msg.position) - goal))) > tol
                    ):
                        return False
                    return until == "passing" or msg.motion_done

                while not reason:
                    remaining = max(0.0, start + wait_for - time.monotonic())
                    try:
                        streams[part].wait_newer(
                            min(remaining, held.renew_due() if held.leases else remaining),
                            there,
                            after_seq=marks[part],
                            max_age=self.state_max_age,
                        )
                        break
                    except StaleState as exc:
                        raise RobotLost(str(exc), code="stale_state") from None
                    except TimeoutError:
                        if time.monotonic() >= start + wait_for:
                            reason = (
                                f"{streams[part].key} did not show motion done within {tol:g} rad "
                                f"of the targets within {wait_for:g} s"
                                if goal is not None
                                else f"{streams[part].key} (not moved) did not come to rest "
                                f"within {wait_for:g} s"
                            )
                    except RobotError as exc:  # a part taken over: ends it, `moved` tells where
                        if exc.kind != "not_owner":
                            raise
                        reason, kind = exc.message, "not_owner"
            if reason or until == "passing":
                break
            now_states = {p: streams[p].latest() for p in PARTS}
            if _at_rest(now_states, sent, tol):  # the whole robot at rest at once
                done_at = max((m.sim_time or 0.0) for m in now_states.values() if m)
                break
            marks = {p: (m.seq if m is not None else 0) for p, m in now_states.items()}
        wall = time.monotonic() - start
        latest = {p: self.joints(p) for p in PARTS}
        moved = Moved(
            reached=not reason,
            targets={j: float(v) for p in parts for j, v in zip(PARTS[p], sent[p], strict=True)},
            measured=_posture_of(latest.values()),
            wall_s=wall,
            sim_time=done_at if done_at else max((m.sim_time or 0.0) for m in latest.values()),
            reason=reason,
        )
        if reason:
            raise RobotError(reason, kind=kind, moved=moved)
        return moved

    def follow(
        self,
        parts: Sequence[str],
        times: np.ndarray,
        rows: np.ndarray,
        actions: Mapping[str, float],
        *,
        owner: str,
        rtf: float,
        ttl: float = LEASE_TTL,
        timeout: float | None = None,
    ) -> rv.TrajectoryReply:
        """Play one trajectory of `parts` (`rows`: their joints one part after the other, rad, at
        `times`, s of sim time from its start) with the archery `actions` {verb: s} in the
        robot's own loop (`followTrajectory`), under leases that last the movement in wall time
        (at the robot's `rtf`; 0: as fast as it runs) and `ttl` more; the reply once it ended.
        RobotError: a part held by another (`not_owner`); the robot refused or aborted it (its
        code: `path_tolerance`, `grasp_missed`, …)."""
        duration = float(times[-1])
        wall = duration / rtf if rtf > 0 else duration
        held = Claim(self.part_call, self._drops, owner, min(LEASE_TTL_RANGE[1], ttl + wall))
        try:  # the leases dropped without waiting: the reply does not wait for three round trips
            for part in parts:
                held.take(part)
            args = rv.TrajectoryArgs(
                parts=[rv.TrajectoryPart(part=p, lease=held.leases[p]) for p in parts],
                times=[float(t) for t in times],
                positions=np.asarray(rows).tolist(),
                actions=tuple(rv.TrajectoryAction(t=at, verb=verb) for verb, at in actions.items()),  # type: ignore[arg-type]
            )
            base = self.timeout if timeout is None else timeout
            wait = base + wall + args.goal_time / (rtf if rtf > 0 else 1.0)
            return self.call(rv.FOLLOW_TRAJECTORY, args, wait)
        finally:
            held.drop(wait=False)

    def close(self) -> None:
        """Stop following the joint states, the leases' drops ended first (within `timeout`)."""
        with self._lock:
            states, self._states = self._states, {}
        for sub in states.values():
            self.node.unsubscribe(sub)
            sub.close()
        with contextlib.suppress(TimeoutError, RuntimeError):  # RuntimeError: closed already
            self._drops.submit(int).result(self.timeout)  # after the drops queued before it
        self._drops.shutdown(wait=False)
