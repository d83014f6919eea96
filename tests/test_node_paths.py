"""Where the node does its work: non-blocking verbs on the receive path, blocking ones on the
server's worker, background ones on a second worker at a lower priority; the publisher's reused
encode buffer; the cheap array checks."""

from __future__ import annotations

import contextlib
import math
import os
import threading
from collections.abc import Callable, Iterator

import msgspec
import numpy as np
import pytest

from archery.mesh.netflags import NetConfig
from archery.mesh.node import Node
from archery.mesh.rpc_server import BACKGROUND_NICE, RpcServer
from archery.protocol.errors import BadRequest, RpcError
from archery.protocol.messages import Array, Image
from archery.protocol.verbs import TABLES, Args, NoArgs, Reply, Verb, VerbTable
from tests.rpc import rpc_call


class WhoArgs(Args, frozen=True):
    x: float = 0.0


class WhoReply(Reply, frozen=True):
    thread: str
    x: float = 0.0


class NiceReply(Reply, frozen=True):
    thread: str
    nice: int  # the serving thread's niceness
    policy: int  # and its scheduling class


PEEK = Verb("peek", WhoArgs, WhoReply, "non-blocking", blocking=False)
HOLD = Verb("hold", NoArgs, WhoReply, "blocks until released")
DRAW = Verb("draw", NoArgs, NiceReply, "a picture for an observer", background=True)
TABLE = VerbTable("paths", ("paths/rpc:i",), (PEEK, HOLD))
LATER = VerbTable("later", ("later/rpc:i",), (HOLD, DRAW))


@pytest.fixture
def pair(net: NetConfig) -> Iterator[tuple[Node, Node]]:
    with Node("server", net) as server, Node(None, net) as client:
        yield server, client


def _holder(release: threading.Event, entered: threading.Event) -> Callable[[NoArgs], WhoReply]:
    """A handler that sets `entered` and returns once `release` is set (10 s at most)."""

    def hold(args: NoArgs) -> WhoReply:
        entered.set()
        if not release.wait(10):
            raise BadRequest("never released")
        return WhoReply(thread=threading.current_thread().name)

    return hold


def _serve(server: Node, key: str, release: threading.Event, entered: threading.Event) -> RpcServer:
    def peek(args: WhoArgs) -> WhoReply:
        return WhoReply(thread=threading.current_thread().name, x=args.x)

    return server.serve(key, TABLE.bind_names({"peek": peek, "hold": _holder(release, entered)}))


def _reachable(server: Node, client: Node) -> None:
    """Once the client sees the server alive: its token follows every port served before it,
    so the router knows them all (a call sent sooner may find no queryable)."""
    server.ready()
    client.wait_alive(["server"], 10)


@contextlib.contextmanager
def _held_call(
    client: Node, key: str, release: threading.Event, entered: threading.Event
) -> Iterator[list[WhoReply]]:
    """A `hold` call on `key` from another thread, in its handler while the block runs (the
    list gets its reply once the block ended and released it)."""
    held: list[WhoReply] = []
    caller = threading.Thread(target=lambda: held.append(client.call_typed(key, HOLD, timeout=15)))
    caller.start()
    try:
        assert entered.wait(5), "the blocking handler never started"
        yield held
        assert not held, "the blocking call returned before it was released"
    finally:
        release.set()
        caller.join(15)


def test_non_blocking_verbs_run_on_the_receive_path_blocking_ones_on_the_worker(
    pair: tuple[Node, Node],
) -> None:
    server, client = pair
    key = f"{server.keys.robot}/paths/rpc:i"
    release, entered = threading.Event(), threading.Event()
    release.set()
    assert _serve(server, key, release, entered).inline == frozenset({"peek"})
    _reachable(server, client)
    peeked = client.call_typed(key, PEEK, WhoArgs(x=1.5))
    held = client.call_typed(key, HOLD)
    assert peeked.x == 1.5
    assert peeked.thread != f"rpc {key}"
    assert held.thread == f"rpc {key}"


def test_a_blocked_handler_never_stalls_a_non_blocking_verb(pair: tuple[Node, Node]) -> None:
    server, client = pair
    key = f"{server.keys.robot}/paths/rpc:i"
    other = f"{server.keys.robot}/paths2/rpc:i"
    release, entered = threading.Event(), threading.Event()
    _serve(server, key, release, entered)
    _serve(server, other, threading.Event(), threading.Event())
    _reachable(server, client)
    with _held_call(client, key, release, entered) as held:
        # the same port's worker is busy: the non-blocking verb is answered anyway, promptly
        for port in (key, other):
            assert client.call_typed(port, PEEK, WhoArgs(x=2.0), timeout=2.0).x == 2.0
    assert held and held[0].thread == f"rpc {key}"


def test_a_background_verb_runs_on_its_own_worker_at_a_lower_priority_beside_a_blocked_one(
    pair: tuple[Node, Node],
) -> None:
    server, client = pair
    key = f"{server.keys.robot}/later/rpc:i"
    release, entered = threading.Event(), threading.Event()

    def draw(args: NoArgs) -> NiceReply:
        me = threading.get_native_id()
        return NiceReply(
            thread=threading.current_thread().name,
            nice=os.getpriority(os.PRIO_PROCESS, me),
            policy=os.sched_getscheduler(me),
        )

    served = server.serve(key, LATER.bind_names({"hold": _holder(release, entered), "draw": draw}))
    assert served.background == frozenset({"draw"}) and served.inline == frozenset()
    _reachable(server, client)
    with _held_call(client, key, release, entered) as held:
        drawn = client.call_typed(key, DRAW, timeout=5.0)  # answered while the worker is busy
    assert held and drawn.thread == f"rpc {key} background" and held[0].thread == f"rpc {key}"
    mine = os.getpriority(0, threading.get_native_id())
    assert drawn.nice == min(19, mine + BACKGROUND_NICE) and drawn.policy == os.SCHED_IDLE


def test_non_blocking_verbs_are_validated_like_blocking_ones(pair: tuple[Node, Node]) -> None:
    server, client = pair
    key = f"{server.keys.robot}/paths/rpc:i"
    _serve(server, key, threading.Event(), threading.Event())
    _reachable(server, client)
    nan = msgspec.msgpack.encode({"type": "RpcRequest", "verb": "peek", "args": {"x": math.nan}})
    reply = client.request(key, nan, verb="peek")
    assert reply.code == "bad_request"
    assert reply.message.startswith("invalid argument of peek at `$.x`")
    with pytest.raises(RpcError, match="invalid argument of peek") as caught:
        rpc_call(client, key, "peek", {"x": "high"})
    assert caught.value.code == "bad_request"
    with pytest.raises(RpcError, match="has no verb 'nope'") as caught:
        rpc_call(client, key, "nope")
    assert caught.value.code == "unknown_verb"
    assert client.request(key, b"\xc1", verb="peek").code == "bad_message"
    assert client.call_typed(key, PEEK, WhoArgs(x=3.0)).x == 3.0  # still serving


def test_only_verbs_that_never_wait_are_non_blocking() -> None:
    """Getters of in-memory settings and status are non-blocking, and so are a part's lease
    verbs (a lock held for a moment: a takeover never queues behind a move), and the camera's
    scene view (the newest view at once; its thread renders the next); anything that moves,
    waits for a frame, the simulation thread or a stream stays on the worker."""
    inline = {(t.title, v.name) for t in TABLES for v in t if not v.blocking}
    assert inline == {
        ("robot controlboard", "getJointNames"),
        ("robot controlboard", "getLimits"),
        ("robot controlboard", "claim"),
        ("robot controlboard", "renewClaim"),
        ("robot controlboard", "dropClaim"),
        ("robot controlboard", "getClaim"),
        ("camera", "status"),
        ("camera", "scene"),
        ("detector", "status"),
        ("cartesian controller of one arm", "getTolerance"),
        ("cartesian controller of one arm", "getTrajTime"),
        ("cartesian controller of one arm", "getDOF"),
        ("cartesian controller: archery posture", "getTrajTime"),
        ("cartesian controller: archery posture", "status"),
        ("learner", "status"),
        ("learner", "confirm"),  # sets an event: a waiting session goes on
    }


def test_only_pictures_for_observers_are_background_verbs() -> None:
    """The detector's frame with its overlay (the dashboard's picture, a session's hit.png) is
    the one verb whose work serves no rollout."""
    later = {(t.title, v.name) for t in TABLES for v in t if v.background}
    assert later == {("detector", "frame")}


def test_the_reused_publish_buffer_never_mixes_frames(pair: tuple[Node, Node]) -> None:
    server, client = pair
    sub = client.subscribe(server.keys.cam_frames(), Image, mode="fifo")
    pub = server.publisher(sub.key, Image, lossless=True)
    assert pub.wait_matched(5), "no subscriber matched the frames"
    sizes = [(64, 48), (8, 4), (64, 48), (1, 1), (32, 16)] * 4
    for i, (w, h) in enumerate(sizes):
        pub.put(Image.from_numpy(np.full((h, w, 3), i, np.uint8), frame=i))
    for i, (w, h) in enumerate(sizes):
        got = sub.get(timeout=5)
        assert (got.frame, got.width, got.height) == (i, w, h)
        assert got.data == bytes([i]) * (w * h * 3)


def test_array_checks_stay_exact() -> None:
    with pytest.raises(ValueError, match="needs 0 bytes, got 8"):
        Array(dtype="<f8", shape=(0, 3), data=b"\0" * 8)
    with pytest.raises(ValueError, match="needs"):  # the size product does not wrap around
        Array(dtype="|u1", shape=(2**32, 2**32), data=b"")
    with pytest.raises(ValueError, match="NaN or infinite"):
        Array.from_numpy(np.array([[1.0, 2.0], [np.inf, 0.0]], np.float32))
    assert Array.from_numpy(np.zeros((2, 3), ">f8")).to_numpy().shape == (2, 3)
