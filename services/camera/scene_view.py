"""The scene view: the whole robot, bow, arrow and target seen from the scene's side camera
(`sim.scene_view`), rendered on request at a low rate for people watching (the dashboard).

Cost: nothing while nobody asks; while watched, a thread of its own at a lower CPU priority
renders the newest world state the camera already follows, at most once per `PERIOD` s, and
keeps out of the learning loop's way (`SceneViews` says how). The capture thread, which renders
the target camera's frames for the detector, is never asked to do any of it.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any

import cv2
import msgspec
import numpy as np

from archery.mesh.memory import BIG_PAYLOAD, note_payload
from archery.mesh.priority import lower_thread_priority
from archery.protocol.errors import ArcheryError, BadRequest
from archery.protocol.messages import Image
from archery.protocol.verbs.camera import SceneReply

__all__ = ["HOLD", "IDLE", "NICE", "PERIOD", "SIZE", "SceneViews"]

log = logging.getLogger("archery.camera")

PERIOD = 1.0  # s: at least this long between two renders of the view
IDLE = 30.0  # s without a request: the view is freed
SIZE = (640, 360)  # px: width, height of a view (a dashboard panel)
NICE = 10  # the render thread's niceness on top of the camera's
HOLD = 2.0  # s: after a landing, no view until the camera captured a frame, or this long
RETRY = 0.1  # s: a view put off is tried again this much later
JPEG_QUALITY = 85


class SceneViews:
    """The scene view of one camera service: `reply()` serves the `scene` verb.

    The first `scene` request starts a thread that builds the view (the robot's meshes: a
    second model, a second GL context) at a lower CPU priority (`NICE`, on top of the camera's;
    the software renderer's threads, started from it, inherit it); it renders the newest world
    state the camera already follows (`ROBOT/world/state:o`: the whole qpos poses the robot),
    at most once per `period` s and only while requests keep coming: each request asks for the
    next view and gets the newest one at once (the verb never waits, so it never holds up a
    `grab` on the port's worker). After `idle` s without a request the thread frees the view
    (some 0.5 GB with the robot's meshes and a second GL context, given back to the system)
    and ends.

    While watched it still keeps out of the learning loop's way where the loop waits on the
    CPU: no view is rendered while an arrow flies, while a `grab` waits for a frame, or after a
    landing until the camera has captured a frame since (the detector's measurement; at most
    `HOLD` s): a view rendered then would share the cores with the target frame the detector
    is waiting for (`_loop_busy`). The view shows the robot drawing and aiming, and the arrow
    in the target.

    Args:
        capture: the camera's capture state (`services.camera.capture.Capture`): its world
            subscription (the newest qpos) and the scene parameters the robot reported.
        period, idle, size: as `PERIOD`, `IDLE` and `SIZE`.
    """

    def __init__(
        self,
        capture: Any,
        *,
        period: float = PERIOD,
        idle: float = IDLE,
        size: tuple[int, int] = SIZE,
    ) -> None:
        self._capture = capture
        self.period, self.idle, self.size = period, idle, size
        self._lock = threading.Lock()
        self._wanted = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._image: Image | None = None
        self._renders = 0
        self._render_ms: float | None = None
        self._error = ""
        self._landing: tuple[int, float, int] | None = None  # shot, seen at (s), frames then
        self.held = 0  # renders put off while the learning loop needed the CPU

    @property
    def running(self) -> bool:
        """Whether the render thread (and its view) exists now."""
        thread = self._thread
        return thread is not None and thread.is_alive()

    def reply(self) -> SceneReply:
        """The newest view; asks for the next one (starts the render thread if it is not
        running). Never waits.

        Raises:
            BadRequest: this camera does not render (a device or folder source), or the view
                cannot be built (the message says why).
        """
        if self._capture.world is None:
            raise BadRequest(
                f"the scene view is rendered only by the mujoco source (this camera is "
                f"{self._capture.config.source.kind})"
            )
        with self._lock:
            if self._error:
                raise BadRequest(f"the scene view cannot be rendered: {self._error}")
            self._wanted.set()
            if not self.running and not self._stop.is_set():
                self._thread = threading.Thread(
                    target=self._run, name="camera-scene-view", daemon=True
                )
                self._thread.start()
            image = self._image
            return SceneReply(
                status="ok" if image is not None else "starting",
                image=image,
                period=self.period,
                renders=self._renders,
                render_ms=self._render_ms,
            )

    def close(self) -> None:
        """Stop the render thread (it frees the view)."""
        self._stop.set()
        self._wanted.set()
        thread = self._thread
        if thread is not None:
            thread.join(timeout=10)

    # -- the render thread ----------------------------------------------------------------
    def _run(self) -> None:
        lower_thread_priority(NICE)  # this thread only (Linux)
        try:
            view = self._open()
        except Exception as exc:  # any cause: the page is told why, never left waiting
            log.error("the scene view cannot be built: %s", exc)
            with self._lock:
                self._error = str(exc)
            return
        log.info("scene view on (%dx%d, at most one per %g s)", *self.size, self.period)
        shown: bytes | None = None  # the qpos rendered last
        try:
            while not self._stop.is_set():
                if not self._wanted.wait(self.idle):
                    break  # nobody asked for a while
                if self._stop.is_set():
                    break
                self._wanted.clear()
                started, held = time.monotonic(), self.held
                try:
                    shown = self._render(view, shown)
                except ArcheryError as exc:  # a world state of another scene: build it again
                    log.warning("scene view: %s: building the robot's scene again", exc)
                    view.close()
                    view = self._open()
                    shown = None
                if self.held != held:  # put off: still wanted, tried again shortly
                    self._wanted.set()
                    self._stop.wait(RETRY)
                    continue
                self._stop.wait(max(0.0, started + self.period - time.monotonic()))
        except Exception as exc:  # the view stops; the camera's frames go on
            log.error("the scene view stopped: %s", exc)
            with self._lock:
                self._error = str(exc)
        finally:
            with self._lock:  # a request from now on starts a new thread
                self._thread = None
            view.close()
            del view
            note_payload(BIG_PAYLOAD)  # the model and its meshes freed: give the pages back
            log.info("scene view off")

    def _loop_busy(self, state: Any) -> bool:
        """Whether the learning loop waits on the CPU now: an arrow in flight, a grab waiting,
        or a landing the camera has captured no frame since (for at most `HOLD` s)."""
        store = self._capture.store
        if state.phase == "flying" or store.waiting():
            return True
        if state.phase not in ("stuck", "missed"):
            self._landing = None
            return False
        if self._landing is None or self._landing[0] != state.shot:
            self._landing = (state.shot, time.monotonic(), store.count)
        _, seen, frames = self._landing
        return store.count == frames and time.monotonic() - seen < HOLD

    def _open(self) -> Any:
        from archery.sim.scene_config import SceneConfig
        from archery.sim.scene_view import SceneView

        scene = self._capture.scene
        config = SceneConfig.of(scene) if scene else SceneConfig()
        return SceneView(config, width=self.size[0], height=self.size[1])

    def _render(self, view: Any, shown: bytes | None) -> bytes | None:
        """Render the newest world state unless it is the one rendered last (then the kept
        view gets a new stamp); returns the qpos (bytes) the kept view shows.

        Raises:
            ConfigError: the state's qpos is of another scene.
        """
        state = self._capture.world.latest()
        if state is None:
            return shown  # no world state yet: "starting"
        if self._loop_busy(state):
            self.held += 1
            return shown
        qpos = state.qpos.to_numpy()
        key = np.ascontiguousarray(qpos, dtype=np.float64).tobytes()
        with self._lock:
            kept = self._image
        if key != shown or kept is None:
            started = time.perf_counter()
            pixels = view.render(qpos)
            ok, data = cv2.imencode(
                ".jpg", pixels[:, :, ::-1], [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY]
            )
            if not ok:
                raise ValueError("the scene view does not encode as JPEG")
            took = round(1e3 * (time.perf_counter() - started), 2)
            kept = Image(width=view.width, height=view.height, encoding="jpeg", data=data.tobytes())
            with self._lock:
                self._renders += 1
                self._render_ms = took
            kept = msgspec.structs.replace(kept, frame=self._renders)
        image = msgspec.structs.replace(kept, sim_time=state.sim_time, stamp=time.time())
        with self._lock:
            self._image = image
        return key
