"""The read side of a YARP robot's body (`services/robot/yarp_parts.py`) and `archery selfcheck
--body yarp`, against YARP's own devices: YARP 3.5's `fakeMotionControl` behind
`controlboardwrapper2`, one `yarpdev` per part, with iCub's axis names (an arm's 16: the arm's 7
and the hand's 9), in an order of their own; on YARP's own `yarpserver`, on loopback."""

from __future__ import annotations

import math
import random
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator, Sequence
from pathlib import Path

import pytest

from archery.apps.yarp.network import stop_group
from archery.protocol.parts import PARTS
from archery.services.robot.yarp_parts import (
    ENCODER_MARGIN,
    STREAM_CARRIER,
    BodyError,
    PartAxes,
    check_encoders,
    map_axes,
    open_parts,
    project_limits,
)
from tests.conftest import archery
from tests.ros2_sdk import until
from tests.yarp_setup import YarpSetup

yarp = pytest.importorskip("yarp", reason="YARP's bindings: `make setup` builds and installs them")

ROOT = Path(__file__).resolve().parents[1]
HAND = ("hand_finger", "thumb_oppose", "thumb_proximal", "thumb_distal", "index_proximal",
        "index_distal", "middle_proximal", "middle_distal", "pinky")  # fmt: skip


def _arm(side: str) -> list[str]:
    """An iCub arm's 16 axis names (`side`: "l" or "r"), in iCub's order."""
    part = {"l": "left_arm", "r": "right_arm"}[side]
    return [*PARTS[part], *(f"{side}_{name}" for name in HAND)]


def _shuffled(names: Sequence[str], seed: int) -> list[str]:
    out = list(names)
    random.Random(seed).shuffle(out)
    return out


#: the robots the tests run, YARP name → part → its axis names in the robot's order
FAKE = {
    "torso": list(reversed(PARTS["torso"])),
    "left_arm": _shuffled(_arm("l"), 3),
    "right_arm": _arm("r"),
}
BAD = {**FAKE, "left_arm": [name.replace("l_elbow", "l_elbow_joint") for name in _arm("l")]}
ROBOTS = {"/fake": FAKE, "/bad": BAD, "/zero": {"left_arm": _arm("l")}}


def _fake_motion_control() -> bool:
    out = subprocess.run(
        [str(Path(sys.executable).parent / "yarpdev"), "--list"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    return "fakeMotionControl" in out.stdout + out.stderr


def _pose() -> dict[str, float]:
    """A posture (rad) with a value of its own for each joint, within its limits."""
    limits = project_limits()
    out = {}
    for names in PARTS.values():
        for k, name in enumerate(names):
            lower, upper = limits[name]
            out[name] = lower + (k + 1) / (len(names) + 2) * (upper - lower)
    return out


POSE = _pose()
HAND_ANGLE = 33.0  # deg, the hands' axes (no joint of the contract)


class Board:
    """YARP's `remote_controlboard` on a fake part, as the tests' own client."""

    def __init__(self, remote: str, local: str) -> None:
        options = yarp.Property()
        options.put("device", "remote_controlboard")
        options.put("remote", remote)
        options.put("local", local)
        options.put("carrier", STREAM_CARRIER)  # as the body: no udp port numbers held after
        self.driver = yarp.PolyDriver(options)
        assert self.driver.isValid(), f"remote_controlboard did not open {remote}"
        self.encoders = self.driver.viewIEncoders()
        self.axes = self.encoders.getAxes()

    def read(self) -> list[float]:
        """Every axis now (deg)."""
        values = yarp.Vector(self.axes)
        until(lambda: self.encoders.getEncoders(values.data()), "the encoders", timeout=10)
        return [values[i] for i in range(self.axes)]

    def pose(self, names: Sequence[str]) -> None:
        """Each axis to its value of `POSE` (the hand's to `HAND_ANGLE`), and wait until read."""
        goal = [math.degrees(POSE[name]) if name in POSE else HAND_ANGLE for name in names]
        position = self.driver.viewIPositionControl()
        for axis, value in enumerate(goal):
            assert position.positionMove(axis, value)
        until(
            lambda: all(abs(a - b) < 1e-6 for a, b in zip(self.read(), goal, strict=True)),
            "the fake part at its posture",
            timeout=10,
        )

    def close(self) -> None:
        self.driver.close()


class Robots:
    """YARP's name server and a `yarpdev` per part of each of `ROBOTS`."""

    def __init__(self, setup: YarpSetup, tmp: Path) -> None:
        self.procs: list[subprocess.Popen[bytes]] = []
        self.logs: list[Path] = []
        self.setup = setup
        self.server = f"127.0.0.1:{setup.port}"
        try:
            # one after another: YARP 3.5's name server, registering ports of several processes
            # starting at once, once gave one of them an address it could not take
            for remote, parts in ROBOTS.items():
                for part, names in parts.items():
                    self._device(tmp, f"{remote}/{part}", names)
                    until(
                        lambda name=f"{remote}/{part}/stateExt:o": self._registered(name),
                        f"{remote}/{part} registered",
                        timeout=30,
                    )
            for part, names in FAKE.items():
                board = Board(f"/fake/{part}", f"/test/pose/{part}")
                try:
                    board.pose(names)
                finally:
                    board.close()
        except BaseException:
            self.close()
            raise

    def _registered(self, name: str) -> bool:
        """Whether `name` is registered; raises as soon as a `yarpdev` has ended."""
        for proc, log in zip(self.procs, self.logs, strict=True):
            if proc.poll() is not None:
                tail = log.read_text(errors="replace").splitlines()[-5:]
                raise AssertionError(f"yarpdev ended with {proc.returncode}: {tail}")
        return bool(yarp.Network.queryName(name).isValid())

    def _device(self, tmp: Path, name: str, axes: Sequence[str]) -> None:
        conf = tmp / f"{name.strip('/').replace('/', '_')}.ini"
        conf.write_text(
            "device controlboardwrapper2\nsubdevice fakeMotionControl\n"
            f"name {name}\nperiod 10\n[GENERAL]\nJoints {len(axes)}\n"
            f"AxisName {' '.join(axes)}\n"
        )
        self.logs.append(tmp / f"{conf.stem}.log")
        log = self.logs[-1].open("wb")
        self.procs.append(
            subprocess.Popen(
                [self.setup.tool("yarpdev"), "--from", str(conf)],
                env=self.setup.env,
                stdin=subprocess.DEVNULL,
                stdout=log,
                stderr=subprocess.STDOUT,
                start_new_session=True,  # the launcher and yarpdev: one group, stopped together
            )
        )

    def read(self, remote: str) -> dict[str, list[float]]:
        """Every axis of each part of `remote` now (deg), through the tests' own clients."""
        out = {}
        for part in ROBOTS[remote]:
            board = Board(f"{remote}/{part}", f"/test/read{time.monotonic_ns()}/{part}")
            try:
                out[part] = board.read()
            finally:
                board.close()
        return out

    def close(self) -> None:
        for proc in self.procs:
            stop_group(proc)


@pytest.fixture(scope="module")
def name_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[YarpSetup]:
    """YARP's own name server on loopback, this process's YARP pointed at it."""
    setup = YarpSetup(yarp, tmp_path_factory.mktemp("yarp_body_server"))
    try:
        yield setup
    finally:
        setup.close()


@pytest.fixture(scope="module")
def robots(name_server: YarpSetup, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Robots]:
    if not _fake_motion_control():
        pytest.skip("this YARP has no fakeMotionControl device (tools/yarp_wheel.py builds it)")
    running = Robots(name_server, tmp_path_factory.mktemp("yarp_body"))
    try:
        yield running
    finally:
        running.close()


def _selfcheck(*flags: str, timeout: float = 60) -> subprocess.CompletedProcess[str]:
    # YARP 3.5, once a device driver is open in this process, reaps every child on SIGCHLD:
    # `subprocess` would then find the child gone and report status 0. Default again.
    signal.signal(signal.SIGCHLD, signal.SIG_DFL)
    return archery("selfcheck", "--body", "yarp", *flags, timeout=timeout)


# -- YARP's devices ---------------------------------------------------------------------------


def test_the_body_opens_maps_by_name_and_reads_the_encoders(
    robots: Robots, caplog: pytest.LogCaptureFixture
) -> None:
    limits = project_limits()
    with caplog.at_level("WARNING"):
        body = open_parts("/fake", local="/test/body", timeout=10)
    try:
        assert list(body.parts) == list(PARTS)
        for part, axes in body.parts.items():
            assert axes.board == f"/fake/{part}"
            assert list(axes.axes) == FAKE[part]
            assert [FAKE[part][i] for i in axes.index] == list(PARTS[part])
            # fakeMotionControl's getLimits fails: the project's limits, unchanged
            assert not axes.from_robot
            assert axes.lower == tuple(limits[name][0] for name in PARTS[part])
            assert axes.upper == tuple(limits[name][1] for name in PARTS[part])
        assert body.parts["left_arm"].unmapped == tuple(
            name for name in FAKE["left_arm"] if name not in PARTS["left_arm"]
        )
        assert len(body.parts["left_arm"].unmapped) == len(HAND)
        said = [r.getMessage() for r in caplog.records if "getLimits fails" in r.getMessage()]
        assert len(said) == 1, said  # said once for the whole body
        assert "torso, left_arm, right_arm" in said[0]
        now = body.encoders()
        for part, values in now.items():
            assert values == pytest.approx([POSE[name] for name in PARTS[part]], abs=1e-9)
    finally:
        body.close()


def test_an_arm_whose_axis_names_do_not_match_is_refused_naming_them(robots: Robots) -> None:
    with pytest.raises(BodyError) as refused:
        open_parts("/bad", {"left_arm": PARTS["left_arm"]}, local="/test/bad", timeout=10)
    message = str(refused.value)
    assert "\n" not in message
    assert "/bad/left_arm has no axis named l_elbow;" in message
    assert "'l_elbow_joint'" in message and "'l_pinky'" in message  # the axes it has
    out = _selfcheck("--remote", "/bad", "--yarp-server", robots.server)
    assert out.returncode == 2, out.stderr
    assert (
        out.stderr.strip()
        .splitlines()[-1]
        .startswith("archery selfcheck: /bad/left_arm has no axis named l_elbow;")
    )
    assert out.stdout == ""


def test_an_encoder_past_its_limits_is_refused(robots: Robots) -> None:
    """fakeMotionControl starts at 0°: an iCub elbow's limits start at 15°."""
    refused = r"/zero/left_arm l_elbow \(axis 3\) reads 0\.0°"
    with (
        open_parts("/zero", {"left_arm": PARTS["left_arm"]}, local="/test/zero") as body,
        pytest.raises(BodyError, match=refused),
    ):
        body.encoders()


def test_selfcheck_prints_the_body_and_moves_nothing(robots: Robots) -> None:
    before = robots.read("/fake")
    out = _selfcheck("--remote", "/fake", "--yarp-server", robots.server)
    assert out.returncode == 0, out.stderr
    lines = out.stdout.splitlines()
    assert lines[0].startswith("YARP body check of /fake")
    assert lines[-1] == "ok: 3 parts, 17 joints within their limits; nothing moved"
    assert (
        "left_arm /fake/left_arm: 16 axes, 7 mapped by name; limits: the project's (the "
        "robot's getLimits fails)" in lines
    )
    elbow = FAKE["left_arm"].index("l_elbow")
    row = next(line for line in lines if line.strip().startswith("l_elbow "))
    assert re.search(rf"axis +{elbow} +limits \[ +15\.2, +105\.8\]°", row), row
    assert f"now {math.degrees(POSE['l_elbow']):7.1f}°" in row
    hand = [name for name in FAKE["left_arm"] if name not in PARTS["left_arm"]]
    assert "  not mapped: " + ", ".join(hand) in lines  # in the robot's order
    assert sum("getLimits fails on" in line for line in out.stderr.splitlines()) == 1
    assert robots.read("/fake") == before  # the same values, to the last bit


def test_a_remote_that_does_not_exist_is_one_line(name_server: YarpSetup) -> None:
    server = f"127.0.0.1:{name_server.port}"
    started = time.monotonic()
    out = _selfcheck("--remote", "/nothere", "--yarp-server", server, "--timeout", "5")
    assert time.monotonic() - started < 30
    assert out.returncode == 2
    assert out.stderr.splitlines() == [
        "archery selfcheck: no control board at /nothere/torso, /nothere/left_arm, "
        f"/nothere/right_arm: the name server at {server} holds none of their rpc:i "
        "ports (is the robot up, and is its name /nothere? `yarp name list` lists the ports)"
    ]


# -- without YARP's devices -------------------------------------------------------------------


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


def test_a_name_server_that_does_not_answer_is_one_line_in_bounded_time() -> None:
    started = time.monotonic()
    out = _selfcheck("--yarp-server", f"127.0.0.1:{_free_port()}", "--timeout", "3")
    assert time.monotonic() - started < 30
    assert out.returncode == 2
    assert len(out.stderr.splitlines()) == 1, out.stderr
    assert out.stderr.startswith("archery selfcheck: no YARP name server answers at 127.0.0.1:")


def test_a_name_server_that_accepts_and_says_nothing_is_one_line_in_bounded_time() -> None:
    listener = socket.socket()
    listener.bind(("127.0.0.1", 0))
    listener.listen(8)
    held: list[socket.socket] = []
    stop = threading.Event()

    def silent() -> None:
        listener.settimeout(0.1)
        while not stop.is_set():
            try:
                held.append(listener.accept()[0])  # kept open, never answered
            except TimeoutError:
                continue

    thread = threading.Thread(target=silent, daemon=True)
    thread.start()
    try:
        started = time.monotonic()
        port = listener.getsockname()[1]
        out = _selfcheck("--yarp-server", f"127.0.0.1:{port}", "--timeout", "2")
        assert time.monotonic() - started < 30
        assert out.returncode == 2
        assert len(out.stderr.splitlines()) == 1, out.stderr
        assert out.stderr.startswith(f"archery selfcheck: the YARP name server at 127.0.0.1:{port}")
    finally:
        stop.set()
        thread.join()
        for conn in held:
            conn.close()
        listener.close()


@pytest.mark.parametrize(
    ("flags", "why"),
    [
        (["--remote", "icub"], "--remote 'icub': give the robot's YARP name"),
        (["--remote", "/icub", "--yarp-server", "nowhere"], "--yarp-server 'nowhere': give"),
        (["--yarp-server", "127.0.0.1:1", "--yarp-ip", "here"], "--yarp-ip 'here': give"),
        (["--echo"], "--echo and --connect are the mesh's check"),
        (["--body", "ros"], "argument --body: invalid choice"),
    ],
)
def test_bad_flags_are_refused_before_any_work(flags: list[str], why: str) -> None:
    out = _selfcheck(*flags)
    assert out.returncode == 2
    assert len(out.stderr.splitlines()) == 1, out.stderr
    assert why in out.stderr


def test_axes_are_mapped_by_name_never_by_index() -> None:
    axes = _shuffled(_arm("r"), 11)
    index = map_axes("/icub/right_arm", PARTS["right_arm"], axes)
    assert [axes[i] for i in index] == list(PARTS["right_arm"])
    with pytest.raises(
        BodyError, match=r"^/icub/right_arm has no axis named r_elbow, r_wrist_yaw;"
    ):
        kept = [name for name in axes if name not in {"r_elbow", "r_wrist_yaw"}]
        map_axes("/icub/right_arm", PARTS["right_arm"], kept)
    with pytest.raises(BodyError, match="names more than one axis r_elbow"):
        map_axes("/icub/right_arm", PARTS["right_arm"], [*axes, "r_elbow"])


def test_an_encoder_that_reads_nan_or_far_past_a_limit_is_refused() -> None:
    names = PARTS["torso"]
    limits = project_limits()
    axes = PartAxes(
        part="torso",
        board="/icub/torso",
        axes=tuple(names),
        joints=tuple(names),
        index=(0, 1, 2),
        lower=tuple(limits[n][0] for n in names),
        upper=tuple(limits[n][1] for n in names),
        from_robot=False,
    )
    upper = axes.upper[2]
    assert check_encoders(axes, [0.0, 0.0, upper + ENCODER_MARGIN * 0.9])  # within the margin
    with pytest.raises(BodyError, match=r"torso_roll \(axis 1\): its encoder reads nan"):
        check_encoders(axes, [0.0, math.nan, 0.0])
    with pytest.raises(BodyError, match=r"outside its limits .* by more than 2°"):
        check_encoders(axes, [0.0, 0.0, upper + ENCODER_MARGIN * 1.1])


def test_the_read_side_touches_no_command_interface() -> None:
    """What `yarp_parts` and the body check call of YARP reads: no position, velocity, direct,
    mode, torque, PWM or current command, no limit set, no encoder reset."""
    commands = re.compile(
        r"viewI(Position|Velocity|PositionDirect|ControlMode|Torque|PWM|Current|Impedance|"
        r"InteractionMode|RemoteCalibrator|ControlCalibration)|positionMove|velocityMove|"
        r"setPosition|setRef|setControlMode|setLimits|setEncoder|resetEncoder"
    )
    for path in ("services/robot/yarp_parts.py", "apps/topics/body_check.py"):
        assert not commands.search((ROOT / path).read_text()), path
