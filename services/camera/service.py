"""`archery camera`: frames of the target on `ROBOT/cam/target:o`, and `ROBOT/cam/rpc:i`.

Sources: `mujoco` renders the robot's scene from `ROBOT/world/state:o` with its own model copy
(built from the scene parameters the robot reports in `archery/rpc:i status`); `device:N` reads
a real camera through OpenCV; `folder:PATH` replays images from disk.

Verbs on `ROBOT/cam/rpc:i`:
- `grab {"after_sim_time": s, "after_stamp": s, "timeout": s}` → an `Image` as a dict (raw
  bytes kept): the first frame rendered from a world state at or after `after_sim_time` (mujoco)
  and captured at or after the wall-clock `after_stamp` (any source), so a measurement never
  sees the scene before the arrow landed; `timeout` error otherwise.
- `calibration {}` (mujoco only) → {"image": Image dict, "pixels": {"target": […], "arrow": […]}}:
  a frame with an arrow on the face and the pixels a user would mark on it.
- `status {}` → source, size, rate, frames published, newest frame's sim time.

One capture thread owns the source (GL contexts and devices belong to the thread that opened
them); RPC handlers hand it work and wait on its frames.
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

import msgspec
import numpy as np

from protocol.errors import BadRequest, ConfigError, RpcError, RpcTimeout
from protocol.messages import Image, WorldState
from protocol.netflags import NetConfig
from protocol.node import Node
from protocol.service import service_main
from services.camera.sources import DeviceSource, FolderSource, SourceSpec, parse_source

__all__ = ["CameraConfig", "main", "run"]

log = logging.getLogger("archery.camera")


@dataclass(frozen=True)
class CameraConfig:
    """Camera settings: source, image size (px), stream rate (frames per wall second)."""

    net: NetConfig = field(default_factory=NetConfig)
    source: SourceSpec = field(default_factory=lambda: SourceSpec("mujoco"))
    width: int = 1280
    height: int = 720
    rate: float = 10.0
    encoding: str = "rgb8"
    robot_timeout: float = 3.0

    def __post_init__(self) -> None:
        if not (16 <= self.width <= 4096 and 16 <= self.height <= 4096):
            raise ConfigError(f"--size {self.width}x{self.height} is outside 16..4096 px")
        if not (0.1 <= self.rate <= 120):
            raise ConfigError(f"--rate {self.rate} is outside 0.1..120 frames/s")
        if self.encoding not in ("rgb8", "jpeg"):
            raise ConfigError(f"--encoding {self.encoding!r} is not rgb8 or jpeg")


class _FrameStore:
    """The newest frame and who waits for one; thread-safe."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self.latest: Image | None = None
        self.waiting = 0
        self.count = 0

    def put(self, image: Image) -> None:
        with self._cond:
            self.latest = image
            self.count += 1
            self._cond.notify_all()

    def wait(
        self, after_sim_time: float | None, after_stamp: float | None, timeout: float
    ) -> Image:
        def fits(image: Image | None) -> bool:
            if image is None:
                return False
            if after_sim_time is not None and (image.sim_time or -1.0) < after_sim_time:
                return False
            return after_stamp is None or image.stamp >= after_stamp

        deadline = time.monotonic() + timeout
        with self._cond:
            self.waiting += 1
            try:
                while not fits(self.latest):
                    remaining = deadline - time.monotonic()
                    if remaining <= 0:
                        newest = self.latest.sim_time if self.latest else None
                        raise RpcTimeout(
                            f"no frame after sim time {after_sim_time} / stamp {after_stamp} "
                            f"within {timeout:g} s (newest frame: sim time {newest})"
                        )
                    self._cond.wait(remaining)
                assert self.latest is not None
                return self.latest
            finally:
                self.waiting -= 1


def _number(args: dict[str, Any], name: str, default: float | None) -> float | None:
    value = args.get(name, default)
    if value is None:
        return None
    if not isinstance(value, int | float) or isinstance(value, bool) or not np.isfinite(value):
        raise BadRequest(f"{name} must be a finite number of seconds, got {value!r}")
    return float(value)


class _Capture:
    """The capture thread's state: the source, and the work RPC handlers hand it."""

    def __init__(self, config: CameraConfig, node: Node, store: _FrameStore) -> None:
        self.config = config
        self.node = node
        self.store = store
        self.jobs: queue.SimpleQueue[tuple[Callable[[], Any], concurrent.futures.Future]] = (
            queue.SimpleQueue()
        )
        self.wake = threading.Event()
        self.renderer: Any = None
        self.reader: DeviceSource | FolderSource | None = None
        self.frame = 0
        self.world = None
        if config.source.kind == "mujoco":
            self.world = node.subscribe(
                node.keys.world_state(), WorldState, callback=lambda _msg: self.wake.set()
            )

    def submit(self, job: Callable[[], Any], timeout: float) -> Any:
        future: concurrent.futures.Future = concurrent.futures.Future()
        self.jobs.put((job, future))
        self.wake.set()
        try:
            return future.result(timeout)
        except concurrent.futures.TimeoutError:
            raise RpcTimeout(f"the capture thread did not answer within {timeout:g} s") from None

    def _scene(self) -> Any:
        from sim.scene import SceneConfig

        try:
            status = self.node.call(
                self.node.keys.archery_rpc(), "status", timeout=self.config.robot_timeout
            )
            return SceneConfig(**status["scene"])
        except (RpcError, KeyError, TypeError) as exc:
            log.warning("robot scene unknown (%s): rendering the default scene", exc)
            return SceneConfig()

    def open(self) -> None:
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

    def publish(self, pixels: np.ndarray, sim_time: float | None, pub: Any) -> None:
        self.frame += 1
        if self.config.encoding == "jpeg":
            import cv2

            ok, data = cv2.imencode(".jpg", np.ascontiguousarray(pixels[:, :, ::-1]))
            if not ok:
                raise ConfigError("JPEG encoding of a frame failed")
            image = Image(
                width=pixels.shape[1],
                height=pixels.shape[0],
                encoding="jpeg",
                data=data.tobytes(),
                frame=self.frame,
                sim_time=sim_time,
            )
        else:
            image = Image.from_numpy(pixels, frame=self.frame, sim_time=sim_time)
        self.store.put(pub.put(image))

    def render_world(self, state: WorldState) -> np.ndarray:
        qpos = state.qpos.to_numpy()
        if qpos.shape != (self.renderer.nq,):
            log.warning(
                "world state has %d qpos values, renderer %d: rebuilding",
                qpos.size,
                self.renderer.nq,
            )
            self.renderer.close()
            self.open()
        return self.renderer.render(qpos)

    def close(self) -> None:
        if self.renderer is not None:
            self.renderer.close()
        if self.reader is not None:
            self.reader.close()


def run(config: CameraConfig, stop: threading.Event) -> None:
    """Serve until `stop` is set."""
    with Node("camera", config.net) as node:
        keys = node.keys
        pub = node.publisher(keys.cam_frames(), Image)
        store = _FrameStore()
        capture = _Capture(config, node, store)

        def grab(args: dict[str, Any]) -> dict[str, Any]:
            unknown = set(args) - {"after_sim_time", "after_stamp", "timeout"}
            if unknown:
                raise BadRequest(
                    f"grab: unknown args {sorted(unknown)}; valid: after_sim_time, "
                    f"after_stamp, timeout"
                )
            timeout = _number(args, "timeout", 5.0) or 5.0
            capture.wake.set()
            image = store.wait(
                _number(args, "after_sim_time", None), _number(args, "after_stamp", None), timeout
            )
            return msgspec.to_builtins(image, builtin_types=(bytes,))

        def calibration(args: dict[str, Any]) -> dict[str, Any]:
            if config.source.kind != "mujoco":
                raise BadRequest(
                    "calibration marks come only from the mujoco source; mark "
                    "pixels by hand and use `archery calibrate` for real images"
                )

            def job() -> dict[str, Any]:
                from sim.calibration import calibration_frame

                latest = capture.world.latest() if capture.world else None
                qpos = latest.qpos.to_numpy() if latest else capture.renderer.model.qpos0
                pixels, marks = calibration_frame(capture.renderer, qpos)
                image = Image.from_numpy(pixels, sim_time=latest.sim_time if latest else None)
                return {
                    "image": msgspec.to_builtins(image, builtin_types=(bytes,)),
                    "pixels": marks,
                }

            return capture.submit(job, timeout=30.0)  # type: ignore[no-any-return]

        def status(args: dict[str, Any]) -> dict[str, Any]:
            latest = store.latest
            return {
                "source": config.source.kind,
                "width": config.width,
                "height": config.height,
                "rate": config.rate,
                "encoding": config.encoding,
                "frames": store.count,
                "latest_sim_time": latest.sim_time if latest else None,
            }

        node.serve(keys.cam_rpc(), {"grab": grab, "calibration": calibration, "status": status})
        capture.open()
        node.ready()
        log.info(
            "camera up: %s source, %dx%d at %g frames/s",
            config.source.kind,
            config.width,
            config.height,
            config.rate,
        )
        period = 1.0 / config.rate
        next_due = 0.0
        last_seq = -1
        try:
            while not stop.is_set():
                while True:
                    try:
                        job, future = capture.jobs.get_nowait()
                    except queue.Empty:
                        break
                    try:
                        future.set_result(job())
                    except Exception as exc:
                        future.set_exception(exc)
                now = time.monotonic()
                due = now >= next_due or store.waiting > 0
                if capture.world is not None:
                    state = capture.world.latest()
                    if state is not None and due and (state.seq != last_seq or now >= next_due):
                        capture.publish(capture.render_world(state), state.sim_time, pub)
                        last_seq = state.seq
                        next_due = now + period
                elif due:
                    capture.publish(capture.reader.read(), None, pub)  # type: ignore[union-attr]
                    next_due = now + period
                capture.wake.wait(max(0.0, min(period, next_due - time.monotonic())))
                capture.wake.clear()
        finally:
            capture.close()


def _add_arguments(parser: argparse.ArgumentParser) -> None:
    defaults = CameraConfig()
    parser.add_argument("--source", default="mujoco", help="mujoco, device:N or folder:PATH")
    parser.add_argument(
        "--size", default=f"{defaults.width}x{defaults.height}", help="image size WIDTHxHEIGHT (px)"
    )
    parser.add_argument("--rate", type=float, default=defaults.rate, help="frames per second")
    parser.add_argument("--encoding", default="rgb8", help="rgb8 (raw) or jpeg (slow links)")


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
