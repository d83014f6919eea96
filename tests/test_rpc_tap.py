"""An `rpc:i` port's taps: each handled request and reply published on its own key while
someone listens, nothing while nobody does, big replies without their result."""

from __future__ import annotations

import threading
from collections.abc import Iterator

import pytest

from archery.mesh.netflags import NetConfig
from archery.mesh.node import Node
from archery.mesh.rpc_server import RpcServer
from archery.mesh.rpc_tap import MAX_TAPPED_REPLY, REDACTED
from archery.protocol.keys import port_of, tap_keys
from archery.protocol.messages import RpcReply, RpcRequest
from archery.protocol.verbs.robot import PART_VERBS, LimitsReply, RefSpeedsReply
from tests.rpc import rpc_call, some_verbs

NAMES = ["a", "b"]
LEASE = "a1b2c3d4e5f6a7b8"


@pytest.fixture
def served(net: NetConfig) -> Iterator[tuple[Node, Node, RpcServer]]:
    handlers = {
        "getLimits": lambda a: LimitsReply(names=NAMES, min=[-1, -1], max=[1, 1], tolerance=0.0),
        "setRefSpeeds": lambda a: RefSpeedsReply(
            names=NAMES, speeds=[0.5, 0.5], lease=LEASE if a.claim else ""
        ),
    }
    with Node("server", net) as server, Node(None, net) as client:
        rpc = server.serve(server.keys.part_rpc("torso"), some_verbs(PART_VERBS, handlers))
        server.ready()
        client.wait_alive(["server"], 10)
        yield server, client, rpc


class _Collected:
    """Tapped requests and replies as they arrive (any thread)."""

    def __init__(self) -> None:
        self.requests: list[RpcRequest] = []
        self.replies: list[RpcReply] = []
        self._cond = threading.Condition()

    def add(self, message: RpcRequest | RpcReply) -> None:
        with self._cond:
            (self.requests if isinstance(message, RpcRequest) else self.replies).append(message)
            self._cond.notify_all()

    def wait(self, requests: int, replies: int) -> tuple[list[RpcRequest], list[RpcReply]]:
        """Once that many requests and replies have arrived (20 s at most)."""
        with self._cond:
            done = self._cond.wait_for(
                lambda: len(self.requests) >= requests and len(self.replies) >= replies, 20
            )
            assert done, (self.requests, self.replies)
            return list(self.requests), list(self.replies)


def test_the_tap_keys_are_ports_of_their_own() -> None:
    requests, replies = tap_keys("icubSim/cartesianController/archery/rpc:i") or ("", "")
    assert requests == "icubSim/cartesianController/archery/requests:o"
    assert port_of(requests).message == "RpcRequest" and port_of(replies).message == "RpcReply"
    assert tap_keys("icubSim/describe/robot") is None


def test_requests_and_replies_are_published_while_someone_listens(
    served: tuple[Node, Node, RpcServer],
) -> None:
    server, client, rpc = served
    key = server.keys.part_rpc("torso")
    assert rpc.tap is not None
    for _ in range(3):  # nobody listens: nothing is encoded or published
        rpc_call(client, key, "getLimits", timeout=10)
    assert rpc.tap.requests.count == rpc.tap.replies.count == 0
    taps = _Collected()
    client.subscribe(
        f"{server.keys.robot}/torso/requests:o", RpcRequest, mode="fifo", callback=taps.add
    )
    client.subscribe(
        f"{server.keys.robot}/torso/replies:o", RpcReply, mode="fifo", callback=taps.add
    )
    assert rpc.tap.requests.wait_matched(10) and rpc.tap.replies.wait_matched(10)
    rpc_call(client, key, "setRefSpeeds", {"speeds": 0.5}, timeout=10)
    with pytest.raises(Exception, match="has no verb"):
        rpc_call(client, key, "velocityMove", {"speeds": [0.1]}, timeout=10)
    requests, replies = taps.wait(2, 2)  # both calls, in the order they were handled
    assert [(r.verb, r.args) for r in requests[:2]] == [
        ("setRefSpeeds", {"speeds": 0.5}),
        ("velocityMove", {"speeds": [0.1]}),
    ]
    assert replies[0].ok and replies[0].result == {"names": NAMES, "speeds": [0.5, 0.5]}
    assert not replies[1].ok and replies[1].code == "unknown_verb"
    assert [r.seq for r in requests[:2]] == [1, 2]  # the tap's own sequence numbers


def test_a_big_reply_is_tapped_without_its_result(served: tuple[Node, Node, RpcServer]) -> None:
    server, client, rpc = served
    assert rpc.tap is not None
    taps = _Collected()
    client.subscribe(
        f"{server.keys.robot}/torso/replies:o", RpcReply, mode="fifo", callback=taps.add
    )
    assert rpc.tap.replies.wait_matched(10)
    big = RpcReply(ok=True, result={"data": b"x" * 100}, seq=7)
    rpc.tap.tap("grab", None, big, MAX_TAPPED_REPLY + 1)
    _, replies = taps.wait(0, 1)
    assert replies[0].result == {"omitted_bytes": MAX_TAPPED_REPLY + 1} and replies[0].ok


def test_lease_ids_are_never_tapped(served: tuple[Node, Node, RpcServer]) -> None:
    server, client, rpc = served
    key = server.keys.part_rpc("torso")
    taps = _Collected()
    for port in ("requests:o", "replies:o"):
        message = RpcRequest if port == "requests:o" else RpcReply
        client.subscribe(f"{server.keys.robot}/torso/{port}", message, callback=taps.add)
    assert rpc.tap is not None
    assert rpc.tap.requests.wait_matched(10) and rpc.tap.replies.wait_matched(10)
    took = rpc_call(client, key, "setRefSpeeds", {"speeds": 0.5, "claim": {"owner": "c"}})
    assert took["lease"] == LEASE  # the caller gets its lease
    rpc_call(client, key, "setRefSpeeds", {"speeds": 0.4, "lease": LEASE}, timeout=10)
    requests, replies = taps.wait(2, 2)
    assert requests[0].args["claim"] == {"owner": "c"}
    assert requests[1].args == {"speeds": 0.4, "lease": REDACTED}
    assert replies[0].result["lease"] == REDACTED
    assert LEASE not in repr(requests) + repr(replies)
