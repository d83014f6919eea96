"""Every CLI verb against a live node over a real router."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest

from archery.apps.topics.selfcheck import ECHO_SERVICE, run_echo
from archery.mesh.netflags import NetConfig
from archery.mesh.node import Node
from archery.protocol.messages import Image
from archery.protocol.parts import PARTS
from archery.protocol.verbs.robot import PART_VERBS
from tests.conftest import archery, serving


@pytest.fixture
def echo(net: NetConfig) -> Iterator[NetConfig]:
    """The sample service as a real child process."""
    argv = [sys.executable, "-m", "archery.apps.cli", "selfcheck", "--echo", "--robot", net.robot]
    argv += ["--connect", net.connect[0]]
    proc = subprocess.Popen(argv, stdin=subprocess.DEVNULL)
    with Node(None, net) as node:
        node.wait_alive([ECHO_SERVICE], 30)
    yield net
    proc.terminate()
    assert proc.wait(10) == 0


def _flags(net: NetConfig) -> list[str]:
    return ["--connect", net.connect[0], "--robot", net.robot]


def test_ports_lists_live_services(echo: NetConfig) -> None:
    out = archery("ports", *_flags(echo))
    assert out.returncode == 0, out.stderr
    assert "echo  (pid" in out.stdout
    verbs = ", ".join(PART_VERBS.names())
    assert f"rpc    {echo.robot}/torso/rpc:i  [RpcRequest]  verbs: {verbs}" in out.stdout
    assert f"pub    {echo.robot}/torso/state:o  [JointState]" in out.stdout
    as_json = archery("ports", "--json", *_flags(echo))
    assert json.loads(as_json.stdout.splitlines()[0])["service"] == "echo"


def test_ports_with_nothing_alive(net: NetConfig) -> None:
    out = archery("ports", *_flags(net), "--timeout", "0.5")
    assert out.returncode == 0 and f"no service alive on robot {net.robot!r}" in out.stderr


def test_ports_without_a_robot_lists_every_robot_of_the_fleet(net: NetConfig) -> None:
    """Two robots on one router (a fleet's `ROBOT1`, `ROBOT2`): plain `ports` groups both by
    prefix; `--robot` narrows it; a robot with nothing alive names the ones that are."""
    fleet = [dataclasses.replace(net, robot=f"{net.robot}f{i}") for i in (1, 2)]
    with serving(run_echo, fleet[0]), serving(run_echo, fleet[1]):
        for robot in fleet:
            with Node(None, robot) as node:
                node.wait_alive([ECHO_SERVICE], 30)
        every = archery("ports", "--connect", net.connect[0])
        one = archery("ports", *_flags(fleet[1]))
        none = archery("ports", *_flags(net), "--timeout", "0.5")
        as_json = archery("ports", "--json", "--connect", net.connect[0])
    assert every.returncode == 0, every.stderr
    for robot in fleet:
        assert f"== robot {robot.robot}: 1 services" in every.stdout
        assert f"{robot.robot}/torso/state:o" in every.stdout
    assert f"{fleet[1].robot}/torso" in one.stdout and f"{fleet[0].robot}/" not in one.stdout
    assert "== robot" not in one.stdout
    assert f"no service alive on robot {net.robot!r}" in none.stderr
    assert f"{fleet[0].robot}, {fleet[1].robot}" in none.stderr and "--robot NAME" in none.stderr
    robots = {json.loads(line)["robot"] for line in as_json.stdout.splitlines()}
    assert {r.robot for r in fleet} <= robots


def test_read_prints_json_lines(echo: NetConfig) -> None:
    out = archery("read", f"{echo.robot}/torso/state:o", "--count", "3", *_flags(echo))
    assert out.returncode == 0, out.stderr
    lines = [json.loads(line) for line in out.stdout.splitlines()]
    assert len(lines) == 3 and all(m["type"] == "JointState" for m in lines)
    assert lines[0]["names"] == ["torso_yaw", "torso_roll", "torso_pitch"]
    assert lines[0]["seq"] < lines[1]["seq"] < lines[2]["seq"]


def test_read_rejects_rpc_and_unknown_keys(net: NetConfig) -> None:
    out = archery("read", f"{net.robot}/torso/rpc:i", *_flags(net))
    assert out.returncode == 2 and "not a stream; use `archery rpc`" in out.stderr
    out = archery("read", f"{net.robot}/legs/state:o", *_flags(net))
    assert out.returncode == 2 and "unknown key" in out.stderr


def test_write_publishes_a_typed_message(echo: NetConfig) -> None:
    command = json.dumps({"part": "torso", "position": [0.1, 0.0, -0.1]})
    out = archery("write", f"{echo.robot}/torso/command:i", command, *_flags(echo))
    assert out.returncode == 0, out.stderr
    assert json.loads(out.stdout)["type"] == "JointCommand"
    count = archery("rpc", f"{echo.robot}/torso/rpc:i", "counters", *_flags(echo))
    counters = json.loads(count.stdout)
    assert (counters["accepted"], counters["undecodable"]) == (1, 0)


@pytest.mark.parametrize(
    ("payload", "error"),
    [
        ('{"part": "torso", "position": [NaN, 0, 0]}', "NaN is not a finite number"),
        ('{"part": "torso", "position": "up"}', "invalid JointCommand"),
        ("{not json", "not valid JSON"),
    ],
)
def test_write_rejects_bad_messages(echo: NetConfig, payload: str, error: str) -> None:
    out = archery("write", f"{echo.robot}/torso/command:i", payload, *_flags(echo))
    assert out.returncode == 2 and error in out.stderr


def test_rpc_ok_error_and_timeout(echo: NetConfig) -> None:
    key = f"{echo.robot}/torso/rpc:i"
    out = archery("rpc", key, "setRefSpeeds", '{"speeds": [1, 2, 0.5]}', *_flags(echo))
    assert out.returncode == 0, out.stderr
    assert json.loads(out.stdout) == {"names": list(PARTS["torso"]), "speeds": [1.0, 2.0, 0.5]}
    out = archery(
        "rpc", key, "positionMove", '{"position": [0.1]}', *_flags(echo)
    )  # refused by the service as wrong: bad input
    assert out.returncode == 2 and "positionMove needs one position per joint" in out.stderr
    out = archery("rpc", key, "jump", *_flags(echo))  # bad input: refused before it is sent
    assert out.returncode == 2 and "no verb 'jump'; verbs: checkMotionDone" in out.stderr
    out = archery("rpc", f"{echo.robot}/learner/rpc:i", "status", *_flags(echo), "--timeout", "1")
    assert out.returncode == 1 and f"{echo.robot}/learner/rpc:i" in out.stderr
    out = archery("rpc", key, "getJointNames", "[1]", *_flags(echo))
    assert out.returncode == 2 and "must be a JSON object" in out.stderr


def test_tools_without_a_router_say_so(tmp_path: Path) -> None:
    from archery.mesh.router import free_tcp_endpoint

    out = archery("ports", "--connect", free_tcp_endpoint())
    assert out.returncode == 1 and "Is a router running there?" in out.stderr


def test_view_saves_the_next_image(net: NetConfig, tmp_path: Path) -> None:
    rgb = np.zeros((72, 128, 3), np.uint8)
    rgb[:, :, 0] = 200  # red
    rgb[10:20, 30:40] = (0, 255, 0)
    with Node("camera", net) as cam:
        pub = cam.publisher(cam.keys.cam_frames(), Image)
        cam.ready()
        stop = threading.Event()

        def stream() -> None:
            frame = 0
            while not stop.wait(0.02):
                frame += 1
                pub.put(Image.from_numpy(rgb, frame=frame))

        thread = threading.Thread(target=stream)
        thread.start()
        try:
            out_png = tmp_path / "frame.png"
            out = archery("view", cam.keys.cam_frames(), "--out", str(out_png), *_flags(net))
        finally:
            stop.set()
            thread.join()
    assert out.returncode == 0, out.stderr
    assert "128x72 rgb8" in out.stdout
    saved = cv2.imread(str(out_png))[:, :, ::-1]
    assert np.array_equal(saved, rgb)
    wrong = archery("view", f"{net.robot}/torso/state:o", "--out", "x.png", *_flags(net))
    assert wrong.returncode == 2 and "does not carry images" in wrong.stderr


def test_router_verb_and_selfcheck() -> None:
    out = archery("selfcheck", timeout=120)
    assert out.returncode == 0, out.stdout + out.stderr
    assert "9 passed, 0 failed" in out.stdout
    bad = archery("router", "--listen", "localhost:1")
    assert bad.returncode == 2 and "not a Zenoh endpoint" in bad.stderr


def test_unknown_verb_lists_the_verbs() -> None:
    out = archery("fly")
    assert out.returncode == 2 and "valid verbs: router, ports" in out.stderr
