"""`archery detector`: the GMM colour detector on the mesh (`ROBOT/detector/rpc:i`, `hit:o`).

Verbs on `ROBOT/detector/rpc:i` (args → result):
- `measure {"after_sim_time": s, "after_stamp": s, "timeout": s}` → grabs a camera frame newer
  than those stamps (`cam/rpc:i grab` with the same args, so it never sees the scene before the
  landing; a camera that does not answer is the error `upstream_lost` naming `camera`), detects,
  publishes the `Detection` on `ROBOT/detector/hit:o` (lossless) and replies
  with it as a dict: `status` ("ok", "no_target", "no_arrow"), `r_m` = arrow − centre on the
  target plane (m; r[0] to the robot's right, r[1] up; the paper's r = m_T − m_A in pixels,
  re-expressed), `target_px`, `arrow_px` (column, row), confidences, the frame's `sim_time`
  and `frame_stamp`, plus `frame` (the camera's frame number) and `timing` {grab_s, detect_s}.
- `calibrate {"pixels": {"target": […], "arrow": […]}, "after_sim_time": s, "after_stamp": s}`
  fits the colour model on a camera frame (newer than the stamps) from the given pixels
  (PIXELS.json form), or, without `pixels`, on the camera's own `calibration` frame and marks
  (the simulated camera provides them); saved to `--model` when given. → the model summary
  (components and BIC per object) and the pixel counts.
- `frame {"overlay": true}` → {"png": bytes, "status": s}: the last measured frame, with the
  detection and the filtered pixels drawn as in the paper's Fig. 9.
- `status {}` → calibrated or not, the model summary, the settings, measurements so far.

Without `--model`, or with a model file that does not exist yet, the detector calibrates itself
from the camera's `calibration` marks as soon as the camera is alive (`--no-auto-calibrate`
turns that off).
"""

from __future__ import annotations

import logging
import threading

from mesh.node import Node
from mesh.service import service_main
from protocol.errors import ArcheryError, BadRequest, RpcError
from protocol.messages import Detection as DetectionMessage
from protocol.robotspec import CAMERA, DETECTOR
from services.detector.config import DetectorConfig, add_arguments, make_config
from services.detector.handlers import DetectorHandlers

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
    """Serve until `stop` is set."""
    with Node(DETECTOR, config.net) as node:
        hits = node.publisher(node.keys.detector_hits(), DetectionMessage, lossless=True)
        handlers = DetectorHandlers(config, node, hits)
        node.serve(node.keys.detector_rpc(), handlers.verbs())
        node.ready()
        log.info("detector up (%s)", "calibrated" if handlers.detector else "not calibrated yet")
        if config.auto_calibrate:
            _auto_calibrate(handlers, node, stop)
        stop.wait()


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
