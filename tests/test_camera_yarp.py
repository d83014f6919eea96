"""The camera from a YARP image port (`--source yarp:/PORT`) against YARP's own devices: a real
target photograph served by `yarpdev --device grabberDual --subdevice fakeFrameGrabber` through
YARP's own `yarpserver` on loopback, read by a real `archery camera` process on a real router;
the frame on the mesh is the photograph's pixels, and the detector finds the target in it as in
the photograph (at 640x480 and 320x240, calibrated from pixels marked at that size). Bad input:
no such port, no name server, a silent port, a frame of another size: one error line each."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import cv2
import msgspec
import numpy as np
import pytest

from archery.apps.yarp.network import free_server_port, stop_group
from archery.mesh.netflags import NetConfig
from archery.mesh.node import Node
from archery.protocol.errors import ConfigError
from archery.protocol.messages import Image
from archery.services.camera.sources import SourceError, SourceSpec, YarpSource, parse_source
from archery.services.detector.calibration import sample_pixels
from archery.services.detector.colour_model import ColourModel
from archery.services.detector.detect import Detector
from tests.ros2_sdk import until
from tests.rpc import rpc_call
from tests.yarp_setup import YarpSetup

yarp = pytest.importorskip("yarp", reason="YARP's bindings: `make setup` builds and installs them")

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "real-targets"
PHOTO = 2  # the photograph served, and whose marked pixels calibrate the detector
ROWS = (360, 1080)  # the photograph's rows kept (960x1280 portrait): 960x720, 4:3 like a camera
WAIT = 60.0  # s: the bound of every wait on a condition


@pytest.fixture(scope="module")
def yarp_net(tmp_path_factory: pytest.TempPathFactory) -> Iterator[YarpSetup]:
    setup = YarpSetup(yarp, tmp_path_factory.mktemp("yarp"))
    try:
        yield setup
    finally:
        setup.close()


def _photo(width: int, height: int) -> tuple[np.ndarray, list[list[float]], np.ndarray, float]:
    """Photo `PHOTO` cropped to `ROWS` and scaled to `width`x`height` px: its RGB pixels, its
    calibration marks, centre (px) and blue ring's diameter (px) at that size."""
    truth = json.loads((DATA / f"target-{PHOTO}.json").read_text())
    photo = cv2.imread(str(DATA / truth["image"]), cv2.IMREAD_COLOR)
    assert photo is not None
    bgr = photo[ROWS[0] : ROWS[1]]
    scale = width / bgr.shape[1]
    assert abs(height / bgr.shape[0] - scale) < 1e-9
    rgb = cv2.resize(bgr, (width, height), interpolation=cv2.INTER_AREA)[:, :, ::-1]
    marks = [[x * scale, (y - ROWS[0]) * scale] for x, y in truth["calibration"]["target"]]
    centre = (np.array(truth["centre_px"]) - [0, ROWS[0]]) * scale
    return np.ascontiguousarray(rgb), marks, centre, truth["blue_ring_outer_diameter_px"] * scale


@contextmanager
def _grabber(setup: YarpSetup, rgb: np.ndarray, name: str, folder: Path) -> Iterator[None]:
    """YARP's own fake frame grabber serving `rgb` (as a .ppm file) on the port `name`."""
    ppm = folder / f"{name.strip('/').replace('/', '-')}.ppm"
    assert cv2.imwrite(str(ppm), rgb[:, :, ::-1])
    with (folder / "yarpdev.log").open("a") as log:
        proc = subprocess.Popen(
            [setup.tool("yarpdev"), "--device", "grabberDual", "--subdevice", "fakeFrameGrabber",
             "--src", str(ppm), "--mode", "[none]", "--period", "50", "--name", name,
             "--fakeFrameGrabber_rpc_port", f"{name}/grabber/rpc"],
            env=setup.env, stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT,
            start_new_session=True,  # YARP's launcher script and the device: one group
        )  # fmt: skip
    try:
        until(lambda: proc.poll() is not None or yarp.Network.exists(name, True), name, WAIT)
        assert proc.poll() is None, (folder / "yarpdev.log").read_text()[-2000:]
        yield
    finally:
        stop_group(proc)


def _camera(*flags: str) -> list[str]:
    return [sys.executable, "-m", "archery.apps.cli", "camera", *flags]


def _fails(
    setup: YarpSetup, net: NetConfig, source: str, *flags: str, env: dict[str, str] | None = None
) -> str:
    """`archery camera --source SOURCE` on the mesh of `net`, which must end at once, with a
    status of failure: the last line it writes on stderr."""
    signal.signal(signal.SIGCHLD, signal.SIG_DFL)  # YARP's ports ignore it: statuses read 0
    done = subprocess.run(
        _camera("--source", source, "--connect", net.connect[0], "--robot", net.robot, *flags),
        env=env or setup.env,
        capture_output=True,
        text=True,
        timeout=WAIT,
        stdin=subprocess.DEVNULL,
    )
    assert done.returncode == 1, done.stderr
    return done.stderr.strip().splitlines()[-1]


@pytest.mark.skipif(
    not (DATA / f"target-{PHOTO}.json").is_file(),
    reason=f"the real target photographs are not at {DATA} (clone the repo beside shared/)",
)
@pytest.mark.parametrize("size", [(640, 480), (320, 240)])
def test_a_yarp_camera_port_on_the_mesh_and_the_detector_finds_the_target(
    yarp_net: YarpSetup, net: NetConfig, tmp_path: Path, size: tuple[int, int]
) -> None:
    rgb, marks, centre, diameter = _photo(*size)
    name = f"/test/cam{size[0]}"
    with _grabber(yarp_net, rgb, name, tmp_path):
        with (tmp_path / "camera.log").open("w") as log:
            camera = subprocess.Popen(
                _camera("--source", f"yarp:{name}", "--connect", net.connect[0],
                        "--robot", net.robot, "--rate", "5"),
                env=yarp_net.env, stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT,
            )  # fmt: skip
        try:
            with Node(None, net) as node:
                node.wait_alive(["camera"], timeout=WAIT)
                keys = node.keys
                frames = node.subscribe(keys.cam_frames(), Image)
                streamed = frames.wait_newer(WAIT).to_numpy()
                asked = time.time()
                reply = rpc_call(node, keys.cam_rpc(), "grab", {"after_stamp": asked}, timeout=30)
                grabbed = msgspec.convert(reply, Image).to_numpy()
                status = rpc_call(node, keys.cam_rpc(), "status", timeout=10)
        finally:
            signal.signal(signal.SIGCHLD, signal.SIG_DFL)  # its status, not 0 (YARP ignores it)
            camera.terminate()
            assert camera.wait(timeout=WAIT) == 0, (tmp_path / "camera.log").read_text()
    assert status["source"] == "yarp" and status["errors"] == 0
    # the photograph's pixels, exactly (lossless on YARP's wire and the mesh's rgb8_lz4)
    for frame in (streamed, grabbed):
        assert frame.shape == (size[1], size[0], 3)
        np.testing.assert_array_equal(frame, rgb)
    # calibrated by pixels marked at this size, the detector finds the centre in the frame as
    # in the photograph itself
    detector = Detector(ColourModel.fit(sample_pixels(rgb, marks, "target")))
    on_mesh, on_file = detector.detect(grabbed), detector.detect(rgb)
    assert on_mesh.target is not None and on_file.target is not None
    assert on_mesh.target.px == on_file.target.px
    assert on_mesh.target.confidence > 0.9
    error = float(np.hypot(*np.subtract(on_mesh.target.px, centre)))
    assert error <= 0.02 * diameter, (error, diameter)


def test_a_port_of_another_size_later_and_any_size_read_exactly(yarp_net: YarpSetup) -> None:
    out = yarp.BufferedPortImageRgb()
    assert out.open("/test/sizes:o")
    source = YarpSource("/test/sizes:o", 5.0)
    try:
        assert source.size is None
        until(lambda: out.getOutputCount() == 1, "the camera's connection", WAIT)
        rng = np.random.default_rng(7)
        sent = rng.integers(0, 256, (241, 321, 3), np.uint8)  # rows YARP pads to 968 bytes

        def write(pixels: np.ndarray) -> None:
            image = out.prepare()
            image.resize(pixels.shape[1], pixels.shape[0])
            for y in range(pixels.shape[0]):
                for x in range(pixels.shape[1]):
                    pixel = image.pixel(x, y)
                    pixel.r, pixel.g, pixel.b = (int(v) for v in pixels[y, x])
            out.write()

        write(sent)
        np.testing.assert_array_equal(source.read(), sent)
        assert source.size == (321, 241)
        write(sent[:240, :320])
        with pytest.raises(
            SourceError, match=r"yarp:/test/sizes:o: a 320x240 px frame after 321x241"
        ):
            source.read()
        source.timeout = 0.2
        with pytest.raises(SourceError, match=r"yarp:/test/sizes:o: no frame within 0.2 s"):
            source.read(fresh=True)
    finally:
        source.close()
        out.close()


def test_no_such_port_and_a_silent_one_are_one_error_line_each(
    yarp_net: YarpSetup, net: NetConfig
) -> None:
    line = _fails(yarp_net, net, "yarp:/test/nowhere")
    assert line.startswith("archery camera: --source yarp:/test/nowhere: no port /test/nowhere")
    silent = yarp.BufferedPortImageRgb()
    assert silent.open("/test/silent:o")
    try:
        line = _fails(yarp_net, net, "yarp:/test/silent:o", "--frame-timeout", "0.5")
        assert line == "archery camera: --source yarp:/test/silent:o: no frame within 0.5 s"
    finally:
        silent.close()


def test_a_name_server_that_does_not_answer_is_one_error_line(
    yarp_net: YarpSetup, net: NetConfig, tmp_path: Path
) -> None:
    port = free_server_port("127.0.0.1")  # nothing listens there
    (tmp_path / "yarp.conf").write_text(f"127.0.0.1 {port} yarp\n")
    env = {**yarp_net.env, "YARP_CONFIG_HOME": str(tmp_path)}
    line = _fails(yarp_net, net, "yarp:/icub/cam/left", env=env)
    assert line == (
        f"archery camera: --source yarp:/icub/cam/left: the YARP name server at "
        f"127.0.0.1:{port} does not answer"
    )


def test_yarp_sources_are_parsed() -> None:
    assert parse_source("yarp:/icub/cam/left") == SourceSpec("yarp", port="/icub/cam/left")
    for text in ("yarp:", "yarp:icub/cam", "yarp:/a b", "yarp:/"):
        with pytest.raises(ConfigError, match="YARP image port"):
            parse_source(text)
