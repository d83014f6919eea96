"""`archery detector`: the GMM colour detector on the mesh: the verbs of
`ROBOT/detector/rpc:i` (`protocol.verbs.detector`; docs/names.md's tables) and each measurement on
`ROBOT/detector/hit:o`. Without `--model` (or with one not made yet) it calibrates itself from
the camera's `calibration` marks once the camera is alive (`--no-auto-calibrate`: not)."""

from __future__ import annotations

import logging
import threading

import cv2

from archery.mesh.node import Node
from archery.mesh.service import service_main
from archery.mesh.signals import wait_for_stop
from archery.protocol.errors import ArcheryError, BadRequest, RpcError
from archery.protocol.messages import Detection as DetectionMessage
from archery.protocol.robotspec import CAMERA, DETECTOR
from archery.services.detector.config import DetectorConfig, add_arguments, make_config
from archery.services.detector.handlers import DetectorHandlers

__all__ = ["main", "run"]

log = logging.getLogger("archery.detector")
RETRY = 1.0  # wall s between auto-calibration attempts


def _auto_calibrate(handlers: DetectorHandlers, node: Node, stop: threading.Event) -> None:
    """Calibrate from the camera's marks once it is alive (until done, refused, or `stop`)."""
    while handlers.detector is None and not stop.is_set():
        try:
            node.wait_alive([CAMERA], timeout=RETRY)
            handlers.ensure_model()
        except RpcError as exc:
            if exc.code == BadRequest.code:  # a real camera: it has no marks to offer
                log.warning("no auto-calibration: %s", exc.message)
                return
            log.info("auto-calibration not possible yet: %s", exc.message)
            stop.wait(RETRY)
        except ArcheryError as exc:
            log.warning("auto-calibration failed: %s", exc.message)
            stop.wait(RETRY)


def run(config: DetectorConfig, stop: threading.Event) -> None:
    """Serve until `stop` is set.

    OpenCV runs single-threaded here (`cv2.setNumThreads(0)`; the same results either way):
    a frame's detection is a few ms of short OpenCV calls, after each of which the pool's
    worker busy-waits (`sched_yield`); that cost the detector about 1 ms of CPU per
    measurement (of some 9 ms, 2-core host) and saved it nothing.
    """
    cv2.setNumThreads(0)
    with Node(DETECTOR, config.net) as node:
        hits = node.publisher(node.keys.detector_hits(), DetectionMessage, lossless=True)
        handlers = DetectorHandlers(config, node, hits)
        node.serve(node.keys.detector_rpc(), handlers.verbs())
        node.ready()
        log.info("detector up (%s)", "calibrated" if handlers.detector else "not calibrated yet")
        if config.auto_calibrate:
            _auto_calibrate(handlers, node, stop)
        wait_for_stop(stop)


def main(argv: list[str] | None = None) -> int:
    """`archery detector`."""
    return service_main(
        argv,
        prog=DETECTOR,
        description=__doc__.splitlines()[0],
        add_arguments=add_arguments,
        make_config=make_config,
        run=run,
    )
