"""One live instance per service name and robot: a second one refuses to start (exit 2, naming
the live one's pid and host) unless --replace, which makes the live one stop cleanly;
`archery ports` lists every instance it sees."""

from __future__ import annotations

import os
import socket
import stat
import subprocess
import sys
from collections.abc import Iterator

import pytest
import zenoh

from archery.mesh.instances import InstanceWatch, live_instances, zid_of
from archery.mesh.netflags import NetConfig, open_session
from archery.mesh.node import Node
from archery.mesh.runtime import runtime_dir
from archery.protocol.codec import encode
from archery.protocol.errors import DuplicateService
from archery.protocol.messages import Describe, ReplaceRequest
from tests.conftest import archery

NAME = "detector"


def _flags(net: NetConfig) -> list[str]:
    return ["--connect", net.connect[0], "--robot", net.robot]


@pytest.fixture
def spawn(net: NetConfig) -> Iterator:
    procs: list[subprocess.Popen[str]] = []

    def start(*extra: str) -> subprocess.Popen[str]:
        argv = [sys.executable, "-m", "tests.solo_service", NAME, *_flags(net), *extra]
        procs.append(
            subprocess.Popen(argv, stdin=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        )
        return procs[-1]

    yield start
    for proc in procs:
        if proc.poll() is None:
            proc.terminate()
            proc.wait(10)


def _instance_pids(node: Node) -> set[int]:
    """Pids of the instances holding NAME's instance token now (from their describe)."""
    from archery.mesh.instances import describe_all

    zids = live_instances(node.session, node.keys, NAME)
    return {d.pid for z, d in describe_all(node.session, node.keys, NAME).items() if z in zids}


def test_a_second_instance_refuses_to_start(net: NetConfig, spawn) -> None:
    first = spawn()
    with Node(None, net) as node:
        node.wait_alive([NAME], 30)
        second = spawn()
        assert second.wait(30) == 2
        err = second.stderr.read()
        assert f"pid {first.pid} on {socket.gethostname()}" in err and "--replace" in err
        assert first.poll() is None and _instance_pids(node) == {first.pid}


def test_replace_stops_the_live_instance(net: NetConfig, spawn) -> None:
    first = spawn()
    with Node(None, net) as node:
        node.wait_alive([NAME], 30)
        second = spawn("--replace")
        assert first.wait(30) == 0  # it stopped cleanly, as on SIGTERM
        assert "replaces this one" in first.stderr.read()
        node.wait_alive([NAME], 30)
        pids: set[int] = set()
        for _ in range(100):
            pids = _instance_pids(node)
            if pids == {second.pid}:
                break
        assert pids == {second.pid}
        assert second.poll() is None


def test_in_process_duplicate_names_the_live_one(net: NetConfig) -> None:
    with Node(NAME, net) as first:
        first.ready()
        with pytest.raises(DuplicateService, match=f"pid {first.describe().pid} on"):
            Node(NAME, net)
        other = NetConfig(connect=net.connect, robot=net.robot + "b")
        with Node(NAME, other) as elsewhere:  # another robot: its own name space
            elsewhere.ready()


def test_ports_shows_every_instance(net: NetConfig) -> None:
    """A second session claiming the name without the check (an old build, a hand-made
    session): `archery ports` lists both, not one of the two."""
    stray = open_session(net)
    try:
        with Node(NAME, net) as node:
            node.ready()
            keys = node.keys
            token = stray.liveliness().declare_token(keys.alive_instance(NAME, zid_of(stray)))
            fake = Describe(service=NAME, ports=[], pid=424242, host="elsewhere", verbs={})

            def answer(query: zenoh.Query) -> None:
                query.reply(query.key_expr, encode(fake))

            queryable = stray.declare_queryable(keys.describe(NAME), answer)
            out = archery("ports", *_flags(net))
            assert out.returncode == 0, out.stderr
            lines = [line for line in out.stdout.splitlines() if line.startswith(NAME)]
            assert len(lines) == 2 and all("[2 instances!]" in line for line in lines)
            assert any(f"pid {node.describe().pid} " in line for line in lines)
            assert any("pid 424242 on elsewhere" in line for line in lines)
            queryable.undeclare()
            token.undeclare()
    finally:
        stray.close()


def test_a_fresh_watch_knows_a_live_instance_at_once(net: NetConfig) -> None:
    """The first check of a fresh watch, made while its subscriber's history is still on its
    way, accepts the live instance (a liveliness query made then may be answered empty)."""
    with Node(NAME, net) as service, Node(None, net) as client:
        service.ready()
        zid = zid_of(service.session)
        for attempt in range(300):
            watch = InstanceWatch(client.session, client.keys)
            try:
                assert watch.is_instance(NAME, zid), f"attempt {attempt}: instance refused"
            finally:
                watch.close()


def test_a_watch_refuses_a_session_that_holds_no_token(net: NetConfig) -> None:
    with Node(NAME, net) as service, Node(None, net) as client:
        service.ready()
        watch = InstanceWatch(client.session, client.keys, settle=0.5)
        try:
            assert watch.is_instance(NAME, zid_of(service.session))
            assert not watch.is_instance(NAME, zid_of(client.session))
            assert watch.holders(NAME) == {zid_of(service.session)}
        finally:
            watch.close()


def test_no_message_but_a_local_replacement_stops_a_service(net: NetConfig, spawn) -> None:
    """The old way (a `replace` payload on describe) and forged requests (another host, a pid
    that is not `archery NAME --replace`, garbage) are refused and logged; the service runs on."""
    first = spawn()
    keys_net = NetConfig(connect=net.connect, robot=net.robot)
    with Node(None, keys_net) as node:
        node.wait_alive([NAME], 30)
        keys = node.keys
        list(node.session.get(keys.describe(NAME), payload=b"replace", timeout=5))
        forged = (
            ReplaceRequest(service=NAME, host="elsewhere", pid=first.pid),
            ReplaceRequest(service=NAME, host=socket.gethostname(), pid=os.getpid()),
            ReplaceRequest(service=NAME, host=socket.gethostname(), pid=2**22 + 7),
        )
        errors = []
        for request in forged:
            for reply in node.session.get(keys.replace(NAME), payload=encode(request), timeout=5):
                assert reply.err is not None
                errors.append(reply.err.payload.to_string())
        for reply in node.session.get(keys.replace(NAME), payload=b"\xc1" * 10, timeout=5):
            assert reply.err is not None
            errors.append(reply.err.payload.to_string())
        assert len(errors) == 4 and all(e.startswith("refused: ") for e in errors), errors
        assert "from host 'elsewhere'" in errors[0]
        assert "does not run detector with --replace" in errors[1]
        assert "no process" in errors[2] and "not a ReplaceRequest" in errors[3]
        assert first.poll() is None and _instance_pids(node) == {first.pid}
    first.terminate()
    assert first.wait(10) == 0
    assert first.stderr.read().count("refused a request to make way") == 4


def test_a_decoy_with_the_right_command_line_cannot_stop_a_service(net: NetConfig, spawn) -> None:
    """A process that only looks like a replacement (`… detector --replace` in its command line,
    running nothing of ours) is refused without the live instance's token; the token lives in a
    folder and file only the service's user may read, and goes when the service stops."""
    first = spawn()
    decoy = subprocess.Popen(
        [sys.executable, "-c", "import sys; sys.stdin.read()", NAME, "--replace"],
        stdin=subprocess.PIPE,
    )
    try:
        with Node(None, net) as node:
            node.wait_alive([NAME], 30)
            (zid,) = live_instances(node.session, node.keys, NAME)
            token = runtime_dir() / net.robot / NAME / zid
            assert stat.S_IMODE(token.stat().st_mode) == 0o600
            assert stat.S_IMODE(token.parent.stat().st_mode) == 0o700
            errors = []
            for proof in ("", "0" * 64):
                request = ReplaceRequest(
                    service=NAME, host=socket.gethostname(), pid=decoy.pid, proof=proof
                )
                for reply in node.session.get(
                    node.keys.replace(NAME), payload=encode(request), timeout=5
                ):
                    assert reply.err is not None
                    errors.append(reply.err.payload.to_string())
            assert len(errors) == 2, errors
            assert all("did not show this instance's token" in e for e in errors), errors
            assert first.poll() is None and _instance_pids(node) == {first.pid}
    finally:
        decoy.stdin.close()  # type: ignore[union-attr]
        decoy.wait(10)
    first.terminate()
    assert first.wait(10) == 0
    assert first.stderr.read().count("did not show this instance's token") == 2
    assert not token.exists()
