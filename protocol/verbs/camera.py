"""Verbs of the camera, `ROBOT/cam/rpc:i`: grab a fresh frame, calibration marks, the scene
view (the whole robot from the side camera), status."""

from __future__ import annotations

from typing import Annotated, Literal

from msgspec import Meta

from archery.protocol.messages import Image
from archery.protocol.verbs.base import Args, NoArgs, Reply, Verb, VerbTable
from archery.protocol.verbs.robot import Scene

__all__ = ["CAMERA_VERBS", "GRAB_BURST", "GRAB_RATE", "MAX_GRAB_TIMEOUT", "SceneReply"]

MAX_GRAB_TIMEOUT = 120.0  # s
# grabs one caller identity may make: GRAB_RATE a second, in bursts of GRAB_BURST (the excess
# refused `busy`); a session's detector grabs once or twice a rollout
GRAB_RATE = 20.0  # calls/s
GRAB_BURST = 20


class GrabArgs(Args, frozen=True):
    """A frame rendered at or after `after_sim_time` and captured at or after `after_stamp`;
    with neither, one captured after the request arrived (never an older kept frame)."""

    after_sim_time: Annotated[float, Meta(description="s: rendered at or after")] | None = None
    after_stamp: Annotated[float, Meta(description="wall s: captured at or after")] | None = None
    timeout: Annotated[float, Meta(gt=0.0, le=MAX_GRAB_TIMEOUT, description="s")] | None = None


class CalibrationReply(Reply, frozen=True):
    image: Image
    pixels: Annotated[dict[str, list[list[float]]], Meta(description="{target, arrow}: [[x, y]…]")]


class SceneReply(Reply, frozen=True):
    """The newest third-person view the camera rendered (JPEG), and how it renders them.

    `status` "starting": the view is being built (the first request of a while starts it), no
    image yet; "ok": `image` is the newest view, rendered at most `period` s apart while views
    are asked for."""

    status: Literal["ok", "starting"]
    period: Annotated[float, Meta(description="s: at least this long between two renders")]
    renders: Annotated[int, Meta(description="views rendered since the camera started")]
    render_ms: Annotated[float, Meta(description="ms: the last render and its encoding")] | None
    image: Image | None = None


class CameraStatusReply(Reply, frozen=True):
    source: str
    width: int
    height: int
    rate: Annotated[float, Meta(description="frames/s")]
    encoding: str
    frames: int
    renders: int
    reuses: Annotated[int, Meta(description="frames of an unchanged scene, not rendered again")]
    render_ms: float | None
    errors: int
    latest_sim_time: float | None
    scene: Scene | None
    scene_from: str
    waiting: Annotated[int, Meta(description="grabs waiting for their frame now")] = 0


GRAB = Verb(
    "grab",
    GrabArgs,
    Image,
    "the first frame fresher than the given times (default 5 s, at most 120 s)",
    reads=True,
    waits=True,
    names_caller=True,  # waiting grabs and their rate are bounded per caller identity
)

CALIBRATION = Verb(
    "calibration",
    NoArgs,
    CalibrationReply,
    "a frame and its target/arrow marks",
    reads=True,
)

SCENE = Verb(
    "scene",
    NoArgs,
    SceneReply,
    "the newest view of the whole robot from the side camera (JPEG, a low rate)",
    blocking=False,
    reads=True,
)

STATUS = Verb(
    "status",
    NoArgs,
    CameraStatusReply,
    "source, size, rate, frames, render time",
    blocking=False,
    reads=True,
)

CAMERA_VERBS = VerbTable(
    "camera",
    ("cam/rpc:i",),
    (
        GRAB,
        CALIBRATION,
        SCENE,
        STATUS,
    ),
)
