"""`archery camera`: frames of the target on `ROBOT/cam/target:o`, and `ROBOT/cam/rpc:i`.

Sources: `mujoco` renders the robot's scene from `ROBOT/world/state:o` with its own model copy
(built from the scene parameters the robot reports in `archery/rpc:i status`, or the default
scene when no robot answers); `device:N` reads a real camera through OpenCV; `folder:PATH`
replays images from disk (read when captured). Frames are RGB (`--encoding rgb8`, default) or
compressed (`jpeg`, `png`) at `--rate` frames per second; a rendered frame carries the world
state's sim time, a real one `sim_time` None.

Idle: frames are captured only while something subscribes to `ROBOT/cam/target:o` or a `grab`
waits; a world state the camera sees unchanged (the same poses of everything movable in its
view) reuses a kept render with a new capture stamp.

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
- `scene {}` (mujoco only) → {"status": "ok"|"starting", "image": a JPEG Image dict or None,
  "period", "renders", "render_ms"}: the newest view of the whole robot, bow, arrow and target
  from the scene's side camera, rendered on its own thread at most once per `period` s while
  asked for, never waited for (`services.camera.scene_view`); nothing is built or rendered
  while nobody asks.
- `status {}` → source, size, rate, encoding, frames published, renders, reuses (frames of an
  unchanged view served from a kept render) and mean render time
  (ms), newest frame's sim time, the scene parameters and where they came from.

One capture thread (the one `run` is called on) owns the source: GL contexts and devices belong
to the thread that opened them. RPC handlers hand it work and wait on its frames.
"""

from __future__ import annotations

import logging
import threading

from mesh.node import Node
from mesh.service import service_main
from protocol.messages import Image
from protocol.robotspec import CAMERA
from services.camera.capture import Capture, capture_loop
from services.camera.config import CameraConfig, add_arguments, make_config
from services.camera.frames import FrameStore
from services.camera.handlers import CameraHandlers
from services.camera.scene_view import SceneViews

__all__ = ["main", "run"]

log = logging.getLogger("archery.camera")


def run(config: CameraConfig, stop: threading.Event) -> None:
    """Serve until `stop` is set; the calling thread becomes the capture thread."""
    with Node(CAMERA, config.net) as node:
        keys = node.keys
        pub = node.publisher(keys.cam_frames(), Image)
        store = FrameStore()
        capture = Capture(config, node, store)
        views = SceneViews(capture)
        node.serve(keys.cam_rpc(), CameraHandlers(config, capture, store, views).verbs())
        try:
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
            capture_loop(capture, pub, stop)
        finally:
            views.close()
            capture.close()


def main(argv: list[str] | None = None) -> int:
    """`archery camera`."""
    return service_main(
        argv,
        prog=CAMERA,
        description=__doc__.splitlines()[0],
        add_arguments=add_arguments,
        make_config=make_config,
        run=run,
    )
