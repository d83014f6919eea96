"""Messages built to hurt, sent to a real robot service over a real router: nesting deeper than
the decoder can follow, and strings of megabytes where a name belongs. Each is a counted drop or
a short error; no traceback, no log line, reply or counter that echoes the whole value, the
service keeps serving, and it gives the memory of a burst back."""

from __future__ import annotations

import logging
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import msgspec
import pytest

from archery.mesh import memory
from archery.mesh.netflags import NetConfig
from archery.mesh.node import Node
from archery.protocol.codec import encode
from archery.protocol.errors import KeyNameError, RpcError
from archery.protocol.messages import JointCommand, JointState, RpcRequest
from archery.protocol.robotspec import ROBOT
from archery.protocol.text import SHOWN_LIMIT, shown
from archery.services.robot.config import RobotConfig
from archery.services.robot.service import run
from archery.sim.scene_config import SceneConfig
from archery.sim.world import WorldConfig
from tests.conftest import serving
from tests.rpc import rpc_call

WORLD = WorldConfig(scene=SceneConfig(meshes=False))
HUGE = 10 * 1024 * 1024  # characters of a hostile name
SHORT = 1000  # characters: a reply's message, a counter or a log line at most, here
DEEP = 100_000  # nesting levels of a hostile payload: past every Python's recursion limit


@pytest.fixture
def robot(net: NetConfig, caplog: pytest.LogCaptureFixture) -> Iterator[Node]:
    """The robot service on a thread, and a client node that sees it alive."""
    caplog.set_level(logging.INFO, logger="archery")
    with serving(run, RobotConfig(net=net, world=WORLD)), Node(None, net) as node:
        node.wait_alive([ROBOT], 30)
        yield node


def _until(check: Callable[[], Any], timeout: float = 20.0) -> Any:
    """Ask `check` again until it returns something true (each call is an RPC round trip)."""
    deadline = time.monotonic() + timeout
    while not (result := check()):
        assert time.monotonic() < deadline, "the condition did not hold in time"
    return result


def _deep(levels: int, opening: bytes = b"\x91") -> bytes:
    """A msgpack value nested `levels` deep: arrays of one item, or with `opening`
    b"\x81\xa1a", maps {"a": …}."""
    return opening * levels + b"\x00"


def _command(position: list[float], **extra: bytes) -> bytes:
    """A JointCommand for the left arm as a raw msgpack map, with more fields given as raw
    msgpack values."""
    fields = {"type": "JointCommand", "schema": 1, "part": "left_arm", "position": position}
    head = msgspec.msgpack.encode(fields)
    body = b"".join(msgspec.msgpack.encode(k) + v for k, v in extra.items())
    return bytes([0x80 | (len(fields) + len(extra))]) + head[1:] + body


def _no_tracebacks(caplog: pytest.LogCaptureFixture, capfd: pytest.CaptureFixture[str]) -> None:
    assert not [r for r in caplog.records if r.exc_info], "a traceback was logged"
    assert all(len(r.getMessage()) < SHORT for r in caplog.records), "a long log line"
    err = capfd.readouterr().err
    assert "Traceback" not in err and "RecursionError" not in err


def test_a_deeply_nested_command_is_a_counted_drop(
    robot: Node, caplog: pytest.LogCaptureFixture, capfd: pytest.CaptureFixture[str]
) -> None:
    key = robot.keys.command("left_arm")
    counters = robot.keys.part_rpc("left_arm")
    home = rpc_call(robot, counters, "getTargets")["position"]
    robot.session.put(key, _command(home, junk=_deep(DEEP)))  # unknown fields, skipped...
    robot.session.put(key, _command(home, more=_deep(DEEP, b"\x81\xa1a")))  # ...by recursion
    robot.session.put(key, _command(home))  # the good one, after them on the same key
    seen = _until(lambda: (c := rpc_call(robot, counters, "counters"))["accepted"] and c)
    assert seen["undecodable"] == 2 and seen["rejected"] == 0
    drops = [r.getMessage() for r in caplog.records if "dropped message" in r.getMessage()]
    assert len(drops) == 2 and all("nests too deep" in line for line in drops)
    # An RPC whose args nest too deep is refused as a bad message, and the port still serves.
    head = msgspec.msgpack.encode({"type": "RpcRequest", "verb": "positionMove"})
    request = b"\x83" + head[1:] + msgspec.msgpack.encode("args") + b"\x81\xa1a" * DEEP + b"\x80"
    reply = robot.request(counters, request, verb="positionMove", timeout=10)
    assert not reply.ok and reply.code == "bad_message" and "deep" in reply.message
    assert rpc_call(robot, counters, "counters")["undecodable"] == 2
    _no_tracebacks(caplog, capfd)


def test_huge_names_are_cut_short_in_replies_counters_and_logs(
    robot: Node, caplog: pytest.LogCaptureFixture, capfd: pytest.CaptureFixture[str]
) -> None:
    name = "x" * HUGE
    key = robot.keys.command("left_arm")
    rpc = robot.keys.part_rpc("left_arm")
    publisher = robot.publisher(key, JointCommand, lossless=True)  # no drop of a big one
    assert publisher.wait_matched(10)
    publisher.put(JointCommand(part=name, position=[0.0] * 7))  # wrong_part, naming the part
    publisher.put(JointCommand(part="left_arm", position=[0.1], names=[name]))  # unknown_joint
    seen = _until(lambda: (c := rpc_call(robot, rpc, "counters"))["rejected"] == 2 and c)
    assert seen["rejected_by_reason"]["wrong_part"] == seen["rejected_by_reason"]["unknown_joint"]
    assert len(seen["last_rejection"]) < SHORT
    assert shown(name) in seen["last_rejection"]  # quoted as "'xxx…… (10485760 chars)'"
    assert f"({HUGE} chars)" in seen["last_rejection"]
    rejected = [r.getMessage() for r in caplog.records if "rejected command" in r.getMessage()]
    assert len(rejected) == 2
    # A verb, an argument's name, a joint name and a bad value of megabytes, over RPC.
    with pytest.raises(KeyNameError) as refused:  # never sent: a verb name is a short word
        robot.request(rpc, b"", verb=name)
    assert len(str(refused.value)) < SHORT
    for verb, args, code in [
        ("status", {}, "bad_message"),  # a payload naming another verb than its key
        ("positionMove", {name: 1}, "bad_request"),
        ("positionMove", {"position": [0.1], "names": [name]}, "bad_request"),
        ("setRefSpeeds", {"speeds": name}, "bad_request"),
    ]:
        request = RpcRequest(
            verb=name if verb == "status" else verb, args=args, seq=0, stamp=time.time()
        )
        reply = robot.request(rpc, encode(request), verb=verb, timeout=20)
        assert not reply.ok and reply.code == code
        assert len(reply.message) < SHORT, reply.message[:SHORT]
    with pytest.raises(RpcError) as info:
        rpc_call(robot, robot.keys.archery_rpc(), "reset", {"seed": name}, timeout=20)
    assert info.value.code == "bad_request" and len(str(info.value)) < SHORT
    assert rpc_call(robot, rpc, "getJointNames")["names"]  # still serving
    assert len(rpc_call(robot, rpc, "counters")["last_rejection"]) < SHORT
    _no_tracebacks(caplog, capfd)


def test_shown_quotes_a_value_on_one_short_line() -> None:
    assert shown("torso") == "'torso'" and shown([0.1, None]) == "[0.1, None]"
    text = shown("x" * HUGE)
    assert len(text) == SHOWN_LIMIT and text.endswith(f"… ({HUGE} chars)")
    assert shown(list(range(10**6)), 80).endswith("… (1000000 items)")
    assert "\n" not in shown("a\nb" * 100) and len(shown(b"\0" * HUGE, 50)) == 50
    nested: Any = []
    for _ in range(DEEP):
        nested = [nested]
    assert shown(nested).endswith("… (1 item)")


def _rss_mb(pid: int) -> float:
    """The resident memory of process `pid` (MB)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    raise AssertionError(f"no VmRSS for {pid}")


def test_memory_goes_back_after_a_burst_of_big_requests(net: NetConfig) -> None:
    # `archery robot` kept 330 MB more for good after 50 such requests; now it gives them back.
    robot = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "archery.apps.cli",
            "robot",
            "--connect",
            net.connect[0],
            "--robot",
            net.robot,
        ],
        stdin=subprocess.DEVNULL,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        with Node(None, net) as node:
            node.wait_alive([ROBOT], 60)
            rpc = node.keys.part_rpc("left_arm")
            node.subscribe(node.keys.state("left_arm"), JointState).wait_newer(30)  # running
            before = _rss_mb(robot.pid)
            args = {"position": [0.0], "names": ["x" * HUGE]}  # 10 MB, refused: unknown joint
            request = encode(RpcRequest(verb="positionMove", args=args, seq=0, stamp=time.time()))
            for _ in range(50):
                reply = node.request(rpc, request, verb="positionMove", timeout=30)
                assert not reply.ok and reply.code == "bad_request"
            deadline = time.monotonic() + 60
            while (now := _rss_mb(robot.pid)) > before + 50:
                assert time.monotonic() < deadline, f"{before:.0f} MB before, {now:.0f} MB after"
                time.sleep(0.1)
            assert rpc_call(node, rpc, "getJointNames")["names"]  # still serving
    finally:
        robot.terminate()
        robot.wait(30)


def test_a_big_payload_gives_memory_back() -> None:
    done = memory.trims()
    memory.note_payload(memory.BIG_PAYLOAD - 1)  # small: nothing to give back
    memory.note_payload(memory.BIG_PAYLOAD)
    deadline = time.monotonic() + 30
    while memory.trims() == done:
        assert time.monotonic() < deadline, "no trim after a big payload"
        time.sleep(0.05)
