"""The landing from the camera alone over a real router: the camera service replays a folder
(`folder:` source, the frames a real camera would send: rendered frames of the scene with an
older arrow in the face) and the detector service measures: a baseline, then a new arrow
appears, moves, rests, and `measure` with the baseline gives the new arrow's r; a scene that
never changes ends in `no_landing` within the timeout; an unknown or expired baseline is a
bad request."""

from __future__ import annotations

import math
import os
import threading
import time
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from archery.mesh.netflags import NetConfig
from archery.mesh.node import Node
from archery.protocol.errors import RpcError
from archery.protocol.messages import Image
from archery.protocol.verbs.detector import KEPT_BASELINES
from archery.services.camera.config import CameraConfig
from archery.services.camera.service import run as run_camera
from archery.services.camera.sources import parse_source
from archery.services.detector.config import DetectorConfig
from archery.services.detector.service import run as run_detector
from tests.conftest import serving
from tests.rpc import rpc_call
from tests.test_detector_landing import NEW_R, Rendered, render_scenes


@pytest.fixture(scope="module")
def scenes() -> Rendered:
    return render_scenes()


class Scene:
    """The one picture of a `folder:` camera's folder, replaced at once (`os.replace`)."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        self.path = folder / "camera" / "frame.png"
        self.path.parent.mkdir()

    def show(self, rgb: np.ndarray) -> float:
        """Show `rgb` from now on; the wall time it was shown (s)."""
        staged = self.folder / "staged.png"
        assert cv2.imwrite(str(staged), np.ascontiguousarray(rgb[:, :, ::-1]))
        os.replace(staged, self.path)
        return time.time()


@contextmanager
def camera_and_detector(net: NetConfig, tmp_path: Path, rendered: Rendered) -> Iterator[Any]:
    """A `folder:` camera showing the older arrow, the detector with the scene's colour model,
    a node that sees both alive, and the folder's `Scene`."""
    scene = Scene(tmp_path)
    scene.show(rendered.old)
    model = tmp_path / "model.json"
    rendered.detector.model.save(str(model))
    camera = CameraConfig(net=net, source=parse_source(f"folder:{scene.path.parent}"), rate=20.0)
    with ExitStack() as stack:
        stack.enter_context(serving(run_camera, camera))
        detector = DetectorConfig(net=net, model=str(model), auto_calibrate=False)
        stack.enter_context(serving(run_detector, detector))
        node = stack.enter_context(Node(None, net))
        node.wait_alive(["camera", "detector"], timeout=30)
        yield node, scene


def test_a_new_arrow_that_lands_is_measured_not_the_older_one(
    net: NetConfig, tmp_path: Path, scenes: Rendered
) -> None:
    with camera_and_detector(net, tmp_path, scenes) as (node, scene):
        key = node.keys.detector_rpc()
        base = rpc_call(node, key, "baseline", {"timeout": 10}, timeout=15)
        assert base["baseline"] >= 1 and base["frame"] >= 1 and base["frame_stamp"] > 0
        frames = node.subscribe(node.keys.cam_frames(), Image)
        replies: list[Any] = []
        args = {"baseline": base["baseline"], "still_s": 1.0, "timeout": 30}
        measuring = threading.Thread(
            target=lambda: replies.append(rpc_call(node, key, "measure", args, timeout=40))
        )
        measuring.start()

        def frames_after(stamp: float, count: int) -> None:
            for _ in range(count):
                stamp = frames.wait_newer(10, lambda i, s=stamp: i.stamp > s).stamp

        frames_after(time.time(), 3)  # the scene as before, for a while
        frames_after(scene.show(scenes.moved), 2)  # the new arrow in flight, 3 cm off
        shown = scene.show(scenes.both)  # and at rest
        measuring.join(timeout=40)
        assert replies, "the measurement did not end"
        reply = replies[0]
        assert reply["status"] == "ok" and math.dist(reply["r_m"], NEW_R) < 0.01, reply
        # measured on a frame of the arrow at rest, still for the window asked
        assert reply["frame_stamp"] >= shown + 1.0 - 0.05
        assert reply["timing"]["wait_s"] >= 1.0 and reply["sim_time"] is None


def test_a_scene_that_never_changes_ends_in_no_landing_within_the_timeout(
    net: NetConfig, tmp_path: Path, scenes: Rendered
) -> None:
    with camera_and_detector(net, tmp_path, scenes) as (node, _):
        key = node.keys.detector_rpc()
        base = rpc_call(node, key, "baseline", {"timeout": 10}, timeout=15)["baseline"]
        started = time.monotonic()
        with pytest.raises(
            RpcError, match=rf"no landing seen in .* compared with baseline {base}"
        ) as no:
            rpc_call(node, key, "measure", {"baseline": base, "timeout": 1.5}, timeout=10)
        assert time.monotonic() - started < 1.5 + 2.0
        assert no.value.code == "no_landing" and "the picture was still" in no.value.message


def test_an_unknown_or_expired_baseline_is_a_bad_request(
    net: NetConfig, tmp_path: Path, scenes: Rendered
) -> None:
    with camera_and_detector(net, tmp_path, scenes) as (node, _):
        key = node.keys.detector_rpc()
        with pytest.raises(RpcError, match=r"no kept baseline 7: .*\(none yet\)") as unknown:
            rpc_call(node, key, "measure", {"baseline": 7, "timeout": 5}, timeout=10)
        assert unknown.value.code == "bad_request"
        ids = [
            rpc_call(node, key, "baseline", {"timeout": 10}, timeout=15)["baseline"]
            for _ in range(KEPT_BASELINES + 1)
        ]
        assert ids == list(range(1, KEPT_BASELINES + 2))  # increasing
        kept = ", ".join(str(n) for n in ids[1:])
        with pytest.raises(RpcError, match=rf"no kept baseline 1: .*\({kept}\)") as expired:
            rpc_call(node, key, "measure", {"baseline": 1, "timeout": 5}, timeout=10)
        assert expired.value.code == "bad_request"
        with pytest.raises(RpcError, match="still_s") as bad:
            rpc_call(node, key, "measure", {"baseline": 2, "still_s": 0}, timeout=10)
        assert bad.value.code == "bad_request"
