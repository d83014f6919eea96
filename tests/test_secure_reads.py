"""The finding of issue 48 in secure mode, through the commands docs/secure.md gives: `archery up
--secure DIR`, then 16 far-future grabs of the camera by the `viewer` identity (120 s each), then
`archery learn --secure DIR`: the session finishes with no abort, the viewer's grabs past its
share are refused `busy`, and a viewer naming another identity's caller reaches nobody."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

from archery.mesh.netflags import NetConfig
from archery.mesh.node import Node
from archery.mesh.router import free_tcp_endpoint
from archery.mesh.rpc_server import MAX_WAITING, MAX_WAITING_PER_CALLER
from archery.protocol.codec import encode
from archery.protocol.errors import Busy
from archery.protocol.keys import verb_key
from archery.protocol.messages import RpcRequest
from archery.protocol.verbs import NoArgs
from archery.protocol.verbs.camera import GRAB, STATUS, GrabArgs
from tests.conftest import archery
from tests.test_read_limits import _error
from tests.test_secure_session import _wait_for_line

ROLLOUTS = 3


@pytest.mark.slow
def test_a_viewers_far_future_grabs_leave_a_secure_session_its_frames(tmp_path: Path) -> None:
    deploy = tmp_path / "secrets"
    made = archery("keys", "init", str(deploy))
    assert made.returncode == 0, made.stderr
    endpoint = free_tcp_endpoint().replace("tcp/", "tls/")
    logs, runs = str(tmp_path / "logs"), str(tmp_path / "runs")
    up_args = ["up", "--secure", str(deploy), "--listen", endpoint, "--logs", logs, "--runs", runs]
    up = subprocess.Popen(
        [sys.executable, "-m", "archery.apps.cli", *up_args],
        stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        _wait_for_line(up, "all alive", timeout=60)
        net = NetConfig(connect=(endpoint,), secure=str(deploy), identity="viewer")
        never = GrabArgs(after_sim_time=1e9, timeout=120.0)
        with Node(None, net) as viewer, ThreadPoolExecutor(MAX_WAITING) as pool:
            key = viewer.keys.cam_rpc()
            grabs = [
                pool.submit(_error, lambda: viewer.call_typed(key, GRAB, never, timeout=40.0))
                for _ in range(MAX_WAITING)
            ]
            deadline = time.monotonic() + 20.0
            while sum(f.done() for f in grabs) < MAX_WAITING - MAX_WAITING_PER_CALLER:
                assert time.monotonic() < deadline, "the viewer's grabs past its share wait"
                time.sleep(0.05)
            busy = [f.result() for f in grabs if f.done()]
            assert all(e is not None and e.code == Busy.code for e in busy), busy
            status = viewer.call_typed(key, STATUS, NoArgs(), timeout=5.0)
            assert status.waiting == MAX_WAITING_PER_CALLER
            secure = ["--secure", str(deploy), "--connect", endpoint]
            learn = archery("learn", *secure, "--rollouts", str(ROLLOUTS), "--no-until-hit")
            assert learn.returncode == 0, learn.stderr
            result = json.loads(learn.stdout.strip().splitlines()[-1])
            assert result["status"] == "finished", result
            assert result["rollouts"] == ROLLOUTS and result["aborted"] == 0, result
            # the viewer's grabs still wait: the session did not need their slots
            status = viewer.call_typed(key, STATUS, NoArgs(), timeout=5.0)
            assert status.waiting == MAX_WAITING_PER_CALLER
            # and the viewer cannot count its grabs as the detector's
            payload = encode(RpcRequest(verb="grab", args={"timeout": 1.0}, stamp=time.time()))
            as_detector = verb_key(key, "grab", "detector")
            assert not list(viewer.session.get(as_detector, payload=payload, timeout=3.0))
        up.send_signal(signal.SIGINT)
        _, err = up.communicate(timeout=60)
        assert up.returncode == 0, err
    finally:
        if up.poll() is None:
            up.kill()
            up.communicate(timeout=10)
