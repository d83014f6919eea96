"""No read can starve a session: the camera's and detector's waiting requests are bounded per
caller identity, a waiting grab whose caller gave up is dropped, and `frame` is rate-limited
per identity. Real camera and detector services over the real router; the calls name their
caller as `archery` tools and services do (`Verb.names_caller`)."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import ExitStack, contextmanager
from pathlib import Path

import pytest

from archery.mesh.netflags import NetConfig
from archery.mesh.node import Node
from archery.mesh.rates import RateLimit
from archery.mesh.rpc_server import MAX_WAITING, MAX_WAITING_PER_CALLER
from archery.protocol.codec import encode
from archery.protocol.errors import Busy, RpcError
from archery.protocol.messages import RpcRequest
from archery.protocol.verbs import NoArgs
from archery.protocol.verbs import detector as dv
from archery.protocol.verbs.camera import GRAB, STATUS, GrabArgs
from archery.services.camera.config import CameraConfig
from archery.services.camera.service import run as run_camera
from archery.services.detector.config import DetectorConfig
from archery.services.detector.service import run as run_detector
from tests.conftest import serving

NEVER = 1e9  # s of sim time: a world state no test publishes


def _as(net: NetConfig, identity: str) -> Node:
    """A node whose calls name `identity` as their caller."""
    return Node(None, dataclasses.replace(net, identity=identity))


@contextmanager
def _camera_and_detector(net: NetConfig, model: Path) -> Iterator[Node]:
    """Camera and detector on threads; yields the learner's node once its first measurement (the
    detector calibrating from the camera's marks) has answered."""
    camera = CameraConfig(net=net, robot_timeout=0.3, width=320, height=180)
    with ExitStack() as stack:
        stack.enter_context(serving(run_camera, camera))
        stack.enter_context(serving(run_detector, DetectorConfig(net=net, model=str(model))))
        learner = stack.enter_context(_as(net, "learner"))
        learner.wait_alive(["camera", "detector"], timeout=30)
        _measure(learner, timeout=60.0)
        yield learner


def _measure(node: Node, timeout: float = 10.0) -> float:
    """One measurement of a frame captured after now; its wall time (s)."""
    start = time.monotonic()
    args = dv.MeasureArgs(timeout=timeout - 2.0)
    node.call_typed(node.keys.detector_rpc(), dv.MEASURE, args, timeout=timeout)
    return time.monotonic() - start


def _error(call: object) -> RpcError | None:
    try:
        call()  # type: ignore[operator]
    except RpcError as exc:
        return exc
    return None


def _waiting(node: Node) -> int:
    return node.call_typed(node.keys.cam_rpc(), STATUS, NoArgs(), timeout=5.0).waiting


def test_a_viewers_far_future_grabs_leave_the_learners_measurement_its_frame(
    net: NetConfig, tmp_path: Path
) -> None:
    never = GrabArgs(after_sim_time=NEVER, timeout=120.0)
    with (
        _camera_and_detector(net, tmp_path / "model.json") as learner,
        _as(net, "viewer") as viewer,
        ThreadPoolExecutor(MAX_WAITING) as pool,
    ):
        key = viewer.keys.cam_rpc()
        grabs = [
            pool.submit(_error, lambda: viewer.call_typed(key, GRAB, never, timeout=8.0))
            for _ in range(MAX_WAITING)
        ]
        # the viewer holds its share of the waiting grabs, the rest of its grabs are refused
        deadline = time.monotonic() + 10.0
        while (
            _waiting(learner) < MAX_WAITING_PER_CALLER
            or sum(f.done() for f in grabs) < len(grabs) - MAX_WAITING_PER_CALLER
        ):
            assert time.monotonic() < deadline, "the viewer's grabs are neither waiting nor refused"
            time.sleep(0.02)
        busy = [f.result() for f in grabs if f.done()]
        assert all(e is not None and e.code == Busy.code for e in busy), busy
        assert all("from 'viewer'" in e.message for e in busy if e is not None), busy
        # the learner's measurement (the detector's grab) is not refused, and answers promptly
        for _ in range(3):
            assert _measure(learner) < 5.0
        assert _waiting(learner) == MAX_WAITING_PER_CALLER  # the viewer's still wait


def test_a_waiting_grab_whose_caller_gave_up_frees_its_slot(net: NetConfig) -> None:
    camera = CameraConfig(net=net, robot_timeout=0.3, width=320, height=180)
    with serving(run_camera, camera), _as(net, "viewer") as viewer:
        viewer.wait_alive(["camera"], timeout=30)
        key = viewer.keys.cam_rpc()
        # a raw request that does not say how long its caller waits, for a grab of 120 s; the
        # caller gives up after 1 s
        args = {"after_sim_time": NEVER, "timeout": 120.0}
        payload = encode(RpcRequest(verb="grab", args=args, stamp=time.time()))
        with ThreadPoolExecutor(MAX_WAITING_PER_CALLER) as pool:
            gone = list(
                pool.map(
                    lambda _: _error(
                        lambda: viewer.request(key, payload, verb="grab", timeout=1.0)
                    ),
                    range(MAX_WAITING_PER_CALLER),
                )
            )
        assert all(e is not None and e.code == "timeout" for e in gone), gone
        # its slots are free again within the camera's cap of an unsaid wait, not after 120 s
        start, deadline = time.monotonic(), time.monotonic() + 15.0
        while _waiting(viewer):
            assert time.monotonic() < deadline, "grabs wait on after their caller gave up"
            time.sleep(0.05)
        assert time.monotonic() - start < 10.0
        # and the same caller's next grab is not refused
        image = viewer.call_typed(key, GRAB, GrabArgs(timeout=20.0), timeout=20.0)
        assert image.width == 320


def test_a_frame_flood_is_refused_busy_and_the_learners_measurement_answers(
    net: NetConfig, tmp_path: Path
) -> None:
    calls = 200
    with (
        _camera_and_detector(net, tmp_path / "model.json") as learner,
        _as(net, "viewer") as viewer,
    ):
        key = viewer.keys.detector_rpc()
        frame = dv.FrameArgs(overlay=True)
        start = time.monotonic()
        with ThreadPoolExecutor(8) as pool:
            flood = [
                pool.submit(_error, lambda: viewer.call_typed(key, dv.FRAME, frame, timeout=30.0))
                for _ in range(calls)
            ]
            # meanwhile the learner measures promptly, and gets its own frame
            took = [_measure(learner) for _ in range(3)]
            own = learner.call_typed(key, dv.FRAME, frame, timeout=10.0)
            ends = [f.result() for f in flood]
        elapsed = time.monotonic() - start
        assert max(took) < 5.0, took
        assert own.png.startswith(b"\x89PNG")
        served = sum(e is None for e in ends)
        busy = [e for e in ends if e is not None and e.code == Busy.code]
        assert served + len(busy) == calls, [e for e in ends if e is not None][:3]
        assert served <= dv.FRAME_BURST + dv.FRAME_RATE * elapsed + 1, (served, elapsed)
        assert "'viewer' is past its rate of 2 calls/s" in busy[0].message, busy[0].message


def test_a_rate_limit_allows_a_burst_then_its_rate_per_identity() -> None:
    limit = RateLimit("a read", rate=1000.0, burst=3)
    for _ in range(3):
        limit.take("viewer")
    with pytest.raises(Busy, match="'viewer' is past its rate of 1000 calls/s"):
        limit.take("viewer")
    limit.take("learner")  # a bucket of its own
    deadline = time.monotonic() + 5.0
    while True:  # a token back after 1 ms
        try:
            limit.take("viewer")
            break
        except Busy:
            assert time.monotonic() < deadline
    assert limit.refused >= 1
    with pytest.raises(ValueError):
        RateLimit("a read", rate=0.0, burst=1)
