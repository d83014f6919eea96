"""A waiting verb (the camera's `grab`) cannot stall a port: it never holds the port's worker,
at most `MAX_WAITING_PER_CALLER` of one caller identity and `MAX_WAITING` in all wait at a time
(the excess refused `busy` at once), a stamp no frame can reach is refused at once, and nothing
waits past its caller's own timeout."""

from __future__ import annotations

import dataclasses
import time
from concurrent.futures import ThreadPoolExecutor

import pytest

from archery.mesh.acl import OPERATOR, VIEWER, granted
from archery.mesh.netflags import NetConfig
from archery.mesh.node import Node
from archery.mesh.rpc_server import MAX_WAITING, MAX_WAITING_PER_CALLER
from archery.protocol.errors import RpcError, RpcTimeout
from archery.protocol.keys import Keys, verb_key
from archery.protocol.verbs import NoArgs
from archery.protocol.verbs.camera import CALIBRATION, GRAB, STATUS, GrabArgs
from archery.services.camera.config import CameraConfig
from archery.services.camera.service import run
from tests.conftest import serving

GRAB = GRAB
STATUS = STATUS
NEVER = 1e9  # s of sim time: a world state no test publishes


def _camera(net: NetConfig) -> CameraConfig:
    return CameraConfig(net=net, rate=5.0, robot_timeout=0.3, width=320, height=180)


def _grab_error(node: Node, args: GrabArgs, timeout: float) -> RpcError | None:
    try:
        node.call_typed(node.keys.cam_rpc(), GRAB, args, timeout=timeout)
    except RpcError as exc:
        return exc
    return None


def test_a_stamp_beyond_the_timeout_is_refused_at_once(net: NetConfig) -> None:
    with serving(run, _camera(net)), Node(None, net) as node:
        node.wait_alive(["camera"], timeout=30)
        start = time.monotonic()
        far = GrabArgs(after_stamp=time.time() + 3600.0, timeout=60.0)
        error = _grab_error(node, far, timeout=60.0)
        took = time.monotonic() - start
        assert error is not None and error.code == "bad_request", error
        assert "ahead of the camera's clock" in error.message
        assert took < 10.0  # not the 60 s the grab asked for


def _as(net: NetConfig, identity: str) -> Node:
    """A node whose calls name `identity` as their caller."""
    return Node(None, dataclasses.replace(net, identity=identity))


def test_waiting_grabs_hold_neither_the_worker_nor_more_than_their_bound(net: NetConfig) -> None:
    callers = MAX_WAITING // MAX_WAITING_PER_CALLER  # identities that fill the port together
    with serving(run, _camera(net)), Node(None, net) as node:
        node.wait_alive(["camera"], timeout=30)
        key = node.keys.cam_rpc()
        never = GrabArgs(after_sim_time=NEVER, timeout=10.0)  # a world state that never comes
        probe = GrabArgs(after_sim_time=NEVER, timeout=0.5)
        others = [_as(net, f"caller{n}") for n in range(callers)]
        try:
            with ThreadPoolExecutor(MAX_WAITING) as pool:
                pending = [
                    pool.submit(_grab_error, other, never, 10.0)
                    for other in others
                    for _ in range(MAX_WAITING_PER_CALLER)
                ]
                # once every slot is taken, the next waiting request is refused `busy` at once
                deadline = time.monotonic() + 8.0
                while node.call_typed(key, STATUS, NoArgs(), timeout=5.0).waiting < MAX_WAITING:
                    assert time.monotonic() < deadline, "the pending grabs are not all waiting"
                    time.sleep(0.02)
                start = time.monotonic()
                error = _grab_error(node, probe, 2.0)
                assert error is not None and error.code == "busy", error
                assert time.monotonic() - start < 1.0
                assert "(the most it takes)" in error.message
                assert "try again later" in error.message
                # one caller past its own bound is told so
                error = _grab_error(others[0], probe, 2.0)
                assert error is not None and error.code == "busy", error
                assert "from 'caller0'" in error.message, error.message
                # the port's blocking verbs still run: a calibration frame is rendered meanwhile
                start = time.monotonic()
                marks = node.call_typed(key, CALIBRATION, NoArgs(), timeout=30.0)
                assert marks.image.width == 320
                assert time.monotonic() - start < 8.0
                assert node.call_typed(key, STATUS, NoArgs(), timeout=5.0).source == "mujoco"
                ends = [future.result() for future in pending]
        finally:
            for other in others:
                other.close()
        # each pending grab ended at its timeout
        assert all(e is not None and e.code == "timeout" for e in ends), ends


def test_a_grab_stops_waiting_when_its_caller_gives_up(net: NetConfig) -> None:
    with serving(run, _camera(net)), Node(None, net) as node:
        node.wait_alive(["camera"], timeout=30)
        never = GrabArgs(after_sim_time=NEVER, timeout=120.0)
        # every slot of its caller taken by calls that give up after 1 s though their grabs
        # ask for 120 s
        with ThreadPoolExecutor(MAX_WAITING_PER_CALLER) as pool:
            calls = range(MAX_WAITING_PER_CALLER)
            gone = list(pool.map(lambda _: _grab_error(node, never, 1.0), calls))
        # (the caller's own timeout, or the camera's reply that it stopped at that time)
        assert all(e is not None and e.code == RpcTimeout.code for e in gone), gone
        # none waits on: their slots are free within seconds, not 120 s
        key, deadline = node.keys.cam_rpc(), time.monotonic() + 10.0
        while node.call_typed(key, STATUS, NoArgs(), timeout=5.0).waiting:
            assert time.monotonic() < deadline, "grabs wait on after their callers gave up"
            time.sleep(0.02)
        error = _grab_error(node, GrabArgs(after_sim_time=NEVER, timeout=1.0), 5.0)
        assert error is not None and error.code == "timeout", error
        # and a plain grab gets its frame
        image = node.call_typed(node.keys.cam_rpc(), GRAB, GrabArgs(timeout=20.0), timeout=20.0)
        assert image.width == 320


@pytest.mark.parametrize(
    ("identity", "verb", "named", "allowed"),
    [
        (VIEWER, "grab", VIEWER, True),
        (VIEWER, "grab", "detector", False),  # a grab names its own caller, none other
        (VIEWER, "grab", None, False),
        (VIEWER, "calibration", None, True),
        (OPERATOR, "grab", OPERATOR, True),
        ("detector", "grab", "detector", True),
        ("learner", "grab", "learner", False),
        ("stranger", "grab", "stranger", False),
    ],
)
def test_granted_follows_the_rules_a_timeout_is_not_called_denied(
    identity: str, verb: str, named: str | None, allowed: bool
) -> None:
    keys = Keys("icubSim")
    assert granted("icubSim", identity, verb_key(keys.cam_rpc(), verb, named)) is allowed


def test_granted_for_moving_verbs() -> None:
    keys = Keys("icubSim")
    assert not granted("icubSim", VIEWER, verb_key(keys.archery_rpc(), "release"))
    assert granted("icubSim", "learner", verb_key(keys.archery_rpc(), "release"))
    assert granted("icubSim", OPERATOR, verb_key(keys.archery_rpc(), "release"))
