"""The camera's scene view (`scene` on `ROBOT/cam/rpc:i`): the whole robot from the side
camera, of the world state the robot publishes, at a low rate, and nothing while nobody asks."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from types import SimpleNamespace
from typing import Any

import msgspec
import numpy as np
import pytest

from archery.mesh.netflags import NetConfig
from archery.mesh.node import Node
from archery.protocol.errors import BadRequest, RpcError
from archery.protocol.messages import Array, WorldState
from archery.protocol.verbs.base import NoArgs
from archery.protocol.verbs.camera import SCENE, STATUS, SceneReply
from archery.services.camera.config import CameraConfig
from archery.services.camera.scene_view import SIZE, SceneViews
from archery.services.camera.service import run
from archery.services.camera.sources import SourceSpec
from archery.sim.model_build import build_scene
from archery.sim.scene import ScenePhysics
from archery.sim.scene_config import SceneConfig
from archery.sim.scene_view import SceneView
from tests.camera_world import camera_with_world
from tests.conftest import serving

THREAD = "camera-scene-view"


def _state(qpos: np.ndarray, sim_time: float) -> WorldState:
    return WorldState(qpos=Array.from_numpy(qpos), phase="idle", sim_time=sim_time)


def _until(check: Callable[[], Any], timeout: float = 60.0) -> Any:
    """`check()`'s first true value, polled until `timeout` s (AssertionError then)."""
    deadline = time.monotonic() + timeout
    while True:
        value = check()
        if value:
            return value
        assert time.monotonic() < deadline, "the condition did not hold in time"
        time.sleep(0.05)


def _view_threads() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name == THREAD]


@pytest.fixture(scope="module")
def qpos() -> np.ndarray:
    physics = ScenePhysics(build_scene(SceneConfig(meshes=False)))
    physics.reset()
    physics.forward()
    return physics.qpos()


def test_the_view_shows_the_published_pose_at_a_low_rate_and_only_when_asked(
    net: NetConfig, qpos: np.ndarray
) -> None:
    config = CameraConfig(net=net, rate=10.0, robot_timeout=0.3)
    with camera_with_world(config, _state(qpos, 1.0)) as (node, world):
        keys = node.keys

        def scene() -> SceneReply:
            return node.call_typed(keys.cam_rpc(), SCENE, NoArgs(), timeout=5)

        # nobody asked yet: no thread, no view, no render
        assert not _view_threads()
        first = scene()
        assert first.renders == 0 and first.period > 0
        shown = _until(lambda: (reply := scene()).status == "ok" and reply)
        assert len(_view_threads()) == 1
        image = shown.image
        assert image is not None and image.encoding == "jpeg"
        assert (image.width, image.height) == SIZE and image.sim_time == 1.0
        # the view is the whole scene at that pose: as the simulator's own side view draws it
        raised = qpos.copy()
        raised[3:] += 0.3  # the joints after the torso's
        with SceneView(SceneConfig(), width=SIZE[0], height=SIZE[1]) as reference:
            expected = reference.render(qpos)
            expected_raised = reference.render(raised)

        def changed(a: np.ndarray, b: np.ndarray) -> float:
            """The share of pixels that differ by more than JPEG's loss."""
            return float((np.abs(a.astype(int) - b.astype(int)).sum(axis=2) > 60).mean())

        pose = changed(expected, expected_raised)  # what the robot's pose changes in the view
        assert pose > 0.002
        assert changed(image.to_numpy(), expected) < 0.25 * pose  # JPEG's loss on edges only

        # the robot moves: a later request shows it, rendered anew
        world.put(_state(raised, 2.0))
        moved = _until(lambda: (reply := scene()).image.sim_time == 2.0 and reply)
        assert moved.renders == shown.renders + 1
        assert changed(moved.image.to_numpy(), expected_raised) < 0.25 * pose

        # asked for as fast as it answers, the robot moving: at most one render per period
        before, started, asked = scene().renders, time.monotonic(), 0
        deadline = started + 120
        while scene().renders < before + 3:
            world.put(_state(raised + 0.01 * np.sin(time.monotonic()), time.monotonic()))
            asked += 1
            assert time.monotonic() < deadline
        took = time.monotonic() - started
        renders = scene().renders - before
        assert asked > 3 * renders and renders <= took / first.period + 1, (renders, took)
        # the capture thread rendered no target frame for it
        assert node.call_typed(keys.cam_rpc(), STATUS, timeout=5).renders == 0


def _fake_capture(world: Any, kind: str = "mujoco") -> SimpleNamespace:
    """What `SceneViews` reads of the camera's capture state: its world subscription (anything
    with `latest()`), its frame store (grabs waiting, frames stored), the robot's scene
    parameters and the source kind."""
    return SimpleNamespace(
        world=world,
        store=SimpleNamespace(waiting=list, count=0),
        scene=None,
        config=SimpleNamespace(source=SourceSpec(kind)),
    )


def test_the_view_is_freed_when_nobody_asks_for_a_while(qpos: np.ndarray) -> None:
    newest = SimpleNamespace(latest=lambda: _state(qpos, 0.5))
    views = SceneViews(_fake_capture(newest), period=0.1, idle=0.5, size=(160, 90))
    try:
        _until(lambda: views.reply().status == "ok")
        assert views.running
        _until(lambda: not views.running)  # no request for 0.5 s: the thread and view are gone
        assert views.reply().image is not None  # the last view is still answered at once
        _until(lambda: views.running)  # and a request starts it again
    finally:
        views.close()
    assert not views.running


def test_a_camera_that_does_not_render_refuses_the_view() -> None:
    views = SceneViews(_fake_capture(None, "folder"))
    with pytest.raises(BadRequest, match=r"only by the mujoco source.*folder"):
        views.reply()


@pytest.mark.parametrize(
    ("scene", "says"),
    [
        (
            msgspec.structs.replace(SceneConfig(meshes=False).to_status(), target_distance=-1.0),
            "target_distance",
        ),
        ({"root_height": 0.62}, "root_height"),  # not a Scene: any error is told, none hangs
    ],
    ids=["out-of-range", "not-a-scene"],
)
def test_a_view_that_cannot_be_built_says_why(qpos: np.ndarray, scene: Any, says: str) -> None:
    capture = _fake_capture(SimpleNamespace(latest=lambda: _state(qpos, 0.5)))
    capture.scene = scene
    views = SceneViews(capture, period=0.1)
    try:

        def refused() -> bool:
            try:
                views.reply()
            except BadRequest as exc:
                assert "cannot be rendered" in str(exc) and says in str(exc)
                return True
            return False

        _until(refused)
    finally:
        views.close()


def test_the_verb_over_the_mesh_refuses_a_folder_camera(net: NetConfig, tmp_path: Any) -> None:
    import cv2

    cv2.imwrite(str(tmp_path / "a.png"), np.zeros((20, 30, 3), np.uint8))
    config = CameraConfig(net=net, source=SourceSpec("folder", path=str(tmp_path)))
    with serving(run, config), Node(None, net) as node:
        node.wait_alive(["camera"], timeout=30)
        with pytest.raises(RpcError, match="only by the mujoco source") as refused:
            node.call_typed(node.keys.cam_rpc(), SCENE, NoArgs(), timeout=5)
        assert refused.value.code == "bad_request"


def test_no_view_is_rendered_while_the_learning_loop_waits_on_the_cpu(qpos: np.ndarray) -> None:
    world = SimpleNamespace(state=_state(qpos, 0.5))
    world.latest = lambda: world.state
    capture = _fake_capture(world)
    views = SceneViews(capture, period=0.1, idle=30.0, size=(160, 90))
    try:
        first = _until(lambda: (reply := views.reply()).status == "ok" and reply)
        # an arrow in flight: views put off
        flying = world.state = WorldState(
            qpos=Array.from_numpy(qpos + 0.01), phase="flying", shot=1, sim_time=1.0
        )
        held = views.held
        _until(lambda: views.reply() and views.held >= held + 3)
        assert views.reply().renders == first.renders
        # landed: still put off until the camera captured a frame (the detector's)
        world.state = WorldState(qpos=flying.qpos, phase="stuck", shot=1, sim_time=1.2)
        held = views.held
        _until(lambda: views.reply() and views.held >= held + 3)
        assert views.reply().renders == first.renders
        capture.store.count += 1  # the grab's frame
        landed = _until(lambda: (reply := views.reply()).image.sim_time == 1.2 and reply)
        assert landed.renders == first.renders + 1
        # a grab waiting: put off again
        world.state = WorldState(qpos=Array.from_numpy(qpos), phase="idle", shot=1, sim_time=2.0)
        capture.store.waiting = lambda: ["a grab"]
        held = views.held
        _until(lambda: views.reply() and views.held >= held + 3)
        assert views.reply().image.sim_time == 1.2
        capture.store.waiting = list
        _until(lambda: views.reply().image.sim_time == 2.0)
    finally:
        views.close()
