"""The node base over a real router: pub/sub, RPC, liveliness, describe, bad payloads."""

from __future__ import annotations

import functools
import logging
import subprocess
import sys
import threading
import time
from collections.abc import Iterator

import pytest
import zenoh

from archery.apps.topics.selfcheck import ECHO_SERVICE
from archery.mesh.instances import describe_all
from archery.mesh.netflags import NetConfig
from archery.mesh.node import Node
from archery.mesh.router import free_tcp_endpoint, spawn_router
from archery.protocol.errors import BadRequest, RpcError, RpcTimeout
from archery.protocol.messages import JointState, WorldEvent
from archery.protocol.verbs import Args, NoArgs, Reply, Verb, VerbTable
from archery.protocol.verbs.robot import PART_VERBS
from tests.rpc import rpc_call, some_verbs


class SpeedArgs(Args, frozen=True):
    speed: float


class SpeedReply(Reply, frozen=True):
    speed: float


# A test's own verbs, served on the archery port's key.
TEST_VERBS = VerbTable(
    "test",
    ("archery/rpc:i",),
    (
        Verb("release", SpeedArgs, SpeedReply, "twice the speed; refuses 0"),
        Verb("crash", NoArgs, SpeedReply, "raises a ZeroDivisionError"),
        Verb("measure", NoArgs, SpeedReply, "waits for a gate"),
    ),
)


def _state(i: int) -> JointState:
    return JointState(part="torso", names=["a"], position=[float(i)], velocity=[0.0])


@pytest.fixture
def pair(net: NetConfig) -> Iterator[tuple[Node, Node]]:
    with Node("server", net) as server, Node(None, net) as client:
        yield server, client


def test_latest_wins_stream(pair: tuple[Node, Node]) -> None:
    server, client = pair
    key = server.keys.state("torso")
    pub = server.publisher(key, JointState)
    sub = client.subscribe(key, JointState)
    assert pub.wait_matched(5)
    for i in range(1, 51):
        pub.put(_state(i))
    last = sub.wait_newer(5, predicate=lambda m: m.seq == 50, after_seq=0)
    assert last.position == [50.0] and sub.latest() == last
    assert last.stamp > 0 and sub.age() < 5


def test_a_stamped_message_counts_but_is_not_sent(pair: tuple[Node, Node]) -> None:
    # what the camera does with a frame no subscriber wants: stamped and counted, never sent
    server, client = pair
    key = server.keys.state("torso")
    pub = server.publisher(key, JointState)
    sub = client.subscribe(key, JointState, mode="fifo")
    assert pub.wait_matched(5)
    kept = pub.stamp(_state(1))
    assert kept.seq == 1 and kept.stamp > 0 and pub.count == 1
    sent = pub.put(_state(2))
    assert sent.seq == 2 and sub.get(timeout=5) == sent  # in order: the stamped one never came
    with pytest.raises(TypeError, match="carries JointState, got WorldEvent"):
        pub.stamp(WorldEvent(kind="reset", shot=0, sim_time=0.0))
    assert pub.count == 2
    # what it does with a frame a grab waits for: stamped and stored first, sent after as it is
    later = pub.stamp(_state(3))
    pub.send(later)
    assert sub.get(timeout=5) == later and pub.count == 3


def test_events_are_lossless_and_ordered(pair: tuple[Node, Node]) -> None:
    server, client = pair
    key = server.keys.world_events()
    pub = server.publisher(key, WorldEvent, lossless=True)
    sub = client.subscribe(key, WorldEvent, mode="fifo")
    assert pub.wait_matched(5)
    for i in range(500):
        pub.put(WorldEvent(kind="released", shot=i))
    shots = [sub.get(timeout=5).shot for _ in range(500)]
    assert shots == list(range(500))
    with pytest.raises(RpcTimeout, match="no message on"):
        sub.get(timeout=0.05)


def test_malformed_stream_payloads_are_counted_and_dropped(pair: tuple[Node, Node]) -> None:
    server, client = pair
    key = server.keys.state("torso")
    sub = client.subscribe(key, JointState)
    pub = server.publisher(key, JointState)
    assert pub.wait_matched(5)
    for garbage in (b"\xc1", b"not msgpack at all", b"\x81\xa4type\xa5Image"):
        server.session.put(key, garbage)
    pub.put(_state(7))
    msg = sub.wait_newer(5, after_seq=0)
    assert msg.position == [7.0]
    assert sub.dropped == 3 and sub.received == 1
    assert "JointState" in sub.last_error or "msgpack" in sub.last_error


def test_rpc_ok_error_and_recovery(pair: tuple[Node, Node]) -> None:
    server, client = pair
    key = server.keys.archery_rpc()

    def release(args: SpeedArgs) -> SpeedReply:
        if args.speed == 0:
            raise BadRequest("release needs a speed above 0 (m/s)")
        return SpeedReply(speed=args.speed * 2)

    def crash(args: NoArgs) -> SpeedReply:
        raise ZeroDivisionError("division by zero")

    verbs = {"release": release, "crash": crash, "measure": crash}
    server.serve(key, TEST_VERBS.bind_names(verbs))
    server.ready()
    client.wait_alive(["server"], 10)
    call = functools.partial(rpc_call, client, key)
    assert call("release", {"speed": 2.5}) == {"speed": 5.0}
    with pytest.raises(RpcError, match="needs a speed above 0") as err:
        call("release", {"speed": 0})
    assert err.value.code == "bad_request"
    with pytest.raises(RpcError, match="missing required field `speed`") as err:
        call("release")
    assert err.value.code == "bad_request"
    with pytest.raises(RpcError, match="no verb 'fly'; verbs: crash, measure, release") as err:
        call("fly")
    assert err.value.code == "unknown_verb"
    with pytest.raises(RpcError, match="ZeroDivisionError") as err:
        call("crash")
    assert err.value.code == "internal"
    for garbage in (b"", b"\xc1", b"\x93\x01\x02\x03"):
        reply = client.request(key, garbage, verb="release")
        assert not reply.ok and reply.code == "bad_message"
    assert call("release", {"speed": 1}) == {"speed": 2}


def test_rpc_timeout_names_the_key(pair: tuple[Node, Node]) -> None:
    server, client = pair
    key = server.keys.detector_rpc()
    gate = threading.Event()

    def wait(_: NoArgs) -> SpeedReply:
        gate.wait(10)
        return SpeedReply(speed=0.0)

    server.serve(key, some_verbs(TEST_VERBS, {"measure": wait}))
    server.ready()
    client.wait_alive(["server"], 10)
    start = time.monotonic()
    with pytest.raises(RpcTimeout, match=r"no reply from .*detector/rpc:i within 0.3 s"):
        rpc_call(client, key, "measure", timeout=0.3)
    assert time.monotonic() - start < 2
    gate.set()


def test_absent_service_fails_within_timeout_naming_the_key(net: NetConfig) -> None:
    with Node(None, net) as client:
        key = client.keys.learner_rpc()
        start = time.monotonic()
        with pytest.raises(RpcTimeout, match="learner/rpc:i"):
            rpc_call(client, key, "status", timeout=1.0)
        assert time.monotonic() - start < 1.5


def test_describe_lists_ports_and_verbs(pair: tuple[Node, Node]) -> None:
    server, client = pair
    server.publisher(server.keys.state("left_arm"), JointState)
    server.serve(server.keys.part_rpc("left_arm"), some_verbs(PART_VERBS, {}))
    server.ready()
    client.wait_alive(["server"], 10)
    from archery.protocol.codec import decode
    from archery.protocol.messages import Describe

    replies = list(client.session.get(client.keys.describe("server"), timeout=5))
    info = decode(replies[0].ok.payload.to_bytes(), Describe)
    assert info.service == "server"
    assert {(p.key, p.kind, p.message) for p in info.ports} == {
        (server.keys.state("left_arm"), "pub", "JointState"),
        (server.keys.part_rpc("left_arm"), "rpc", "RpcRequest"),
        (f"{server.keys.robot}/left_arm/requests:o", "pub", "RpcRequest"),
        (f"{server.keys.robot}/left_arm/replies:o", "pub", "RpcReply"),
    }
    assert info.verbs[server.keys.part_rpc("left_arm")] == PART_VERBS.names()
    assert all(p.count == 0 for p in info.ports)


def test_describe_counts_the_messages_of_each_publisher(pair: tuple[Node, Node]) -> None:
    server, client = pair
    states = server.publisher(server.keys.state("torso"), JointState)
    server.publisher(server.keys.state("left_arm"), JointState)
    server.ready()
    for _ in range(3):  # nobody subscribes: the count is the publisher's own
        states.put(JointState(part="torso", names=["a"], position=[0.0], velocity=[0.0]))
    described = describe_all(client.session, client.keys)
    counts = {p.key: p.count for d in described.values() for p in d.ports}
    assert counts == {server.keys.state("torso"): 3, server.keys.state("left_arm"): 0}


def test_an_unsubscribed_stream_leaves_describe_and_calls_back_no_more(
    pair: tuple[Node, Node],
) -> None:
    server, client = pair
    key = server.keys.state("torso")
    states = server.publisher(key, JointState)
    got: list[JointState] = []
    arrived = threading.Event()

    def on_state(message: JointState) -> None:
        got.append(message)
        arrived.set()

    sub = client.subscribe(key, JointState, mode="fifo", callback=on_state)
    assert (key, "sub") in {(p.key, p.kind) for p in client.describe().ports}
    state = JointState(part="torso", names=["a"], position=[0.0], velocity=[0.0])
    states.wait_matched(10.0)
    states.put(state)
    assert arrived.wait(10)
    unmatched = threading.Event()
    stop = states.on_matching(lambda matching: None if matching else unmatched.set())
    try:
        client.unsubscribe(sub)
        client.unsubscribe(sub)  # once gone, ignored
        assert (key, "sub") not in {(p.key, p.kind) for p in client.describe().ports}
        assert unmatched.wait(10) or not states.matching()  # undeclared: nobody matches
    finally:
        stop()


def _spawn_echo(net: NetConfig) -> subprocess.Popen[bytes]:
    argv = [sys.executable, "-m", "archery.apps.cli", "selfcheck", "--echo", "--robot", net.robot]
    for endpoint in net.connect:
        argv += ["--connect", endpoint]
    return subprocess.Popen(argv, stdin=subprocess.DEVNULL)


@pytest.mark.parametrize("how", ["kill", "terminate", "interrupt"])
def test_liveliness_follows_a_real_process(net: NetConfig, how: str) -> None:
    with Node(None, net) as client:
        proc = _spawn_echo(net)
        try:
            client.wait_alive([ECHO_SERVICE], 30)
            if how == "kill":
                proc.kill()
            elif how == "terminate":
                proc.terminate()
            else:
                proc.send_signal(2)
            client.wait_gone(ECHO_SERVICE, 15)
            # a liveliness query may see the token a moment after its deletion was delivered
            deadline = time.monotonic() + 5
            while ECHO_SERVICE in client.alive():
                assert time.monotonic() < deadline, "a query still sees the service after 5 s"
            code = proc.wait(10)
            assert code == (-9 if how == "kill" else 0)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()


def test_wait_alive_reports_what_is_missing(net: NetConfig) -> None:
    with Node(None, net) as client, pytest.raises(RpcTimeout, match=r"not alive.*: camera, robot"):
        client.wait_alive(["robot", "camera"], 0.3)


def test_anonymous_nodes_have_no_token(net: NetConfig) -> None:
    with Node(None, net) as tool:
        with pytest.raises(ValueError, match="anonymous"):
            tool.ready()
        assert tool.alive(timeout=0.5) == set()


def test_close_never_raises_and_says_in_one_line_what_it_could_not_close(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """The router killed under a node with ports, and one part whose close fails as Zenoh's does
    when it times out: close returns, and one warning line names what was not closed."""
    endpoint = free_tcp_endpoint()
    router = spawn_router(endpoint)
    try:
        node = Node("closer", NetConfig(connect=(endpoint,), robot="closing"))
        node.subscribe(node.keys.world_state(), WorldEvent)
        node.publisher(node.keys.world_events(), WorldEvent)
        node.ready()

        class Stuck:
            def close(self) -> None:
                raise zenoh.ZError("close operation timed out")

        node._closables.append(Stuck())
    finally:
        router.kill()
        router.wait(timeout=10)
    with caplog.at_level(logging.WARNING, logger="archery"):
        node.close()
        node.close()  # twice is a no-op
    lines = [r.getMessage() for r in caplog.records if "not closed cleanly" in r.getMessage()]
    assert len(lines) == 1 and "Stuck: close operation timed out" in lines[0]
    assert not [r for r in caplog.records if r.exc_info]  # no traceback


def test_a_wait_on_a_subscription_ends_as_it_closes(pair: tuple[Node, Node]) -> None:
    _, client = pair
    sub = client.subscribe(client.keys.state("torso"), JointState)
    ended: list[BaseException] = []

    def wait() -> None:
        try:
            sub.wait_newer(60.0)
        except RpcTimeout as exc:
            ended.append(exc)

    waiter = threading.Thread(target=wait)
    waiter.start()
    client.unsubscribe(sub)
    waiter.join(10)  # the wait would otherwise last its 60 s
    assert not waiter.is_alive() and len(ended) == 1
    with pytest.raises(RpcTimeout):
        sub.wait_newer(60.0)  # closed: nothing newer will come, at once
