"""`archery selfcheck`: start a router and a sample service, and check the mesh end to end.

With `--echo`, run only the sample service (a torso controlboard that moves nothing, serving
the real controlboard verbs, and streams a joint state) until SIGINT/SIGTERM; tests use it as a
real process to kill. With `--body yarp`, check a YARP robot's body instead (body_check).
"""

from __future__ import annotations

import importlib.util
import statistics
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from typing import cast

import zenoh

from archery.apps.topics.body_check import add_body_args, check_body_flags, run_body_check
from archery.mesh.cliargs import ArgumentParser, seconds
from archery.mesh.netflags import NetConfig, add_network_args, open_session
from archery.mesh.node import Node
from archery.mesh.router import free_tcp_endpoint, open_router
from archery.mesh.signals import shutdown_on_signals
from archery.mesh.subscription import Subscription
from archery.protocol.codec import decode
from archery.protocol.errors import ArcheryError, BadRequest, RpcError
from archery.protocol.exit_status import BAD_INPUT, for_error
from archery.protocol.messages import Describe, JointCommand, JointState, WorldEvent
from archery.protocol.parts import PARTS
from archery.protocol.verbs import NoArgs, ServedVerbs
from archery.protocol.verbs import learner as learner_verbs
from archery.protocol.verbs import robot as rv

__all__ = ["ECHO_SERVICE", "main", "run_echo"]

ECHO_SERVICE = "echo"


def _torso_verbs(commands: Subscription[JointCommand]) -> ServedVerbs:
    """A torso controlboard that moves nothing: the real verb table, answered from fixed joint
    values; `positionMove` refuses a position list of the wrong length (an error reply),
    `counters` counts the commands received on `torso/command:i`, and it keeps no leases (the
    claim verbs answer `unknown_verb`, as a robot without them would)."""
    names = list(PARTS["torso"])
    zeros = [0.0] * len(names)
    speeds = [0.5] * len(names)
    targets = list(zeros)

    def set_speeds(a: rv.SetRefSpeedsArgs) -> rv.RefSpeedsReply:
        given = a.speeds if isinstance(a.speeds, list) else [a.speeds] * len(names)
        if len(given) != len(names):
            raise BadRequest(f"setRefSpeeds needs {len(names)} speeds, got {len(given)}")
        speeds[:] = given
        return rv.RefSpeedsReply(names=names, speeds=list(speeds))

    def move(a: rv.PositionMoveArgs) -> rv.TargetsReply:
        wanted = a.names or names
        if len(a.position) != len(wanted) or not set(wanted) <= set(names):
            raise BadRequest(
                f"positionMove needs one position per joint of {wanted}, got {len(a.position)}"
            )
        for name, value in zip(wanted, a.position, strict=True):
            targets[names.index(name)] = value
        return rv.TargetsReply(names=names, position=list(targets))

    def follow(a: rv.PartTrajectoryArgs) -> rv.TrajectoryReply:
        """The last waypoint becomes the targets at once (the sample torso has no time)."""
        move(rv.PositionMoveArgs(position=a.positions[-1], names=a.names))
        return rv.TrajectoryReply(
            parts=["torso"], started=0.0, ended=0.0, path_error=0.0, goal_error=0.0, actions={}
        )

    def no_leases(_: object) -> rv.LeaseReply:
        raise ArcheryError(
            "the sample torso keeps no leases: it takes commands from anyone", code="unknown_verb"
        )

    def counters(_: NoArgs) -> rv.CountersReply:
        return rv.CountersReply(
            accepted=commands.received,
            clamped=0,
            rejected=0,
            rejected_by_reason={},
            watchdog_trips=0,
            last_rejection="",
            streaming=False,
            undecodable=commands.dropped,
        )

    return rv.PART_VERBS.bind_names(
        {
            "getJointNames": lambda _: rv.JointNamesReply(names=names),
            "getLimits": lambda _: rv.LimitsReply(
                names=names, min=[-1.0] * len(names), max=[1.0] * len(names), tolerance=0.01
            ),
            "getPositions": lambda _: rv.PositionsReply(
                names=names, position=zeros, velocity=zeros, sim_time=0.0
            ),
            "getHistory": lambda _: rv.HistoryReply(names=names, times=[0.0], positions=[zeros]),
            "getTargets": lambda _: rv.TargetsReply(names=names, position=list(targets)),
            "checkMotionDone": lambda _: rv.MotionDoneReply(done=True),
            "setRefSpeeds": set_speeds,
            "getRefSpeeds": lambda _: rv.RefSpeedsReply(names=names, speeds=list(speeds)),
            "positionMove": move,
            "followTrajectory": follow,
            "counters": counters,
            "status": lambda _: rv.PartStatusReply(
                part="torso",
                names=names,
                motion_done=True,
                counters=counters(NoArgs()),
                position=list(targets),
                velocity=zeros,
                sim_time=0.0,
            ),
            "claim": no_leases,
            "renewClaim": no_leases,
            "dropClaim": no_leases,
            "getClaim": lambda _: rv.ClaimReply(held=False, owner="", ttl=0.0, expires_in=0.0),
        }
    )


def run_echo(net: NetConfig, stop: threading.Event, rate_hz: float = 50.0) -> None:
    """Serve the sample service until `stop` is set: a torso controlboard (`torso/rpc:i`, the
    real verbs, see `_torso_verbs`); `torso/state:o` at `rate_hz`; every command on
    `torso/command:i` is re-published as a `world/events:o` event (so tests can check lossless
    delivery)."""
    with Node(ECHO_SERVICE, net) as node:
        keys = node.keys
        events = node.publisher(keys.world_events(), WorldEvent, lossless=True)
        state = node.publisher(keys.state("torso"), JointState)
        received: list[int] = []

        def on_command(msg: JointCommand) -> None:
            received.append(msg.seq)
            events.put(WorldEvent(kind="nocked", shot=len(received)))

        commands = node.subscribe(
            keys.command("torso"), JointCommand, mode="fifo", callback=on_command
        )
        node.serve(keys.part_rpc("torso"), _torso_verbs(commands))
        node.ready()
        names = list(PARTS["torso"])
        period = 1.0 / rate_hz
        while not stop.wait(period):
            state.put(JointState(part="torso", names=names, position=[0.0] * 3, velocity=[0.0] * 3))


def _check(results: list[bool], label: str, func: Callable[[], str]) -> None:
    start = time.perf_counter()
    try:
        detail = func()
        ok = True
    except (ArcheryError, AssertionError) as exc:
        detail, ok = str(exc), False
    ms = (time.perf_counter() - start) * 1e3
    print(f"  {'ok  ' if ok else 'FAIL'} {label:<44} {ms:8.1f} ms  {detail}", flush=True)
    results.append(ok)


def _rendering() -> str:
    """The backend frames are rendered with here (`sim.gl_backend.check`), or why none."""
    if importlib.util.find_spec("mujoco") is None:
        return "skipped: MuJoCo is not installed here (archery[robot])"
    from archery.sim.gl_backend import check

    return f"{check()} (MuJoCo renders offscreen)"


def _selfcheck(net: NetConfig, timeout: float) -> bool:
    argv = [sys.executable, "-m", "archery.apps.cli", "selfcheck", "--echo", "--robot", net.robot]
    for endpoint in net.connect:
        argv += ["--connect", endpoint]
    child = subprocess.Popen(argv, stdin=subprocess.DEVNULL)
    results: list[bool] = []
    try:
        with Node(None, net) as node:
            keys = node.keys
            rpc = keys.part_rpc("torso")

            def alive() -> str:
                node.wait_alive([ECHO_SERVICE], timeout)
                return f"alive: {sorted(node.alive())}"

            def describe() -> str:
                replies = list(node.session.get(keys.describe(ECHO_SERVICE), timeout=timeout))
                ok = cast(zenoh.Sample, replies[0].ok)  # describe replies ok
                info = decode(ok.payload.to_bytes(), Describe)
                return f"{len(info.ports)} ports, pid {info.pid}"

            def stream() -> str:
                sub = node.subscribe(keys.state("torso"), JointState)
                msg = sub.wait_newer(timeout)
                return f"seq {msg.seq}, joints {', '.join(msg.names)}"

            def rpc_ok() -> str:
                times = []
                for _ in range(200):
                    t0 = time.perf_counter()
                    reply = node.call_typed(rpc, rv.GET_JOINT_NAMES, timeout=timeout)
                    times.append((time.perf_counter() - t0) * 1e3)
                    assert reply.names == list(PARTS["torso"])
                return f"200 round trips, median {statistics.median(times):.3f} ms"

            def rpc_error() -> str:
                try:
                    wrong = rv.PositionMoveArgs(position=[0.1])  # the torso has 3 joints
                    node.call_typed(rpc, rv.POSITION_MOVE, wrong, timeout=timeout)
                except RpcError as exc:
                    assert exc.code == "bad_request", exc.code
                    return f"error reply [{exc.code}]"
                raise AssertionError("an error reply was expected")

            def malformed() -> str:
                reply = node.request(
                    rpc, b"\xc1 not msgpack", verb="getJointNames", timeout=timeout
                )
                assert not reply.ok and reply.code == "bad_message", reply
                still = node.call_typed(rpc, rv.GET_JOINT_NAMES, timeout=timeout)
                assert still.names == list(PARTS["torso"])
                return f"rejected [{reply.code}], still serving"

            def missing() -> str:
                try:
                    node.call_typed(keys.learner_rpc(), learner_verbs.STATUS, timeout=1.0)
                except RpcError as exc:
                    return str(exc)[:60] + "…"
                raise AssertionError("a timeout was expected")

            def death() -> str:
                child.terminate()
                node.wait_gone(ECHO_SERVICE, timeout)
                return f"token gone, exit status {child.wait(timeout)}"

            print(f"mesh self-check on {', '.join(net.connect)} (robot {net.robot!r})")
            for label, func in (
                ("rendering backend starts", _rendering),
                ("service appears by liveliness", alive),
                ("describe lists its ports", describe),
                ("state stream (latest wins)", stream),
                ("rpc round trip", rpc_ok),
                ("rpc error reply with a code", rpc_error),
                ("malformed request gets an error reply", malformed),
                ("absent service fails with its key", missing),
                ("SIGTERM: clean exit, liveliness drops", death),
            ):
                _check(results, label, func)
    finally:
        if child.poll() is None:
            child.kill()
            child.wait()
    print(f"{sum(results)} passed, {len(results) - sum(results)} failed")
    return all(results)


def main(argv: list[str] | None = None) -> int:
    """Run the self-check (exit 0 when every check passes) or, with --echo, the sample service;
    with --body yarp, the body check of a YARP robot (exit 0, or 2 with one line of what is
    wrong)."""
    parser = ArgumentParser(prog="archery selfcheck", description=__doc__)
    add_network_args(parser)
    parser.add_argument("--echo", action="store_true", help="only run the sample service")
    parser.add_argument("--timeout", type=seconds, default=10.0, help="seconds per check")
    add_body_args(parser)
    args = parser.parse_args(argv)
    if args.body == "yarp":
        try:
            run_body_check(check_body_flags(args), args.timeout)
        except ArcheryError as exc:
            print(f"archery selfcheck: {exc}", file=sys.stderr)
            return BAD_INPUT
        return 0
    try:
        net = NetConfig.from_args(args)
    except ArcheryError as exc:
        print(f"archery selfcheck: {exc}", file=sys.stderr)
        return 2
    try:
        if args.echo:
            run_echo(net, shutdown_on_signals())
            return 0
        if args.connect:
            open_session(net).close()  # no router there: say so before starting anything
            return 0 if _selfcheck(net, args.timeout) else 1
    except ArcheryError as exc:
        print(f"archery selfcheck: {exc}", file=sys.stderr)
        return for_error(exc.code)
    endpoint = free_tcp_endpoint()
    with open_router(endpoint):
        net = NetConfig(connect=(endpoint,), robot=args.robot)
        ok = _selfcheck(net, args.timeout)
    return 0 if ok else 1
