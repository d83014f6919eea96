"""The camera's capture thread: it owns the source (renderer, device, folder or YARP port),
renders or reads frames, encodes and publishes them, and runs the work RPC handlers hand it
(`jobs`).

GL contexts and devices belong to the thread that opened them, so everything that touches the
source runs here. A rendered frame follows the robot's world states on `ROBOT/world/state:o`
with a model built from the scene the robot reports (its `status`, asked through the one
`RobotClient`; the default scene until the robot answers). `capture_loop` says when frames go
out (only while someone wants them), `Capture.view` when a render is reused rather than made
again.
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from typing import Any

import cv2
import numpy as np

from archery.mesh.jobs import JobQueue
from archery.mesh.node import Node
from archery.mesh.publisher import Publisher
from archery.mesh.robot_client import RobotClient
from archery.protocol.errors import ArcheryError, ConfigError, RpcError, RpcTimeout
from archery.protocol.messages import Image, WorldState
from archery.protocol.verbs.robot import Scene
from archery.services.camera.config import CameraConfig
from archery.services.camera.frames import FrameStore, Freshness
from archery.services.camera.sources import (
    DeviceSource,
    FolderSource,
    SourceError,
    YarpSource,
)

__all__ = ["Capture", "capture_loop", "encode"]

log = logging.getLogger("archery.camera")
KEPT_RENDERS = 4  # renders kept for reuse by view key (2.7 MB each at 1280×720)


def encode(pixels: np.ndarray, encoding: str, **fields: Any) -> Image:
    """RGB pixels (H, W, 3) as an `Image`: raw (rgb8), lossless LZ4 (rgb8_lz4) or compressed
    (jpeg, png)."""
    if encoding in ("rgb8", "rgb8_lz4"):
        return Image.from_numpy(pixels, encoding, **fields)
    ok, data = cv2.imencode(".jpg" if encoding == "jpeg" else ".png", pixels[:, :, ::-1])
    if not ok:
        raise ConfigError(f"{encoding} encoding of a {pixels.shape} frame failed")
    height, width = pixels.shape[:2]
    return Image(width=width, height=height, encoding=encoding, data=data.tobytes(), **fields)


class Capture:
    """The capture thread's state: the source, its frames, and the work RPC handlers hand it."""

    def __init__(self, config: CameraConfig, node: Node, store: FrameStore) -> None:
        self.config = config
        self.node = node
        self.robot = RobotClient(node)
        self.store = store
        self.jobs = JobQueue(RpcTimeout, "the capture thread")
        self.renderer: Any = None
        self.reader: DeviceSource | FolderSource | YarpSource | None = None
        self.scene: Scene | None = None
        self.scene_from = ""
        self.scene_error = ""
        self.scene_checked = 0.0
        self.frame = 0
        self.renders = 0
        self.reuses = 0  # frames of an unchanged view served from a kept render
        self.render_seconds = 0.0
        # the last renders by view key (the most recent last): a few, so the empty target's
        # render outlives the rollout that shows an arrow in it
        self._shown: collections.OrderedDict[bytes, np.ndarray] = collections.OrderedDict()
        self.errors = 0
        self.watched = False  # someone subscribes to the frames (the capture loop keeps it)
        self.joined = False  # a subscriber appeared: it gets a frame at once
        self.world = None
        if config.source.kind == "mujoco":
            self.world = node.subscribe(node.keys.world_state(), WorldState, callback=self._woken)

    def _woken(self, state: WorldState) -> None:
        """A world state arrived: wake the capture thread if a frame is wanted at all (a
        subscriber, or a waiting grab this state or a capture now would serve: grabs waiting
        for a sim time to come do not wake it at every state)."""
        if self.watched or _serves(self.store.waiting(), state.sim_time, time.time()):
            self.jobs.notify()

    def watch(self, matching: bool) -> None:
        """Subscribers to the frames appeared (True) or all went (False)."""
        self.watched = matching
        self.joined = self.joined or matching
        self.jobs.notify()

    def _robot_scene(self, timeout: float) -> Any:
        """The robot's SceneConfig from its `status`, or None when no robot answers."""
        from archery.sim.scene_config import SceneConfig

        try:
            return SceneConfig.of(self.robot.scene(timeout))
        except (RpcError, KeyError, TypeError, ValueError) as exc:
            self.scene_error = str(exc)
            return None

    def _scene(self) -> Any:
        from archery.sim.scene_config import SceneConfig

        scene = self._robot_scene(max(0.1, self.config.robot_timeout))
        if scene is None:
            log.warning(
                "the robot's scene is unknown (%s): rendering the default scene until the robot "
                "answers",
                self.scene_error,
            )
            scene = SceneConfig()
            self.scene_from = "default"
        else:
            self.scene_from = "robot"
        self.scene = scene.to_status()
        self.scene_checked = time.monotonic()
        return scene

    def recheck_scene(self) -> None:
        """While rendering the default scene, ask the robot again (at most every 2 s) once its
        world states arrive, and rebuild the renderer if its scene differs (capture thread)."""
        if self.scene_from != "default" or time.monotonic() - self.scene_checked < 2.0:
            return
        self.scene_checked = time.monotonic()
        scene = self._robot_scene(0.5)
        if scene is None:
            return
        self.scene_from = "robot"
        if scene.to_status() != self.scene:
            log.info("the robot reports another scene than the default: rebuilding it")
            self.renderer.close()
            self.renderer = None
            self._shown.clear()
            from archery.sim.render import SceneRenderer

            self.renderer = SceneRenderer(scene, width=self.config.width, height=self.config.height)
            self.scene = scene.to_status()
        else:
            log.info("the robot's scene is the default one")

    def open(self) -> None:
        """Open the source (capture thread).

        Raises:
            ConfigError: the device cannot be opened, the folder holds no readable image, or
                the YARP port gives no frame (no name server, no such port, no frame within
                `frame_timeout`).
        """
        source = self.config.source
        if source.kind == "mujoco":
            from archery.sim.render import SceneRenderer

            self.renderer = SceneRenderer(
                self._scene(), width=self.config.width, height=self.config.height
            )
        elif source.kind == "device":
            self.reader = DeviceSource(source.index, self.config.width, self.config.height)
        elif source.kind == "yarp":
            try:
                self.reader = YarpSource(source.port, self.config.frame_timeout)
                self.reader.read()
            except SourceError as exc:
                raise ConfigError(f"--source {exc}") from None
        else:
            self.reader = FolderSource(source.path)
            try:
                self.reader.read()
            except ArcheryError as exc:
                raise ConfigError(f"--source folder:{source.path}: {exc}") from None

    def publish(
        self, pixels: np.ndarray, sim_time: float | None, captured: float, pub: Any
    ) -> None:
        """Encode, stamp and store a frame whose capture started at wall time `captured`, then
        send it to the subscribers, if any: a waiting `grab` gets it first (its reply goes out
        while the subscribers' copy is sent)."""
        self.frame += 1
        image = pub.stamp(encode(pixels, self.config.encoding, frame=self.frame, sim_time=sim_time))
        self.store.put(image, captured)
        if pub.matching():
            pub.send(image)

    def render(self, qpos: np.ndarray) -> np.ndarray:
        """Render `qpos`; a qpos of another length rebuilds the scene from the robot's status."""
        self.fit_scene(qpos)
        started = time.perf_counter()
        pixels: np.ndarray = self.renderer.render(qpos)
        self.renders += 1
        self.render_seconds += time.perf_counter() - started
        return pixels

    def fit_scene(self, qpos: np.ndarray) -> None:
        """Rebuild the scene from the robot's status if `qpos` is of another length than its
        (a robot of another scene, `--shot whole`, whose status was not known yet)."""
        if qpos.shape != (self.renderer.nq,):
            log.warning(
                "world state has %d qpos values, the scene %d: rebuilding it from the robot's "
                "status",
                qpos.size,
                self.renderer.nq,
            )
            self.renderer.close()
            self._shown.clear()
            self.open()

    def view(self, qpos: np.ndarray) -> np.ndarray:
        """The pixels of `qpos`: a kept render of the same view key, else a new render.

        A world state that looks, to the camera, like one of the last few rendered (the same
        poses of everything movable in its view: `SceneRenderer.view_key`; the robot moving its
        arms behind the camera, or a scene reset to its empty target, changes nothing it sees)
        is not rendered again: the pixels would be the same, so that render goes out again with
        this capture's stamp and the new state's sim time. That keeps `grab`'s promise: a frame
        "captured after a stamp" shows the newest world state known at that time, as a fresh
        render of it would.
        """
        if qpos.shape != (self.renderer.nq,):
            return self.render(qpos)  # rebuilds the scene
        key = self.renderer.view_key(qpos)
        pixels = self._shown.get(key)
        if pixels is not None:
            self._shown.move_to_end(key)
            self.reuses += 1
            return pixels
        pixels = self.render(qpos)
        self._shown[key] = pixels
        while len(self._shown) > KEPT_RENDERS:
            self._shown.popitem(last=False)
        return pixels

    def close(self) -> None:
        """Fail the pending and later jobs, and free the renderer or the device."""
        self.jobs.close("the camera is shutting down")
        if self.renderer is not None:
            self.renderer.close()
        if self.reader is not None:
            self.reader.close()


def _sender_stamp(reader: Any, captured: float) -> float:
    """When a frame was captured (wall s): its sender's stamp for a YARP port's frame that
    carries one (`YarpSource.stamp`, never later than `captured`), else `captured`, when its
    read started."""
    if isinstance(reader, YarpSource) and reader.stamp is not None:
        return min(reader.stamp, captured)
    return captured


def _serves(waiting: list[Freshness], sim_time: float | None, wall: float) -> bool:
    """True if a frame of a world state at `sim_time` (s) captured at `wall` (s) would serve
    one of the `waiting` grabs."""
    return any(
        (want.after_sim_time is None or (sim_time is not None and sim_time >= want.after_sim_time))
        and (want.after_stamp is None or want.after_stamp <= wall)
        for want in waiting
    )


def _needs_recapture(
    waiting: list[Freshness], cached: tuple[np.ndarray, float | None, float] | None
) -> bool:
    """True if a waiting grab asks only for a capture after a wall stamp, which the render of
    the newest world state (`cached`: pixels, sim time s, captured wall s) can serve again."""
    sim_time = None if cached is None else cached[1]
    return any(
        want.after_stamp is not None
        and (cached is None or cached[2] < want.after_stamp)
        and (
            want.after_sim_time is None
            or (sim_time is not None and sim_time >= want.after_sim_time)
        )
        for want in waiting
    )


def capture_loop(capture: Capture, pub: Publisher[Image], stop: threading.Event) -> None:
    """Publish at the configured rate while someone subscribes (at `rest_rate` while the view is
    unchanged), and at once whenever a waiting grab can be served; sleep otherwise.

    Idle cost: frames are captured only while someone subscribes to the frames or a `grab`
    waits; otherwise the thread sleeps (a subscriber appearing wakes it). While the view is
    unchanged (the frame due would carry the same render as the last one sent), frames go out
    at `rest_rate`, not at `rate`: a subscriber (a recording) is not sent megabytes of the same
    pixels ten times a second. A changed view, a waiting `grab` and a new subscriber get their
    frame at once.
    """
    store = capture.store
    period = 1.0 / capture.config.rate
    rest_period = max(period, 1.0 / capture.config.rest_rate)
    next_due = 0.0
    last_seq: int | None = None
    cached: tuple[np.ndarray, float | None, float] | None = None  # pixels, sim time, captured
    sent: np.ndarray | None = None  # the render the last frame sent carried
    sent_at = 0.0  # monotonic s it was sent

    def send(pixels: np.ndarray, sim_time: float | None, captured: float, now: float) -> None:
        nonlocal sent, sent_at
        capture.publish(pixels, sim_time, captured, pub)
        sent, sent_at = pixels, now

    def resting(pixels: np.ndarray, now: float) -> bool:
        """The frame due shows the render last sent, sent less than `rest_period` ago."""
        return pixels is sent and now - sent_at < rest_period

    stop_watching = pub.on_matching(capture.watch)
    try:
        while not stop.is_set():
            capture.jobs.drain()
            now = time.monotonic()
            watched = capture.watched = pub.matching()
            if capture.joined:
                capture.joined, sent = False, None  # a new subscriber: its first frame now
            due = watched and now >= next_due
            waiting = store.waiting()
            try:
                if capture.world is not None:
                    state = capture.world.latest()
                    new = state is not None and state.seq != last_seq
                    # only a grab this state can serve asks for its render (one waiting for a
                    # later sim time, or a stamp to come, does not: it must not make the camera
                    # render every state meanwhile)
                    wanted = state is not None and _serves(waiting, state.sim_time, time.time())
                    # the kept render is of the newest state (a newer one not rendered yet
                    # must not be stood in for by an older render)
                    newest = state is None or state.seq == last_seq
                    if state is not None and new and (due or wanted):
                        capture.recheck_scene()
                        last_seq = state.seq
                        captured = time.time()
                        pixels = capture.view(state.qpos.to_numpy())
                        cached = (pixels, state.sim_time, captured)
                        if wanted or not resting(pixels, now):
                            send(pixels, state.sim_time, captured, now)
                        next_due = now + period
                    elif (recapture := newest and _needs_recapture(waiting, cached)) or due:
                        if cached is None:  # no world state yet: the model's initial state
                            qpos = np.asarray(capture.renderer.model.qpos0)
                            cached = (capture.render(qpos), None, time.time())
                        if recapture or not resting(cached[0], now):
                            # the newest state is rendered already: the same pixels, captured now
                            send(cached[0], cached[1], time.time(), now)
                        next_due = now + period
                else:
                    wall = time.time()
                    serve = any(w.after_stamp is None or w.after_stamp <= wall for w in waiting)
                    if due or serve:
                        captured = time.time()
                        pixels = capture.reader.read(fresh=serve)  # type: ignore[union-attr]  # not MuJoCo: a device, folder or YARP port
                        captured = _sender_stamp(capture.reader, captured)
                        capture.publish(pixels, None, captured, pub)
                        next_due = now + period
            except ArcheryError as exc:
                capture.errors += 1
                if capture.errors <= 5 or capture.errors % 100 == 0:
                    log.error(
                        "frame %d failed (%d so far): %s", capture.frame + 1, capture.errors, exc
                    )
                next_due = time.monotonic() + period
            # idle (no subscriber, no grab): wake on a job, a grab, a subscriber or the stop flag
            wait = min(period, next_due - time.monotonic()) if watched else 0.5
            capture.jobs.wait(max(0.0, wait))
    finally:
        stop_watching()
