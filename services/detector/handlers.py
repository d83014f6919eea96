"""The detector's RPC verbs on `ROBOT/detector/rpc:i` (`protocol.verbs.detector`): baseline,
measure, calibrate, frame, status; and the colour model they share (guarded by one lock).

The frames of the last `KEPT_FRAMES` measurements are kept (by their detection's seq), so a
client may ask for a measurement's picture later (`frame` with `seq`): the learner draws only
the latest hit's, once, instead of every hit's. The last `KEPT_BASELINES` baselines (frames
before a shot, as compared: `services.detector.landing`) are kept by id for `measure`."""

from __future__ import annotations

import collections
import dataclasses
import logging
import threading
import time
from pathlib import Path
from typing import Any

import msgspec
import numpy as np

from archery.mesh.node import Node
from archery.mesh.publisher import Publisher
from archery.mesh.rates import RateLimit
from archery.mesh.rpc_server import caller_left, caller_or_anonymous
from archery.protocol.errors import BadRequest, RpcTimeout, UpstreamLost
from archery.protocol.messages import Detection as DetectionMessage
from archery.protocol.messages import Image
from archery.protocol.robotspec import CALL_TIMEOUT, CAMERA
from archery.protocol.verbs import NoArgs, ServedVerbs
from archery.protocol.verbs import detector as dv
from archery.protocol.verbs.camera import CALIBRATION, GRAB, GrabArgs
from archery.services.detector.calibration import fit_from_marks, parse_pixels
from archery.services.detector.colour_model import ColourModel
from archery.services.detector.config import DetectorConfig
from archery.services.detector.detect import Detection, Detector
from archery.services.detector.errors import DetectorError
from archery.services.detector.landing import GreyFrame, LandingThresholds, grey_frame
from archery.services.detector.landing_wait import Landed, wait_for_landing
from archery.services.detector.overlay import draw_overlay, encode_png

__all__ = ["CALIBRATION_GRACE", "DetectorHandlers", "NotCalibrated"]

log = logging.getLogger("archery.detector")
GRAB_GRACE = 1.0  # wall s a grab's reply may take beyond the grab's own timeout
CALIBRATION_GRACE = 30.0  # wall s the camera may take to render its calibration frame


class NotCalibrated(DetectorError):
    """A measurement before any colour model exists."""

    code = "not_calibrated"


class DetectorHandlers:
    """One method per detector verb, the colour model and the last measured frame.

    Args:
        config: the detector's settings (model file, detection settings, camera wait).
        node: calls the camera's `cam/rpc:i`.
        hits: publishes each measurement on `ROBOT/detector/hit:o`.
    """

    def __init__(
        self, config: DetectorConfig, node: Node, hits: Publisher[DetectionMessage]
    ) -> None:
        self._config = config
        self._node = node
        self._hits = hits
        self._lock = threading.Lock()
        self._calibrating = threading.Lock()
        self.detector: Detector | None = None
        self._model: ColourModel | None = None
        # the last KEPT_FRAMES measured frames by their detection's seq, the newest last
        self._kept: collections.OrderedDict[int, tuple[np.ndarray, Detection, Detector]] = (
            collections.OrderedDict()
        )
        self._measured = 0
        self._landing = LandingThresholds()
        # the last KEPT_BASELINES baselines by id, the newest last
        self._baselines: collections.OrderedDict[int, GreyFrame] = collections.OrderedDict()
        self._baseline_ids = 0
        self.frames = RateLimit("detector frame", dv.FRAME_RATE, dv.FRAME_BURST)  # per caller
        if config.model and Path(config.model).exists():
            self._set_model(ColourModel.load(config.model), save=False)

    def verbs(self) -> ServedVerbs:
        """The verbs of `ROBOT/detector/rpc:i`."""
        return dv.DETECTOR_VERBS.bind(
            dv.BASELINE.to(self.baseline),
            dv.MEASURE.to(self.measure),
            dv.CALIBRATE.to(self.calibrate),
            dv.FRAME.to(self.frame),
            dv.STATUS.to(self.status),
        )

    def _set_model(self, model: ColourModel, *, save: bool) -> None:
        detector = Detector(model, self._config.settings)
        with self._lock:
            self._model, self.detector = model, detector
        if save and self._config.model:
            model.save(self._config.model)
            log.info("colour model saved to %s", self._config.model)

    def _timeout(self, args: dv.MeasureArgs | dv.CalibrateArgs | dv.BaselineArgs) -> float:
        """s to wait for the frame: the request's, else the configured one; a measurement never
        past its caller's own timeout (`RpcRequest.wait`, less the grab's grace; `CALL_TIMEOUT`
        when the request does not say), so no grab waits on for a caller that is gone."""
        timeout = self._config.camera_timeout if args.timeout is None else args.timeout
        if isinstance(args, dv.MeasureArgs | dv.BaselineArgs):
            left = caller_left()
            timeout = min(timeout, CALL_TIMEOUT if left is None else left - GRAB_GRACE)
        return max(timeout, 1e-3)

    def _grab(self, args: dv.MeasureArgs | dv.CalibrateArgs | dv.BaselineArgs) -> Image:
        if isinstance(args, dv.BaselineArgs):
            return self._grab_after(None, None, self._timeout(args))
        return self._grab_after(args.after_sim_time, args.after_stamp, self._timeout(args))

    def _grab_after(
        self, after_sim_time: float | None, after_stamp: float | None, timeout: float
    ) -> Image:
        """The camera's first frame rendered at or after `after_sim_time` (s) and captured at
        or after `after_stamp` (wall s); with neither, one captured after the grab arrived."""
        grab = GrabArgs(after_sim_time=after_sim_time, after_stamp=after_stamp, timeout=timeout)
        key = self._node.keys.cam_rpc()
        try:
            return self._node.call_typed(key, GRAB, grab, timeout=timeout + GRAB_GRACE)
        except RpcTimeout as exc:  # the camera is gone or stuck: not the detector's fault
            raise UpstreamLost(CAMERA, f"the camera did not answer: {exc.message}") from None

    def _calibrate_from(self, image: Image, pixels: Any) -> dv.CalibrateReply:
        fitted = fit_from_marks(image.to_numpy(), parse_pixels(pixels, "pixels"))
        self._set_model(fitted.model, save=True)
        return dv.CalibrateReply(
            **fitted.model.summary(),
            target_pixels=fitted.target_pixels,
            arrow_pixels=fitted.arrow_pixels,
            frame_sim_time=image.sim_time,
            saved=self._config.model,
        )

    def calibrate(self, args: dv.CalibrateArgs) -> dv.CalibrateReply:
        """Fit the colour model on a camera frame from the given pixels, or from the camera's
        own calibration frame and marks; saved to the model file when there is one."""
        if args.pixels is not None:
            return self._calibrate_from(self._grab(args), args.pixels)
        timeout = self._timeout(args) + CALIBRATION_GRACE
        marks = self._node.call_typed(self._node.keys.cam_rpc(), CALIBRATION, timeout=timeout)
        return self._calibrate_from(marks.image, marks.pixels)

    def ensure_model(self) -> Detector | None:
        """The detector, calibrated from the camera's marks first if there is none yet."""
        with self._calibrating:
            if self.detector is None:
                reply = self.calibrate(dv.CalibrateArgs())
                log.info("calibrated from the camera's marks: %s", reply)
        return self.detector

    def baseline(self, args: dv.BaselineArgs) -> dv.BaselineReply:
        """Keep a frame captured after the request arrived as the scene before a shot, under a
        new id (the last `KEPT_BASELINES` are kept), for `measure` with `baseline`."""
        image = self._grab(args)
        frame = grey_frame(image.to_numpy(), self._landing)
        with self._lock:
            self._baseline_ids += 1
            number = self._baseline_ids
            self._baselines[number] = frame
            while len(self._baselines) > dv.KEPT_BASELINES:
                self._baselines.popitem(last=False)
        return dv.BaselineReply(baseline=number, frame_stamp=image.stamp, frame=image.frame)

    def _landed(self, args: dv.MeasureArgs, number: int) -> Landed:
        """The frame of a landing since baseline `number` (`landing_wait.wait_for_landing`).

        Raises:
            BadRequest: no such kept baseline.
            NoLanding: none within the measurement's timeout.
        """
        with self._lock:
            baseline = self._baselines.get(number)
            kept = ", ".join(str(n) for n in self._baselines) or "none yet"
        if baseline is None:
            raise BadRequest(
                f"no kept baseline {number}: the detector keeps its last {dv.KEPT_BASELINES} "
                f"baselines ({kept}); call `baseline` before the shot"
            )
        return wait_for_landing(
            self._grab_after,
            baseline,
            name=f"baseline {number}",
            after_sim_time=args.after_sim_time,
            after_stamp=args.after_stamp,
            timeout=self._timeout(args),
            still_s=dv.LANDING_STILL_S if args.still_s is None else args.still_s,
            thresholds=self._landing,
            min_arrow_pixels=self._config.settings.min_arrow_pixels,
        )

    def measure(self, args: dv.MeasureArgs) -> dv.MeasureReply:
        """Grab a frame newer than the stamps, detect, publish the detection and reply with it
        (plus the camera's frame number and the timing {grab_s, wait_s, detect_s}, wall s).

        With `baseline`, the frame is that of the landing since the baseline (a new object,
        then `still_s` of a still picture: `landing_wait`), and the arrow's tip is searched
        only where the picture changed since the baseline, so an older arrow is never taken.

        Measurements wait each on a thread of their own (`Verb.waits`), at most
        `mesh.rpc_server.MAX_WAITING_PER_CALLER` of one caller identity at a time, so one
        caller's waits never hold another's, and none waits past its caller's timeout.

        Raises:
            NotCalibrated: no colour model.
            BadRequest: an unknown baseline.
            NoLanding: no landing since the baseline within the timeout.
            ImageError: a frame of another size than the baseline's.
        """
        detector = self.ensure_model() if self._config.auto_calibrate else self.detector
        if detector is None:
            raise NotCalibrated(
                "the detector has no colour model yet: call `calibrate` (with pixels for a "
                "real camera), or start it with --model FILE"
            )
        started = time.perf_counter()
        region, wait_s = None, 0.0
        if args.baseline is None:
            image = self._grab(args)
            rgb = image.to_numpy()
        else:
            landed = self._landed(args, args.baseline)
            image, rgb, region, wait_s = landed.image, landed.rgb, landed.region, landed.wait_s
        grabbed_at = time.perf_counter()
        found = detector.detect(rgb, region)
        detect_s = time.perf_counter() - grabbed_at
        with self._lock:
            self._measured += 1
        message = self._hits.put(
            DetectionMessage(
                frame_stamp=image.stamp,
                status=found.status,  # type: ignore[arg-type]  # Detection.status: ok, no_target or no_arrow
                target_px=list(found.target.px) if found.target else None,
                arrow_px=list(found.arrow.px) if found.arrow else None,
                target_confidence=found.target.confidence if found.target else 0.0,
                arrow_confidence=found.arrow.confidence if found.arrow else 0.0,
                r_m=list(found.r_m) if found.r_m else None,
                rings=[[*e.centre, *e.axes, e.angle] for e in found.rings] or None,
                sim_time=image.sim_time,
            )
        )
        with self._lock:
            self._kept[message.seq] = (rgb, found, detector)
            while len(self._kept) > dv.KEPT_FRAMES:
                self._kept.popitem(last=False)
        timing = {
            "grab_s": round(grabbed_at - started, 6),
            "wait_s": round(wait_s, 6),
            "detect_s": round(detect_s, 6),
        }
        fields = msgspec.to_builtins(message)
        del fields["rings"]  # the hits stream's, for viewers: the reply keeps its fields
        return dv.MeasureReply(**fields, frame=image.frame, timing=timing)

    def frame(self, args: dv.FrameArgs) -> dv.FrameReply:
        """The last measured frame (or that of the measurement `seq`, one of the last
        `KEPT_FRAMES`) as PNG, with the detection drawn when `overlay`; at most `FRAME_RATE` a
        second (bursts of `FRAME_BURST`) for one caller identity.

        Raises:
            Busy: the caller is past its rate.
            BadRequest: no such kept frame.
        """
        self.frames.take(caller_or_anonymous())
        with self._lock:
            if not self._kept:
                raise BadRequest("no frame measured yet: call `measure` first")
            seq = next(reversed(self._kept)) if args.seq is None else args.seq
            kept = self._kept.get(seq)
            seqs = f"{next(iter(self._kept))}..{next(reversed(self._kept))}"
        if kept is None:
            raise BadRequest(
                f"no kept frame of measurement {seq}: the detector keeps those of its last "
                f"{dv.KEPT_FRAMES} measurements ({seqs})"
            )
        rgb, found, detector = kept
        if args.overlay:
            rgb = draw_overlay(rgb, found, detector.memberships(rgb))
        return dv.FrameReply(png=encode_png(rgb), status=found.status)

    def status(self, args: NoArgs) -> dv.DetectorStatusReply:
        """Calibrated or not, the model summary, the settings, measurements so far."""
        with self._lock:
            model = self._model
            return dv.DetectorStatusReply(
                calibrated=model is not None,
                model_file=self._config.model,
                model=model.summary() if model else None,
                settings=dataclasses.asdict(self._config.settings),
                measured=self._measured,
            )
