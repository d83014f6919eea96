"""The wait of a measurement with a baseline: frames grabbed one after another until a new
object has appeared since the baseline and the picture has been still for `still_s` (frame
differencing, `services.detector.landing`), within the measurement's timeout."""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from archery.protocol.errors import Busy, RpcError, RpcTimeout
from archery.protocol.messages import Image
from archery.services.detector.errors import NoLanding
from archery.services.detector.landing import (
    Change,
    GreyFrame,
    LandingThresholds,
    compare,
    grey_frame,
    moved_fraction,
    search_region,
)

__all__ = ["FRAME_INTERVAL", "STAMP_STEP", "Grab", "Landed", "wait_for_landing"]

# wall s at least between two grabs: at most 12.5 frames/s, under the camera's limit of
# GRAB_RATE (20/s) per caller identity, which the detector's other grabs share
FRAME_INTERVAL = 0.08
STAMP_STEP = 1e-3  # s: each frame captured at least this long after the previous one

#: grab(after_sim_time s, after_stamp wall s, timeout s) → the first frame newer than both.
Grab = Callable[[float | None, float | None, float], Image]


@dataclass(frozen=True)
class Landed:
    """The frame a landing was seen in.

    Attributes:
        image: the frame as the camera sent it (its stamps and number).
        rgb: its pixels (H, W, 3) uint8.
        region: where the newest arrow is searched (bool, H × W): what changed since the
            baseline, widened.
        change: how it differs from the baseline.
        wait_s: wall s from the start of the wait to this frame's comparison.
        frames: frames grabbed and compared.
    """

    image: Image
    rgb: np.ndarray
    region: np.ndarray
    change: Change
    wait_s: float
    frames: int


@dataclass
class _Seen:
    """What the wait has seen so far, for its message when no landing comes."""

    frames: int = 0
    largest: int = 0  # compared px: the largest changed blob since the baseline
    needed: float = 0.0  # compared px: a new object's
    moved: float | None = None  # fraction changed between the last two frames
    still_s: float = 0.0  # s the picture had been still at the last frame
    camera: str | None = None  # the camera's reason for sending no frame

    def no_landing(self, name: str, waited: float, still_s: float, side: int) -> NoLanding:
        if self.frames == 0:
            return NoLanding(
                f"no landing seen in {waited:.2f} s: the camera sent no frame to compare with "
                f"{name} ({self.camera or 'none in time'})"
            )
        change = (
            f"the largest change since {name} was a blob of {self.largest} px (a new object "
            f"needs {math.ceil(self.needed)} px; px of a copy {side} px on its shorter side)"
        )
        if self.moved is None:
            motion = "one frame only, so no stillness seen"
        elif self.still_s >= still_s:
            motion = f"the picture was still ({100 * self.moved:.2g}% changed between the last two)"
        else:
            motion = (
                f"the picture was moving ({100 * self.moved:.2g}% changed between the last two; "
                f"still for {self.still_s:.2f} s of the {still_s:g} s needed)"
            )
        return NoLanding(
            f"no landing seen in {waited:.2f} s ({self.frames} frames compared with {name}): "
            f"{change}; {motion}"
        )


def wait_for_landing(
    grab: Grab,
    baseline: GreyFrame,
    *,
    name: str,
    after_sim_time: float | None,
    after_stamp: float | None,
    timeout: float,
    still_s: float,
    thresholds: LandingThresholds,
    min_arrow_pixels: float,
    interval: float = FRAME_INTERVAL,
) -> Landed:
    """Grab frames one after another (each captured after the previous one; the first after
    `after_sim_time` and `after_stamp`, wall s) until one shows a new object since `baseline`
    and every consecutive pair over the last `still_s` s (by the frames' stamps) is still.

    Args:
        grab: the camera's grab (`Grab`).
        baseline: the frame before the shot, as compared.
        name: what the messages call the baseline ("baseline 3").
        timeout: s to wait in all.
        min_arrow_pixels: full-resolution px an arrow's tip needs (`DetectorSettings`).
        interval: wall s at least between two grabs.

    Raises:
        NoLanding: none within `timeout` (the message says what was seen).
        ImageError: a frame of another size than the baseline's.
        UpstreamLost, RpcError: the camera is lost or refused the grab.
    """
    started = time.monotonic()
    deadline = started + timeout
    seen = _Seen(needed=float(thresholds.min_new_pixels))
    previous: tuple[GreyFrame, float] | None = None  # the last frame and its stamp (wall s)
    still_since = 0.0  # wall s (frame stamps): every pair since has been still
    next_grab = started
    while True:
        pause = min(next_grab, deadline) - time.monotonic()
        if pause > 0:
            time.sleep(pause)
        left = deadline - time.monotonic()
        if left <= 0:
            raise seen.no_landing(name, time.monotonic() - started, still_s, thresholds.side)
        stamp = after_stamp
        if previous is not None:
            stamp = max(previous[1] + STAMP_STEP, -math.inf if stamp is None else stamp)
        next_grab = time.monotonic() + interval
        try:
            image = grab(after_sim_time, stamp, left)
        except RpcError as exc:
            if exc.code == Busy.code:  # the camera's rate for this caller: the next in turn
                seen.camera = exc.message
                continue
            if exc.code == RpcTimeout.code and not isinstance(exc, RpcTimeout):
                seen.camera = exc.message  # the camera's own: no frame within `left`
                waited = time.monotonic() - started
                raise seen.no_landing(name, waited, still_s, thresholds.side) from None
            raise
        rgb = image.to_numpy()
        frame = grey_frame(rgb, thresholds)
        change = compare(baseline, frame, thresholds, min_arrow_pixels)
        seen.frames += 1
        seen.largest, seen.needed = max(seen.largest, change.largest), change.needed
        if previous is None:
            still_since = image.stamp
        else:
            seen.moved = moved_fraction(previous[0], frame, thresholds)
            if seen.moved >= thresholds.still_fraction:
                still_since = image.stamp
        seen.still_s = image.stamp - still_since
        previous = (frame, image.stamp)
        if change.new_object and seen.still_s >= still_s:
            return Landed(
                image=image,
                rgb=rgb,
                region=search_region(change, frame, thresholds),
                change=change,
                wait_s=time.monotonic() - started,
                frames=seen.frames,
            )
