"""`archery camera`: frames of the target on `ROBOT/cam/target:o` and the verbs of
`ROBOT/cam/rpc:i` (`protocol.verbs.camera`; docs/names.md's tables). Sources: `mujoco` renders the
robot's scene, `device:N` reads a camera, `folder:PATH` replays images, `yarp:/PORT` reads a YARP
image port (a real iCub's camera). One capture thread (the one `run` is called on) owns the
source; frames are captured only while wanted (`services.camera.capture`)."""

from __future__ import annotations

import logging
import threading

from archery.mesh.node import Node
from archery.mesh.service import service_main
from archery.protocol.messages import Image
from archery.protocol.robotspec import CAMERA
from archery.services.camera.capture import Capture, capture_loop
from archery.services.camera.config import CameraConfig, add_arguments, make_config
from archery.services.camera.frames import FrameStore
from archery.services.camera.handlers import CameraHandlers
from archery.services.camera.scene_view import SceneViews

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
