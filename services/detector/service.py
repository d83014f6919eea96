"""`archery detector`: the GMM colour detector on the mesh (`ROBOT/detector/rpc:i`, `hit:o`).

Verbs on `ROBOT/detector/rpc:i`:
- `measure {"after_sim_time": s, "after_stamp": s, "timeout": s}` → grabs a camera frame newer
  than those stamps (so it never sees the scene before the landing), detects, publishes the
  `Detection` on `ROBOT/detector/hit:o` and replies with it as a dict: `status` ("ok",
  "no_target", "no_arrow"), `r_m` = arrow − centre on the target plane (m; r[0] to the robot's
  right, r[1] up), pixels and confidences, and `sim_time` of the frame.
- `calibrate {"pixels": {"target": […], "arrow": […]}}` fits the colour model on the newest frame
  (or on the camera's own marks when `pixels` is absent: the simulated camera provides them);
  the model is saved to `--model` when given.
- `frame {"overlay": true}` → {"png": bytes}: the last measured frame, with the detection drawn.
- `status {}` → calibrated or not, model components, counts.

Without `--model`, or with a missing model file, the detector calibrates itself from the camera's
`calibration` marks as soon as the camera is alive (`--no-auto-calibrate` turns that off).
"""

from __future__ import annotations

import argparse
import logging
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgspec
import numpy as np

from protocol.errors import ArcheryError, BadRequest, ConfigError, DecodeError, RpcError
from protocol.messages import Detection as DetectionMessage
from protocol.messages import Image
from protocol.netflags import NetConfig
from protocol.node import Node
from protocol.service import service_main
from services.detector.calibration import sample_pixels
from services.detector.colour_model import ColourModel
from services.detector.detect import Detection, Detector, DetectorSettings
from services.detector.errors import DetectorError
from services.detector.overlay import draw_overlay, encode_png

__all__ = ["DetectorConfig", "main", "run"]

log = logging.getLogger("archery.detector")


class NotCalibrated(DetectorError):
    """A measurement before any colour model exists."""

    code = "not_calibrated"


@dataclass(frozen=True)
class DetectorConfig:
    """Detector settings: model file, detection settings, camera timeout (s)."""

    net: NetConfig = field(default_factory=NetConfig)
    model: str | None = None
    settings: DetectorSettings = field(default_factory=DetectorSettings)
    auto_calibrate: bool = True
    camera_timeout: float = 10.0


def _image_from(result: Any, what: str) -> Image:
    try:
        return msgspec.convert(result, Image)
    except msgspec.ValidationError as exc:
        raise DecodeError(f"{what} is not a valid Image: {exc}") from None


class _State:
    """The detector's model and last frame; guarded by one lock."""

    def __init__(self, config: DetectorConfig) -> None:
        self.config = config
        self.lock = threading.Lock()
        self.detector: Detector | None = None
        self.model: ColourModel | None = None
        self.last: tuple[np.ndarray, Detection] | None = None
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

        def calibrate_from(image: Image, pixels: Any) -> dict[str, Any]:
            if not isinstance(pixels, dict) or "target" not in pixels:
                raise BadRequest("pixels must be {'target': [[x, y], ...], 'arrow': [...]}")
            rgb = image.to_numpy()
            target = sample_pixels(rgb, pixels["target"], "target")
            arrow = sample_pixels(rgb, pixels["arrow"], "arrow") if pixels.get("arrow") else None
            model = ColourModel.fit(target, arrow)
            state.set_model(model, save=True)
            return {
                "target_components": model.target.n_components,
                "arrow_components": model.arrow.n_components if model.arrow else None,
                "target_pixels": len(target),
                "arrow_pixels": 0 if arrow is None else len(arrow),
            }

        def calibrate(args: dict[str, Any]) -> dict[str, Any]:
            if "pixels" in args:
                image = _image_from(
                    node.call(keys.cam_rpc(), "grab", {}, timeout=config.camera_timeout), "frame"
                )
                return calibrate_from(image, args["pixels"])
            marks = node.call(keys.cam_rpc(), "calibration", {}, timeout=config.camera_timeout)
            return calibrate_from(_image_from(marks["image"], "calibration frame"), marks["pixels"])

        def measure(args: dict[str, Any]) -> dict[str, Any]:
            unknown = set(args) - {"after_sim_time", "after_stamp", "timeout"}
            if unknown:
                raise BadRequest(
                    f"measure: unknown args {sorted(unknown)}; valid: "
                    f"after_sim_time, after_stamp, timeout"
                )
            with state.lock:
                detector = state.detector
            if detector is None:
                raise NotCalibrated(
                    "the detector has no colour model yet: call `calibrate` "
                    "(or start it with --model FILE)"
                )
            timeout = float(args.get("timeout", config.camera_timeout))
            grab_args = {k: v for k, v in args.items() if k != "timeout"}
            grab_args["timeout"] = timeout
            image = _image_from(
                node.call(keys.cam_rpc(), "grab", grab_args, timeout=timeout + 1.0), "frame"
            )
            rgb = image.to_numpy()
            started = time.perf_counter()
            found = detector.detect(rgb)
            detect_ms = (time.perf_counter() - started) * 1e3
            with state.lock:
                state.last = (rgb, found)
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
            reply = msgspec.to_builtins(message)
            reply.update(frame=image.frame, detect_ms=round(detect_ms, 3))
            return reply  # type: ignore[no-any-return]

        def frame(args: dict[str, Any]) -> dict[str, Any]:
            with state.lock:
                last = state.last
            if last is None:
                raise BadRequest("no frame measured yet: call `measure` first")
            rgb, found = last
            shown = draw_overlay(rgb, found) if args.get("overlay", True) else rgb
            return {"png": encode_png(shown), "status": found.status}

        def status(args: dict[str, Any]) -> dict[str, Any]:
            with state.lock:
                model = state.model
                return {
                    "calibrated": model is not None,
                    "model": config.model,
                    "target_components": model.target.n_components if model else None,
                    "arrow_components": model.arrow.n_components if model and model.arrow else None,
                    "measured": state.measured,
                }

        node.serve(
            keys.detector_rpc(),
            {"measure": measure, "calibrate": calibrate, "frame": frame, "status": status},
        )
        node.ready()
        log.info("detector up (%s)", "calibrated" if state.detector else "not calibrated yet")
        while not stop.is_set():
            if state.detector is None and config.auto_calibrate:
                try:
                    node.wait_alive(["camera"], timeout=1.0)
                    log.info("calibrated from the camera's marks: %s", calibrate({}))
                except (ArcheryError, RpcError) as exc:
                    log.info("auto-calibration not possible yet: %s", exc)
                    stop.wait(1.0)
                    continue
            stop.wait(0.5)


def _add_arguments(parser: argparse.ArgumentParser) -> None:
    defaults = DetectorSettings()
    parser.add_argument(
        "--model", help="colour model file (read if it exists, written on calibrate)"
    )
    parser.add_argument(
        "--no-auto-calibrate",
        action="store_true",
        help="do not calibrate from the camera's marks when there is no model",
    )
    parser.add_argument(
        "--target-diameter",
        type=float,
        default=defaults.target_diameter_m,
        help="target face diameter (m)",
    )
    parser.add_argument(
        "--coloured-fraction",
        type=float,
        default=defaults.coloured_fraction,
        help="diameter of the calibrated colours over the face's",
    )
    parser.add_argument("--camera-timeout", type=float, default=10.0, help="wall s")


def _make_config(args: argparse.Namespace, net: NetConfig) -> DetectorConfig:
    if args.camera_timeout <= 0:
        raise ConfigError(f"--camera-timeout must be > 0 s, got {args.camera_timeout}")
    settings = DetectorSettings(
        target_diameter_m=args.target_diameter, coloured_fraction=args.coloured_fraction
    )
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
