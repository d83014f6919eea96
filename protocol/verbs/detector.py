"""Verbs of the detector, `ROBOT/detector/rpc:i`: baseline, measure, calibrate, frame, status."""

from __future__ import annotations

from typing import Annotated, Any, Literal

from msgspec import Meta

from archery.protocol.verbs.base import Args, NoArgs, Reply, Verb, VerbTable

__all__ = [
    "DETECTOR_VERBS",
    "FRAME_BURST",
    "FRAME_RATE",
    "KEPT_BASELINES",
    "KEPT_FRAMES",
    "LANDING_STILL_S",
    "MAX_STILL_S",
    "MAX_TIMEOUT",
]

MAX_TIMEOUT = 120.0  # s
# frames one caller identity may ask for: FRAME_RATE a second, in bursts of FRAME_BURST (the
# excess refused `busy`); each costs the detector tens of ms of colour maps and a PNG, and a
# session's learner asks for one now and then (its latest hit's)
FRAME_RATE = 2.0  # calls/s
FRAME_BURST = 4

Timeout = Annotated[float, Meta(gt=0.0, le=MAX_TIMEOUT, description="s to wait for a frame")]

#: The detector keeps its last KEPT_BASELINES baselines (by id) for `measure`.
KEPT_BASELINES = 8
#: s the picture must be still for a landing, when a measurement with a baseline does not say.
LANDING_STILL_S = 0.5
MAX_STILL_S = 10.0  # s


class BaselineArgs(Args, frozen=True):
    """Keep a frame captured after the request arrived as the scene before a shot."""

    timeout: Timeout | None = None


class BaselineReply(Reply, frozen=True):
    baseline: Annotated[int, Meta(ge=1, description="its id, for `measure`: increasing")]
    frame_stamp: Annotated[float, Meta(description="wall s: the frame's capture")]
    frame: Annotated[int, Meta(description="the camera's frame number")]


class MeasureArgs(Args, frozen=True):
    """Measure a frame rendered at or after `after_sim_time` and captured at or after
    `after_stamp`; with neither, one captured after the request arrived.

    With `baseline` (an id `baseline` replied), measure the newest arrow once it has landed:
    frames are grabbed one after another (the first as above) until one shows a new object
    since the baseline's frame and the picture has been still for `still_s`; the tip is
    searched only where the picture changed since the baseline (`no_landing` when none comes
    within the timeout). `still_s` counts only with a baseline."""

    after_sim_time: Annotated[float, Meta(description="s: rendered at or after")] | None = None
    after_stamp: Annotated[float, Meta(description="wall s: captured at or after")] | None = None
    timeout: Timeout | None = None
    baseline: (
        Annotated[int, Meta(ge=1, description="a baseline's id: wait for a landing since it")]
        | None
    ) = None
    still_s: (
        Annotated[
            float,
            Meta(
                gt=0.0,
                le=MAX_STILL_S,
                description=f"s the picture must be still (default {LANDING_STILL_S})",
            ),
        ]
        | None
    ) = None


class CalibrateArgs(Args, frozen=True):
    """Fit the colour model on a fresh frame (the stamps as `MeasureArgs`) from `pixels`, or on
    the camera's own calibration frame and marks."""

    after_sim_time: Annotated[float, Meta(description="s: rendered at or after")] | None = None
    after_stamp: Annotated[float, Meta(description="wall s: captured at or after")] | None = None
    timeout: Timeout | None = None
    pixels: (
        Annotated[
            dict[str, Any],
            Meta(description="PIXELS.json: {target: [[x, y]…], arrow?: […]}; absent: the marks"),
        ]
        | None
    ) = None


#: The detector keeps the frames of its last KEPT_FRAMES measurements for `frame`.
KEPT_FRAMES = 8


class FrameArgs(Args, frozen=True):
    overlay: bool = True
    seq: (
        Annotated[
            int,
            Meta(ge=1, description="the measurement's seq (its reply's); absent: the last"),
        ]
        | None
    ) = None


class MeasureReply(Reply, frozen=True):
    type: str
    schema: int
    seq: int
    stamp: float
    sim_time: float | None
    frame_stamp: float
    status: Literal["ok", "no_target", "no_arrow"]
    target_px: list[float] | None
    arrow_px: list[float] | None
    target_confidence: float
    arrow_confidence: float
    r_m: (
        Annotated[
            list[float],
            Meta(
                min_length=2,
                max_length=2,
                description="m: arrow − centre on the target plane, [right, up]",
            ),
        ]
        | None
    )
    frame: int
    timing: Annotated[dict[str, float], Meta(description="s: grab_s, wait_s, detect_s")]


class CalibrateReply(Reply, frozen=True):
    target: dict[str, Any] | None
    arrow: dict[str, Any] | None
    target_pixels: int
    arrow_pixels: int
    frame_sim_time: float | None
    saved: str | None


class FrameReply(Reply, frozen=True):
    png: bytes
    status: str


class DetectorStatusReply(Reply, frozen=True):
    calibrated: bool
    model_file: str | None
    model: dict[str, Any] | None
    settings: dict[str, Any]
    measured: int


BASELINE = Verb(
    "baseline",
    BaselineArgs,
    BaselineReply,
    "keep a fresh frame as the scene before a shot, for `measure` with `baseline`",
    waits=True,  # for a fresh frame: one caller's waits never hold another's
    names_caller=True,  # waiting requests are bounded per caller identity
)

MEASURE = Verb(
    "measure",
    MeasureArgs,
    MeasureReply,
    "detect target and arrow in a fresh frame",
    waits=True,  # for a fresh frame: one caller's waits never hold another's
    names_caller=True,  # waiting measurements are bounded per caller identity
)

CALIBRATE = Verb("calibrate", CalibrateArgs, CalibrateReply, "fit the colour model from pixels")

FRAME = Verb(
    "frame",
    FrameArgs,
    FrameReply,
    "a recently measured frame as PNG (with overlay): the last, or that of `seq`",
    reads=True,
    background=True,
    names_caller=True,  # its rate is bounded per caller identity
)

STATUS = Verb(
    "status",
    NoArgs,
    DetectorStatusReply,
    "colour model, settings, frames measured",
    blocking=False,
    reads=True,
)

DETECTOR_VERBS = VerbTable(
    "detector",
    ("detector/rpc:i",),
    (
        BASELINE,
        MEASURE,
        CALIBRATE,
        FRAME,
        STATUS,
    ),
)
