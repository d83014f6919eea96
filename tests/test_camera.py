"""The camera service over a real router: rendered frames of published world states, grab after
a sim time or a wall stamp, the folder and device sources, bad requests and settings."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import cv2
import msgspec
import numpy as np
import pytest

from archery.mesh.netflags import NetConfig
from archery.mesh.node import Node
from archery.protocol.errors import ConfigError, RpcError
from archery.protocol.messages import Array, Image, WorldState
from archery.services.camera.config import CameraConfig
from archery.services.camera.service import run
from archery.services.camera.sources import DeviceSource, SourceError, SourceSpec, parse_source
from archery.sim.arrow import arrow_quat
from archery.sim.model_build import build_scene
from archery.sim.render import SceneRenderer, project
from archery.sim.scene import ScenePhysics
from archery.sim.scene_config import TARGET_CENTRE_SITE, SceneConfig
from tests.camera_world import camera_with_world
from tests.conftest import archery, serving
from tests.rpc import rpc_call


def _image(result: object) -> Image:
    return msgspec.convert(result, Image)


@pytest.fixture(scope="module")
def physics() -> ScenePhysics:
    return ScenePhysics(build_scene(SceneConfig(meshes=False)))


def _state(qpos: np.ndarray, sim_time: float) -> WorldState:
    return WorldState(qpos=Array.from_numpy(qpos), phase="stuck", shot=1, sim_time=sim_time)


def test_grab_renders_a_world_state_at_or_after_the_asked_sim_time(
    net: NetConfig, physics: ScenePhysics
) -> None:
    config = CameraConfig(net=net, rate=20.0, robot_timeout=0.3)
    physics.reset()
    physics.forward()
    centre = physics.site_position(TARGET_CENTRE_SITE)
    stuck = centre + np.array([0.0, 0.08, -0.05])  # an arrow 8 cm right, 5 cm low
    with serving(run, config), Node(None, net) as node:
        keys = node.keys
        node.wait_alive(["camera"], timeout=30)
        frames = node.subscribe(keys.cam_frames(), Image)
        world = node.publisher(keys.world_state(), WorldState)
        # before any world state: frames of the model's initial state, without a sim time
        first = frames.wait_newer(10)
        assert first.sim_time is None and (first.width, first.height) == (1280, 720)
        with pytest.raises(RpcError) as missing:
            rpc_call(
                node, keys.cam_rpc(), "grab", {"after_sim_time": 0.0, "timeout": 0.3}, timeout=5
            )
        assert missing.value.code == "timeout" and "no frame with sim time" in str(missing.value)

        physics.set_arrow_pose(stuck, arrow_quat(np.array([-1.0, 0.0, -0.05])))
        assert world.wait_matched(5)
        world.put(_state(physics.qpos(), 2.5))
        grabbed = _image(
            rpc_call(node, keys.cam_rpc(), "grab", {"after_sim_time": 2.5}, timeout=10)
        )
        # the default encoding: the raw pixels in one LZ4 block (lossless, a fraction of the size)
        assert grabbed.sim_time == 2.5 and grabbed.encoding == "rgb8_lz4"
        assert len(grabbed.data) < 1280 * 720 * 3 / 10
        assert grabbed.stamp > 0 and grabbed.frame > first.frame
        pixels = grabbed.to_numpy()
        # the frame shows that state: the green tip where the arrow was put
        with SceneRenderer(SceneConfig(meshes=False)) as renderer:
            renderer.render(physics.qpos())
            tip = project(renderer, stuck[None])[0]
        col, row = np.round(tip).astype(int)
        patch = pixels[row - 12 : row + 13, col - 12 : col + 13].reshape(-1, 3).astype(int)
        green = (patch[:, 1] > 150) & (patch[:, 1] > patch[:, 0] + 60)
        assert green.sum() > 30

        # a later sim time: the grab waits for a state that reaches it
        threading.Timer(0.3, lambda: world.put(_state(physics.qpos(), 3.0))).start()
        later = _image(
            rpc_call(
                node, keys.cam_rpc(), "grab", {"after_sim_time": 2.9, "timeout": 5}, timeout=10
            )
        )
        assert later.sim_time == 3.0
        # and after a wall stamp: a frame whose capture started after it
        now = time.time()
        world.put(_state(physics.qpos(), 3.1))
        fresh = _image(rpc_call(node, keys.cam_rpc(), "grab", {"after_stamp": now}, timeout=10))
        assert fresh.stamp >= now

        status = rpc_call(node, keys.cam_rpc(), "status", timeout=5)
        assert status["source"] == "mujoco" and status["scene_from"] == "default"
        assert status["renders"] >= 2 and status["render_ms"] > 0 and status["errors"] == 0
        assert status["reuses"] >= 2  # 3.0 and 3.1 show the qpos of 2.5: not rendered again
        assert status["latest_sim_time"] >= 3.0

        for args, message in (
            ({"after": 1}, "unknown field `after`.*after_sim_time, after_stamp, timeout"),
            ({"after_sim_time": "soon"}, r"`\$.after_sim_time`.*got `str`.*must be float"),
            ({"timeout": 0}, r"timeout must be float in \(0, 120\]"),
        ):
            with pytest.raises(RpcError, match=message) as bad:
                rpc_call(node, keys.cam_rpc(), "grab", args, timeout=5)
            assert bad.value.code == "bad_request"

        # a world state of another scene is logged, never fatal
        world.put(_state(np.zeros(7), 4.0))
        world.put(_state(physics.qpos(), 4.1))
        assert _image(rpc_call(node, keys.cam_rpc(), "grab", {"after_sim_time": 4.1}, timeout=10))


def test_an_unwatched_camera_renders_only_for_a_grab_and_never_an_unchanged_scene(
    net: NetConfig, physics: ScenePhysics
) -> None:
    physics.reset()
    physics.forward()
    qpos = physics.qpos()
    with serving(run, CameraConfig(net=net, rate=20.0, robot_timeout=0.3)), Node(None, net) as node:
        keys = node.keys
        node.wait_alive(["camera"], timeout=30)
        world = node.publisher(keys.world_state(), WorldState)
        assert world.wait_matched(5)

        def status() -> dict:
            return rpc_call(node, keys.cam_rpc(), "status", timeout=5)

        def grab(**args: float) -> Image:
            return _image(rpc_call(node, keys.cam_rpc(), "grab", args, timeout=10))

        # a robot at rest, nobody watching: 1 s of states at 30/s and no frame at all
        for _ in range(30):
            world.put(_state(qpos, 1.0))
            time.sleep(1 / 30)
        idle = status()
        assert (idle["renders"], idle["reuses"], idle["frames"]) == (0, 0, 0)

        # a grab still gets a fresh frame of the newest state: one render
        assert grab(after_sim_time=1.0).sim_time == 1.0
        assert status()["renders"] == 1
        # the same qpos again, asked for after a stamp: the last render, stamped now (the grab
        # names the state's sim time too: it may reach the camera before the state does, and a
        # grab after a stamp alone is served by the newest state the camera knows)
        now = time.time()
        world.put(_state(qpos, 1.5))
        again = grab(after_sim_time=1.5, after_stamp=now)
        assert again.sim_time == 1.5 and again.stamp >= now
        after = status()
        assert (after["renders"], after["reuses"]) == (1, 1)

        # a subscriber appears: frames flow (at the rest rate: the scene is unchanged) without
        # renders
        frames = node.subscribe(keys.cam_frames(), Image, mode="fifo")
        got = [frames.get(timeout=10) for _ in range(3)]
        assert [f.frame for f in got] == sorted({f.frame for f in got})
        assert status()["renders"] == 1
        # the robot moving behind the camera changes nothing it sees: not rendered again
        turned = qpos.copy()
        turned[0] += 0.1  # the torso
        world.put(_state(turned, 1.5))
        assert grab(after_sim_time=1.5).sim_time == 1.5
        assert status()["renders"] == 1
        # an arrow on the face, in its view, is rendered again
        centre = physics.site_position(TARGET_CENTRE_SITE)
        on_face = centre + np.array([0.0, 0.05, 0.05])
        physics.set_arrow_pose(on_face, arrow_quat(np.array([-1.0, 0, -0.05])))
        world.put(_state(physics.qpos(), 2.0))
        assert grab(after_sim_time=2.0).sim_time == 2.0
        assert status()["renders"] == 2


def test_a_watched_unchanged_view_goes_out_at_the_rest_rate_and_a_change_at_once(
    net: NetConfig, physics: ScenePhysics
) -> None:
    physics.reset()
    physics.forward()
    qpos = physics.qpos()
    config = CameraConfig(net=net, rate=20.0, rest_rate=0.1, robot_timeout=0.3)
    with camera_with_world(config, _state(qpos, 1.0)) as (node, world):
        keys = node.keys
        frames = node.subscribe(keys.cam_frames(), Image, mode="fifo")
        first = frames.get(timeout=10)  # a new subscriber gets a frame at once
        while first.sim_time != 1.0:  # (one of the initial state may come first)
            first = frames.get(timeout=10)
        # the robot moving behind the camera: the same pixels, not sent again within 10 s;
        # then an arrow on the face: that frame at once, the next one the subscriber gets
        turned = qpos.copy()
        turned[0] += 0.1
        world.put(_state(turned, 1.5))
        centre = physics.site_position(TARGET_CENTRE_SITE)
        physics.set_arrow_pose(
            centre + np.array([0.0, 0.05, 0.05]), arrow_quat(np.array([-1.0, 0, -0.05]))
        )
        world.put(_state(physics.qpos(), 2.0))
        changed = frames.get(timeout=10)
        assert changed.sim_time == 2.0 and changed.frame == first.frame + 1
        assert changed.stamp - first.stamp < 1 / config.rest_rate
        # a grab of the unchanged view is still served at once, and the subscriber gets it too
        now = time.time()
        grabbed = _image(rpc_call(node, keys.cam_rpc(), "grab", {"after_stamp": now}, timeout=10))
        assert grabbed.stamp >= now and grabbed.sim_time == 2.0
        assert frames.get(timeout=10).frame == grabbed.frame


def test_calibration_marks_come_with_their_frame(net: NetConfig) -> None:
    with serving(run, CameraConfig(net=net, rate=5.0, robot_timeout=0.3)), Node(None, net) as node:
        node.wait_alive(["camera"], timeout=30)
        result = rpc_call(node, node.keys.cam_rpc(), "calibration", timeout=30)
        frame = _image(result["image"]).to_numpy()
        assert frame.shape == (720, 1280, 3)
        assert len(result["pixels"]["target"]) >= 100 and len(result["pixels"]["arrow"]) >= 8


def _write(folder: Path, name: str, colour: tuple[int, int, int]) -> None:
    cv2.imwrite(str(folder / name), np.full((48, 64, 3), colour[::-1], np.uint8))


def test_folder_source_replays_images_captured_after_the_request(
    net: NetConfig, tmp_path: Path
) -> None:
    _write(tmp_path, "a.png", (200, 0, 0))
    _write(tmp_path, "b.jpg", (0, 0, 200))
    (tmp_path / "notes.txt").write_text("not an image")
    config = CameraConfig(net=net, source=parse_source(f"folder:{tmp_path}"), rate=2.0)
    with serving(run, config), Node(None, net) as node:
        keys = node.keys
        node.wait_alive(["camera"], timeout=30)
        seen: dict[int, int] = {}  # frame number -> its dominant colour channel
        while len(set(seen.values())) < 2 and len(seen) < 8:
            now = time.time()
            image = _image(rpc_call(node, keys.cam_rpc(), "grab", {"after_stamp": now}, timeout=10))
            assert image.stamp >= now and image.sim_time is None
            assert (image.width, image.height) == (64, 48)
            seen[image.frame] = int(np.argmax(image.to_numpy()[24, 32]))
        assert set(seen.values()) == {0, 2}  # both files, in turn: a frame's parity gives its file
        assert len({(frame % 2, colour) for frame, colour in seen.items()}) == 2, seen
        # no sim time on real frames: after_sim_time means "captured after this request"
        asked = time.time()
        image = _image(rpc_call(node, keys.cam_rpc(), "grab", {"after_sim_time": 99.0}, timeout=10))
        assert image.stamp >= asked
        with pytest.raises(RpcError, match="only from the mujoco source") as refused:
            rpc_call(node, keys.cam_rpc(), "calibration", timeout=5)
        assert refused.value.code == "bad_request"


class _FakeCapture:
    """A stand-in for cv2.VideoCapture: frames numbered by how many were taken."""

    def __init__(self, opened: bool = True, fail: bool = False) -> None:
        self.opened, self.fail, self.taken, self.settings = opened, fail, 0, {}

    def isOpened(self) -> bool:  # OpenCV's name
        return self.opened

    def set(self, prop: int, value: float) -> bool:
        self.settings[prop] = value
        return True

    def grab(self) -> bool:
        self.taken += 1
        return True

    def read(self) -> tuple[bool, np.ndarray | None]:
        if self.fail:
            return False, None
        self.taken += 1
        frame = np.zeros((4, 6, 3), np.uint8)
        frame[..., 0] = self.taken  # blue channel in BGR
        return True, frame

    def release(self) -> None:
        self.opened = False


def test_device_source_drops_a_buffered_frame_when_a_fresh_one_is_asked() -> None:
    fake = _FakeCapture()
    device = DeviceSource(0, 1280, 720, capture=fake)
    assert fake.settings[cv2.CAP_PROP_FRAME_WIDTH] == 1280
    assert fake.settings[cv2.CAP_PROP_BUFFERSIZE] == 1
    assert device.read()[0, 0, 2] == 1  # RGB: the blue channel last
    assert device.read(fresh=True)[0, 0, 2] == 3  # frame 2 was dropped
    with pytest.raises(SourceError, match="returned no frame"):
        DeviceSource(1, 64, 48, capture=_FakeCapture(fail=True)).read()
    with pytest.raises(ConfigError, match="cannot be opened"):
        DeviceSource(7, 64, 48, capture=_FakeCapture(opened=False))


def test_bad_sources_and_settings_are_refused(tmp_path: Path) -> None:
    assert parse_source("device:2") == SourceSpec("device", index=2)
    for text, message in (
        ("webcam", "is not one of"),
        ("device:x", "is not one of"),
        (f"folder:{tmp_path / 'none'}", "is not a folder"),
    ):
        with pytest.raises(ConfigError, match=message):
            parse_source(text)
    with pytest.raises(ConfigError, match="--rate"):
        CameraConfig(rate=0.0)
    with pytest.raises(ConfigError, match="--rest-rate"):
        CameraConfig(rest_rate=0.0)
    with pytest.raises(ConfigError, match="--encoding"):
        CameraConfig(encoding="bmp")
    with pytest.raises(ConfigError, match="--size"):
        CameraConfig(width=8)


def test_the_command_line_explains_a_bad_source(tmp_path: Path) -> None:
    done = archery("camera", "--source", f"folder:{tmp_path}", "--connect", "tcp/127.0.0.1:9")
    assert done.returncode == 2 and "holds no image" in done.stderr
