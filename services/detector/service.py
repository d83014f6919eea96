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

import argparse
import dataclasses
import logging
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgspec
import numpy as np

from protocol.cliargs import check_writable_dir
from protocol.errors import (
    ArcheryError,
    BadRequest,
    ConfigError,
    RpcError,
    RpcTimeout,
    UpstreamLost,
)
from protocol.messages import Detection as DetectionMessage
from protocol.messages import Image
from protocol.netflags import NetConfig
from protocol.node import Node
from protocol.service import service_main
from protocol.verbs import NoArgs
from protocol.verbs import detector as dv
from protocol.verbs.camera import CAMERA_VERBS, GrabArgs
from services.detector.calibration import parse_pixels, sample_pixels
from services.detector.colour_model import ColourModel
from services.detector.detect import Detection, Detector, DetectorSettings
from services.detector.errors import DetectorError, ModelFileError
from services.detector.offline import add_settings_arguments, settings_from_args
from services.detector.overlay import draw_overlay, encode_png

GRAB = CAMERA_VERBS["grab"]
CALIBRATION = CAMERA_VERBS["calibration"]

__all__ = ["DetectorConfig", "NotCalibrated", "main", "run"]

log = logging.getLogger("archery.detector")
MAX_TIMEOUT = dv.MAX_TIMEOUT  # s


class NotCalibrated(DetectorError):
    """A measurement before any colour model exists."""

    code = "not_calibrated"


@dataclass(frozen=True)
class DetectorConfig:
    """Detector settings.

    Attributes:
        net: network settings.
        model: colour model file (read at start if it exists, written by `calibrate`).
        settings: detection settings (target size, thresholds).
        auto_calibrate: without a model, calibrate from the camera's marks once it is alive.
        camera_timeout: default wait for a camera frame (s).
    """

    net: NetConfig = field(default_factory=NetConfig)
    model: str | None = None
    settings: DetectorSettings = field(default_factory=DetectorSettings)
    auto_calibrate: bool = True
    camera_timeout: float = 10.0

    def __post_init__(self) -> None:
        if not (
            isinstance(self.camera_timeout, int | float) and 0 < self.camera_timeout <= MAX_TIMEOUT
        ):
            raise ConfigError(
                f"camera timeout must be in (0, {MAX_TIMEOUT:g}] s, got {self.camera_timeout!r}"
            )


class _State:
    """The detector's model and last frame; guarded by one lock."""

    def __init__(self, config: DetectorConfig) -> None:
        self.config = config
        self.lock = threading.Lock()
        self.detector: Detector | None = None
        self.model: ColourModel | None = None
        self.last: tuple[np.ndarray, Detection, Detector] | None = None
        self.measured = 0
        if config.model and Path(config.model).exists():
            self.set_model(ColourModel.load(config.model), save=False)

    def set_model(self, model: ColourModel, *, save: bool) -> None:
        detector = Detector(model, self.config.settings)
        with self.lock:
            self.model, self.detector = model, detector
        if save and self.config.model:
            model.save(self.config.model)
            log.info("colour model saved to %s", self.config.model)


def run(config: DetectorConfig, stop: threading.Event) -> None:
    """Serve until `stop` is set."""
    state = _State(config)
    with Node("detector", config.net) as node:
        keys = node.keys
        hits = node.publisher(keys.detector_hits(), DetectionMessage, lossless=True)

        def grab(args: dv.MeasureArgs | dv.CalibrateArgs) -> Image:
            timeout = config.camera_timeout if args.timeout is None else args.timeout
            grab_args = GrabArgs(
                after_sim_time=args.after_sim_time, after_stamp=args.after_stamp, timeout=timeout
            )
            try:
                return node.call_typed(keys.cam_rpc(), GRAB, grab_args, timeout=timeout + 1.0)
            except RpcTimeout as exc:  # the camera is gone or stuck: not the detector's fault
                raise UpstreamLost("camera", f"the camera did not answer: {exc.message}") from None

        def calibrate_from(image: Image, pixels: Any) -> dv.CalibrateReply:
            marks = parse_pixels(pixels, "pixels")
            rgb = image.to_numpy()
            target = sample_pixels(rgb, marks["target"], "target")
            arrow = sample_pixels(rgb, marks["arrow"], "arrow") if "arrow" in marks else None
            model = ColourModel.fit(target, arrow)
            state.set_model(model, save=True)
            return dv.CalibrateReply(
                **model.summary(),
                target_pixels=len(target),
                arrow_pixels=0 if arrow is None else len(arrow),
                frame_sim_time=image.sim_time,
                saved=config.model,
            )

        def calibrate(args: dv.CalibrateArgs) -> dv.CalibrateReply:
            if args.pixels is not None:
                return calibrate_from(grab(args), args.pixels)
            timeout = config.camera_timeout if args.timeout is None else args.timeout
            marks = node.call_typed(keys.cam_rpc(), CALIBRATION, timeout=timeout + 30.0)
            return calibrate_from(marks.image, marks.pixels)

        calibrating = threading.Lock()

        def ensure_model() -> Detector | None:
            """The detector, calibrated from the camera's marks first if there is none yet."""
            with calibrating:
                if state.detector is None:
                    log.info(
                        "calibrated from the camera's marks: %s", calibrate(dv.CalibrateArgs())
                    )
            return state.detector

        def measure(args: dv.MeasureArgs) -> dv.MeasureReply:
            detector = ensure_model() if config.auto_calibrate else state.detector
            if detector is None:
                raise NotCalibrated(
                    "the detector has no colour model yet: call `calibrate` (with pixels for a "
                    "real camera), or start it with --model FILE"
                )
            started = time.perf_counter()
            image = grab(args)
            rgb = image.to_numpy()
            grabbed_at = time.perf_counter()
            found = detector.detect(rgb)
            detect_s = time.perf_counter() - grabbed_at
            with state.lock:
                state.last = (rgb, found, detector)
                state.measured += 1
            message = hits.put(
                DetectionMessage(
                    frame_stamp=image.stamp,
                    status=found.status,  # type: ignore[arg-type]
                    target_px=list(found.target.px) if found.target else None,
                    arrow_px=list(found.arrow.px) if found.arrow else None,
                    target_confidence=found.target.confidence if found.target else 0.0,
                    arrow_confidence=found.arrow.confidence if found.arrow else 0.0,
                    r_m=list(found.r_m) if found.r_m else None,
                    sim_time=image.sim_time,
                )
            )
            timing = {"grab_s": round(grabbed_at - started, 6), "detect_s": round(detect_s, 6)}
            return dv.MeasureReply(**msgspec.to_builtins(message), frame=image.frame, timing=timing)

        def frame(args: dv.FrameArgs) -> dv.FrameReply:
            with state.lock:
                last = state.last
            if last is None:
                raise BadRequest("no frame measured yet: call `measure` first")
            rgb, found, detector = last
            if args.overlay:
                rgb = draw_overlay(rgb, found, detector.memberships(rgb))
            return dv.FrameReply(png=encode_png(rgb), status=found.status)

        def status(args: NoArgs) -> dv.DetectorStatusReply:
            with state.lock:
                model = state.model
                return dv.DetectorStatusReply(
                    calibrated=model is not None,
                    model_file=config.model,
                    model=model.summary() if model else None,
                    settings=dataclasses.asdict(config.settings),
                    measured=state.measured,
                )

        verbs = {"measure": measure, "calibrate": calibrate, "frame": frame, "status": status}
        node.serve(keys.detector_rpc(), dv.DETECTOR_VERBS.bind(verbs))
        node.ready()
        log.info("detector up (%s)", "calibrated" if state.detector else "not calibrated yet")
        auto = config.auto_calibrate
        while auto and state.detector is None and not stop.is_set():
            try:
                node.wait_alive(["camera"], timeout=1.0)
                ensure_model()
            except RpcError as exc:
                if exc.code == BadRequest.code:  # a real camera: it has no marks to offer
                    log.warning("no auto-calibration: %s", exc.message)
                    auto = False
                else:
                    log.info("auto-calibration not possible yet: %s", exc.message)
                    stop.wait(1.0)
            except ArcheryError as exc:
                log.warning("auto-calibration failed: %s", exc.message)
                stop.wait(1.0)
        stop.wait()


def _add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--model", help="colour model file (read if it exists, written on calibrate)"
    )
    parser.add_argument(
        "--no-auto-calibrate",
        action="store_true",
        help="do not calibrate from the camera's marks when there is no model",
    )
    add_settings_arguments(parser)
    parser.add_argument("--camera-timeout", type=float, default=10.0, help="wall s")


def _make_config(args: argparse.Namespace, net: NetConfig) -> DetectorConfig:
    if args.model:
        model = Path(args.model)
        if model.exists() and not model.is_file():
            raise ConfigError(f"--model {args.model!r} is not a file")
        check_writable_dir(model.parent, f"--model {args.model!r}: folder", create=False)
    if args.model and Path(args.model).exists():
        try:
            ColourModel.load(args.model)
        except ModelFileError as exc:
            raise ConfigError(f"--model {args.model}: {exc}") from None
    settings = settings_from_args(args)
    return DetectorConfig(
        net=net,
        model=args.model,
        settings=settings,
        auto_calibrate=not args.no_auto_calibrate,
        camera_timeout=args.camera_timeout,
    )


def main(argv: list[str] | None = None) -> int:
    """`archery detector`."""
    return service_main(
        argv,
        prog="detector",
        description=__doc__.splitlines()[0],
        add_arguments=_add_arguments,
        make_config=_make_config,
        run=run,
    )
