"""`archery camera`: frames of the target on `ROBOT/cam/target:o`, and `ROBOT/cam/rpc:i`.

Sources: `mujoco` renders the robot's scene from `ROBOT/world/state:o` with its own model copy
(built from the scene parameters the robot reports in `archery/rpc:i status`, or the default
scene when no robot answers); `device:N` reads a real camera through OpenCV; `folder:PATH`
replays images from disk (read when captured). Frames are RGB (`--encoding rgb8`, default) or
compressed (`jpeg`, `png`) at `--rate` frames per second; a rendered frame carries the world
state's sim time, a real one `sim_time` None.

Verbs on `ROBOT/cam/rpc:i` (args → result):
- `grab {"after_sim_time": s, "after_stamp": s, "timeout": s}` → an `Image` as a dict
  (`msgspec.to_builtins(image, builtin_types=(bytes,))`; `msgspec.convert(result, Image)` on the
  caller's side): the first frame rendered from a world state with sim time ≥ `after_sim_time`
  and whose capture started at wall time ≥ `after_stamp`, so a measurement never sees the scene
  before the arrow landed. A device or folder frame has no sim time: there `after_sim_time`
  means "captured after this request arrived". Error `timeout` when none comes within
  `timeout` (default 5 s).
- `calibration {}` (mujoco only) → {"image": Image dict, "pixels": {"target": [[x, y]…],
  "arrow": [[x, y]…]}}: a frame with an arrow on the face and the pixels a user would mark.
- `status {}` → source, size, rate, encoding, frames published, renders and mean render time
  (ms), newest frame's sim time, the scene parameters and where they came from.

One capture thread (the one `run` is called on) owns the source: GL contexts and devices belong
to the thread that opened them. RPC handlers hand it work and wait on its frames.
"""

from __future__ import annotations

import argparse
import concurrent.futures
import logging
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from protocol.errors import ArcheryError, BadRequest, ConfigError, RpcError, RpcTimeout
from protocol.messages import Image, WorldState
from protocol.netflags import NetConfig
from protocol.node import Node, Publisher
from protocol.robotspec import CAMERA, ROBOT_TIMEOUT
from protocol.service import service_main
from protocol.verbs import NoArgs
from protocol.verbs import camera as camera_verbs
from protocol.verbs import robot as robot_verbs
from protocol.verbs.camera import CAMERA_VERBS, CalibrationReply, CameraStatusReply, GrabArgs
from services.camera.frames import FrameStore, Freshness
from services.camera.sources import DeviceSource, FolderSource, SourceSpec, parse_source

__all__ = ["ENCODINGS", "CameraConfig", "main", "run"]

log = logging.getLogger("archery.camera")
ENCODINGS = ("rgb8", "jpeg", "png")
MAX_GRAB_TIMEOUT = camera_verbs.MAX_GRAB_TIMEOUT  # s


@dataclass(frozen=True)
class CameraConfig:
    """Camera settings.

    Attributes:
        net: network settings.
        source: where frames come from (`parse_source`).
        width, height: image size (px) of rendered frames, and asked of a device.
        rate: frames published per wall second.
        encoding: rgb8 (raw), jpeg or png.
        robot_timeout: how long to wait for the robot's scene parameters at start (s).
    """

    net: NetConfig = field(default_factory=NetConfig)
    source: SourceSpec = field(default_factory=lambda: SourceSpec("mujoco"))
    width: int = 1280
    height: int = 720
    rate: float = 10.0
    encoding: str = "rgb8"
    robot_timeout: float = ROBOT_TIMEOUT

    def __post_init__(self) -> None:
        if not isinstance(self.source, SourceSpec):
            raise ConfigError(f"source must be a SourceSpec (parse_source), got {self.source!r}")
        if not (16 <= self.width <= 4096 and 16 <= self.height <= 4096):
            raise ConfigError(f"--size {self.width}x{self.height} is outside 16..4096 px")
        if not (isinstance(self.rate, int | float) and 0.1 <= self.rate <= 120):
            raise ConfigError(f"--rate {self.rate} is outside 0.1..120 frames/s")
        if self.encoding not in ENCODINGS:
            raise ConfigError(f"--encoding {self.encoding!r} is not one of {', '.join(ENCODINGS)}")
        if not (isinstance(self.robot_timeout, int | float) and 0 <= self.robot_timeout <= 60):
            raise ConfigError(f"robot timeout {self.robot_timeout!r} is outside 0..60 s")


def _encode(pixels: np.ndarray, encoding: str, **fields: Any) -> Image:
    if encoding == "rgb8":
        return Image.from_numpy(pixels, **fields)
    ok, data = cv2.imencode(".jpg" if encoding == "jpeg" else ".png", pixels[:, :, ::-1])
    if not ok:
        raise ConfigError(f"{encoding} encoding of a {pixels.shape} frame failed")
    height, width = pixels.shape[:2]
    return Image(width=width, height=height, encoding=encoding, data=data.tobytes(), **fields)


class _Capture:
    """The capture thread's state: the source, its frames, and the work RPC handlers hand it."""

    def __init__(self, config: CameraConfig, node: Node, store: FrameStore) -> None:
        self.config = config
        self.node = node
        self.store = store
        self.jobs: queue.SimpleQueue[tuple[Callable[[], Any], concurrent.futures.Future[Any]]]
        self.jobs = queue.SimpleQueue()
        self.wake = threading.Event()
        self.renderer: Any = None
        self.reader: DeviceSource | FolderSource | None = None
        self.scene: dict[str, Any] | None = None
        self.scene_from = ""
        self.scene_error = ""
        self.scene_checked = 0.0
        self.frame = 0
        self.renders = 0
        self.render_seconds = 0.0
        self.errors = 0
        self.world = None
        if config.source.kind == "mujoco":
            self.world = node.subscribe(
                node.keys.world_state(), WorldState, callback=lambda _msg: self.wake.set()
            )

    def submit(self, job: Callable[[], Any], timeout: float) -> Any:
        """Run `job` on the capture thread and return its result (or raise its error)."""
        future: concurrent.futures.Future[Any] = concurrent.futures.Future()
        self.jobs.put((job, future))
        self.wake.set()
        try:
            return future.result(timeout)
        except concurrent.futures.TimeoutError:
            raise RpcTimeout(f"the capture thread did not answer within {timeout:g} s") from None

    def run_jobs(self) -> None:
        """Run the queued jobs (capture thread)."""
        while True:
            try:
                job, future = self.jobs.get_nowait()
            except queue.Empty:
                return
            try:
                future.set_result(job())
            except Exception as exc:
                future.set_exception(exc)

    def _robot_scene(self, timeout: float) -> Any:
        """The robot's SceneConfig from its `status`, or None when no robot answers."""
        from sim.scene import SceneConfig

        try:
            status = self.node.call_typed(
                self.node.keys.archery_rpc(), robot_verbs.ARCHERY_VERBS["status"], timeout=timeout
            )
            return SceneConfig(**status.scene)
        except (RpcError, KeyError, TypeError, ValueError) as exc:
            self.scene_error = str(exc)
            return None

    def _scene(self) -> Any:
        from sim.scene import SceneConfig

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
        self.scene = scene.to_dict()
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
        if scene.to_dict() != self.scene:
            log.info("the robot reports another scene than the default: rebuilding it")
            self.renderer.close()
            self.renderer = None
            from sim.render import SceneRenderer

            self.renderer = SceneRenderer(scene, width=self.config.width, height=self.config.height)
            self.scene = scene.to_dict()
        else:
            log.info("the robot's scene is the default one")

    def open(self) -> None:
        """Open the source (capture thread).

        Raises:
            ConfigError: the device cannot be opened, or the folder holds no readable image.
        """
        source = self.config.source
        if source.kind == "mujoco":
            from sim.render import SceneRenderer

            self.renderer = SceneRenderer(
                self._scene(), width=self.config.width, height=self.config.height
            )
        elif source.kind == "device":
            self.reader = DeviceSource(source.index, self.config.width, self.config.height)
        else:
            self.reader = FolderSource(source.path)
            try:
                self.reader.read()
            except ArcheryError as exc:
                raise ConfigError(f"--source folder:{source.path}: {exc}") from None

    def publish(
        self, pixels: np.ndarray, sim_time: float | None, captured: float, pub: Any
    ) -> None:
        """Encode, publish and store a frame whose capture started at wall time `captured`."""
        self.frame += 1
        image = _encode(pixels, self.config.encoding, frame=self.frame, sim_time=sim_time)
        self.store.put(pub.put(image), captured)

    def render(self, qpos: np.ndarray) -> np.ndarray:
        """Render `qpos`; a qpos of another length rebuilds the scene from the robot's status."""
        if qpos.shape != (self.renderer.nq,):
            log.warning(
                "world state has %d qpos values, the scene %d: rebuilding it from the robot's "
                "status",
                qpos.size,
                self.renderer.nq,
            )
            self.renderer.close()
            self.open()
        started = time.perf_counter()
        pixels = self.renderer.render(qpos)
        self.renders += 1
        self.render_seconds += time.perf_counter() - started
        return pixels

    def close(self) -> None:
        """Free the renderer or the device."""
        if self.renderer is not None:
            self.renderer.close()
        if self.reader is not None:
            self.reader.close()


def _loop(capture: _Capture, pub: Publisher[Image], stop: threading.Event) -> None:
    """Publish at the configured rate, and at once whenever a waiting grab can be served."""
    store = capture.store
    period = 1.0 / capture.config.rate
    next_due = 0.0
    last_seq: int | None = None
    cached: tuple[np.ndarray, float | None, float] | None = None  # pixels, sim time, captured
    while not stop.is_set():
        capture.run_jobs()
        now = time.monotonic()
        due = now >= next_due
        waiting = store.waiting()
        try:
            if capture.world is not None:
                state = capture.world.latest()
                new = state is not None and state.seq != last_seq
                if state is not None and new and (due or waiting):
                    capture.recheck_scene()
                    last_seq = state.seq
                    captured = time.time()
                    pixels = capture.render(state.qpos.to_numpy())
                    cached = (pixels, state.sim_time, captured)
                    capture.publish(pixels, state.sim_time, captured, pub)
                    next_due = now + period
                elif due:
                    if cached is None:  # no world state yet: the model's initial state
                        qpos = np.asarray(capture.renderer.model.qpos0)
                        cached = (capture.render(qpos), None, time.time())
                    capture.publish(*cached, pub)
                    next_due = now + period
            else:
                wall = time.time()
                serve = any(w.after_stamp is None or w.after_stamp <= wall for w in waiting)
                if due or serve:
                    captured = time.time()
                    pixels = capture.reader.read(fresh=serve)  # type: ignore[union-attr]
                    capture.publish(pixels, None, captured, pub)
                    next_due = now + period
        except ArcheryError as exc:
            capture.errors += 1
            if capture.errors <= 5 or capture.errors % 100 == 0:
                log.error("frame %d failed (%d so far): %s", capture.frame + 1, capture.errors, exc)
            next_due = time.monotonic() + period
        capture.wake.wait(max(0.0, min(period, next_due - time.monotonic())))
        capture.wake.clear()


def run(config: CameraConfig, stop: threading.Event) -> None:
    """Serve until `stop` is set."""
    with Node(CAMERA, config.net) as node:
        keys = node.keys
        pub = node.publisher(keys.cam_frames(), Image)
        store = FrameStore()
        capture = _Capture(config, node, store)
        rendered = config.source.kind == "mujoco"

        def grab(args: GrabArgs) -> Image:
            timeout = 5.0 if args.timeout is None else args.timeout
            after_sim_time, after_stamp = args.after_sim_time, args.after_stamp
            if not rendered and after_sim_time is not None:
                after_sim_time, after_stamp = None, max(after_stamp or 0.0, time.time())
            want = Freshness(after_sim_time=after_sim_time, after_stamp=after_stamp)
            return store.wait(want, timeout, on_wait=capture.wake.set)

        def calibration(args: NoArgs) -> CalibrationReply:
            if not rendered:
                raise BadRequest(
                    f"calibration marks come only from the mujoco source (this camera is "
                    f"{config.source.kind}): mark pixels by hand and use `archery calibrate`, "
                    f"or the detector's `calibrate` verb with pixels"
                )

            def job() -> CalibrationReply:
                from sim.render import calibration_frame

                latest = capture.world.latest() if capture.world else None
                qpos = latest.qpos.to_numpy() if latest else capture.renderer.model.qpos0
                pixels, marks = calibration_frame(capture.renderer, qpos)
                image = Image.from_numpy(
                    pixels, sim_time=latest.sim_time if latest else None, stamp=time.time()
                )
                return CalibrationReply(image=image, pixels=marks)

            return capture.submit(job, timeout=30.0)  # type: ignore[no-any-return]

        def status(args: NoArgs) -> CameraStatusReply:
            latest = store.latest
            renders = capture.renders
            return CameraStatusReply(
                source=config.source.kind,
                width=config.width,
                height=config.height,
                rate=config.rate,
                encoding=config.encoding,
                frames=store.count,
                renders=renders,
                render_ms=round(1e3 * capture.render_seconds / renders, 3) if renders else None,
                errors=capture.errors,
                latest_sim_time=latest.sim_time if latest else None,
                scene=capture.scene,
                scene_from=capture.scene_from,
            )

        verbs = CAMERA_VERBS.bind({"grab": grab, "calibration": calibration, "status": status})
        node.serve(keys.cam_rpc(), verbs)
        capture.open()
        node.ready()
        log.info(
            "camera up: %s source, %dx%d at %g frames/s (%s)",
            config.source.kind,
            config.width,
            config.height,
            config.rate,
            config.encoding,
        )
        try:
            _loop(capture, pub, stop)
        finally:
            capture.close()


def _add_arguments(parser: argparse.ArgumentParser) -> None:
    defaults = CameraConfig()
    parser.add_argument(
        "--source",
        default="mujoco",
        help="mujoco (render the robot's scene), device:N or folder:PATH",
    )
    parser.add_argument(
        "--size", default=f"{defaults.width}x{defaults.height}", help="image size WIDTHxHEIGHT (px)"
    )
    parser.add_argument("--rate", type=float, default=defaults.rate, help="frames per second")
    parser.add_argument(
        "--encoding", default=defaults.encoding, help="rgb8 (raw), jpeg or png (slow links)"
    )
    parser.add_argument(
        "--robot-timeout",
        type=float,
        default=defaults.robot_timeout,
        help="wait this long for the robot's scene parameters at start (s)",
    )


def _make_config(args: argparse.Namespace, net: NetConfig) -> CameraConfig:
    try:
        width, height = (int(v) for v in args.size.lower().split("x"))
    except ValueError:
        raise ConfigError(f"--size {args.size!r} is not WIDTHxHEIGHT, e.g. 1280x720") from None
    return CameraConfig(
        net=net,
        source=parse_source(args.source),
        width=width,
        height=height,
        rate=args.rate,
        encoding=args.encoding,
        robot_timeout=args.robot_timeout,
    )


def main(argv: list[str] | None = None) -> int:
    """`archery camera`."""
    return service_main(
        argv,
        prog="camera",
        description=__doc__.splitlines()[0],
        add_arguments=_add_arguments,
        make_config=_make_config,
        run=run,
    )
