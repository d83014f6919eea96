"""The landing seen from the camera alone: frame differencing against a frame taken before the
shot (a new object appeared) and between consecutive frames (the picture is still), and the
region where the newest arrow may be searched.

Frames are compared as grey copies downscaled so that the shorter side is `side` px (area
averaging) and Gaussian-blurred, so a camera's pixel noise and a frame's JPEG blocks do not
count as a change; the median difference of the two copies is taken off first, so a uniform
shift of the grey levels (a camera's exposure adjusting a little) does not either. Every
count here is of pixels of that copy ("compared px"), unless it says full-resolution px.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from archery.protocol.errors import ConfigError
from archery.services.detector.errors import ImageError

__all__ = [
    "Change",
    "GreyFrame",
    "LandingThresholds",
    "changed_pixels",
    "compare",
    "grey_frame",
    "moved_fraction",
    "search_region",
]


@dataclass(frozen=True)
class LandingThresholds:
    """When two frames differ, and by what.

    Attributes:
        side: shorter side of the compared copy (px); 240 px keeps an arrow a camera sees
            from the robot (a shaft ~2 px wide at 240 px of a 720 px frame) and costs ~1 ms.
        blur_sigma: Gaussian blur of the compared copy (compared px): sensor noise and JPEG
            blocks averaged out before the difference.
        grey_levels: a pixel changed when its grey level (0..255) differs by more than this,
            after the median difference is taken off: a strong camera noise (σ = 15 levels
            per full-resolution px) is σ ≈ 3 levels after the blur alone, ~1 after a 3×
            downscale too, so 20 levels is far beyond it; an arrow against the face differs
            by 50 levels or more.
        min_new_pixels: a new object is a connected blob of at least this many changed
            compared px (and at least `DetectorSettings.min_arrow_pixels` full-resolution px,
            see `compare`): a 4×3 px blob, which the noise after the blur never makes, and a
            tenth of the rendered arrow (~140 compared px).
        still_fraction: two consecutive frames are still when fewer than this fraction of
            the compared px changed (5e-4: ~50 px of a 240×427 copy; a rendered arrow that
            appears changes ~140, one that moves twice that; the noise above, none).
        margin_fraction: the changed region is widened by this fraction of the compared
            copy's shorter side (0.02: ~5 compared px, 15 px of a 720 px frame) before the
            arrow's tip is searched in it, so a tip at the edge of the change is inside.
    """

    side: int = 240
    blur_sigma: float = 1.5
    grey_levels: int = 20
    min_new_pixels: int = 12
    still_fraction: float = 5e-4
    margin_fraction: float = 0.02

    def __post_init__(self) -> None:
        checks = {
            "side": (self.side, 32, 4096),
            "blur_sigma": (self.blur_sigma, 0.0, 10.0),
            "grey_levels": (self.grey_levels, 1, 254),
            "min_new_pixels": (self.min_new_pixels, 1, 1e6),
            "still_fraction": (self.still_fraction, 0.0, 1.0),
            "margin_fraction": (self.margin_fraction, 0.0, 0.5),
        }
        for name, (value, low, high) in checks.items():
            if not (
                isinstance(value, int | float) and math.isfinite(value) and low <= value <= high
            ):
                raise ConfigError(
                    f"landing threshold {name} = {value!r} is outside [{low}, {high}]"
                )


@dataclass(frozen=True)
class GreyFrame:
    """A frame as it is compared.

    Attributes:
        pixels: the grey, downscaled, blurred copy (uint8, compared px).
        size: the full frame's (width, height) px.
    """

    pixels: np.ndarray
    size: tuple[int, int]

    @property
    def factor(self) -> float:
        """Full-resolution px per compared px (along a side)."""
        return float(self.size[0] / self.pixels.shape[1])


@dataclass(frozen=True)
class Change:
    """How a frame differs from the baseline.

    Attributes:
        mask: the changed compared px (bool).
        largest: the largest connected blob of changed px (compared px).
        needed: the blob size that makes a new object (compared px).
    """

    mask: np.ndarray
    largest: int
    needed: float

    @property
    def new_object(self) -> bool:
        """A new object appeared: the largest changed blob is large enough."""
        return self.largest >= self.needed


def grey_frame(rgb: np.ndarray, thresholds: LandingThresholds) -> GreyFrame:
    """The compared copy of an RGB uint8 frame (H, W, 3): grey, area-downscaled so the shorter
    side is `thresholds.side` px (never enlarged), blurred by `blur_sigma` compared px."""
    height, width = rgb.shape[:2]
    grey = cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2GRAY)
    factor = min(height, width) / thresholds.side
    if factor > 1.0:
        size = (max(1, round(width / factor)), max(1, round(height / factor)))
        grey = cv2.resize(grey, size, interpolation=cv2.INTER_AREA)
    if thresholds.blur_sigma > 0:
        grey = cv2.GaussianBlur(grey, (0, 0), thresholds.blur_sigma)
    return GreyFrame(pixels=grey, size=(width, height))


def changed_pixels(
    before: GreyFrame, after: GreyFrame, thresholds: LandingThresholds
) -> np.ndarray:
    """The compared px whose grey level differs by more than `grey_levels` (bool), after the
    median difference of the two frames (an exposure change) is taken off.

    Raises:
        ImageError: frames of different sizes (the camera changed its size).
    """
    if before.size != after.size:
        raise ImageError(
            f"the frames compared are of different sizes: {before.size[0]}x{before.size[1]} px "
            f"before, {after.size[0]}x{after.size[1]} px now (did the camera change its size? "
            f"take a new baseline)"
        )
    difference = after.pixels.astype(np.int16) - before.pixels.astype(np.int16)
    offset = int(np.median(difference[::4, ::4]))
    return np.abs(difference - offset) > thresholds.grey_levels


def compare(
    baseline: GreyFrame, frame: GreyFrame, thresholds: LandingThresholds, min_arrow_pixels: float
) -> Change:
    """How `frame` differs from `baseline`: a new object is a connected blob (8-connected) of
    at least `min_new_pixels` changed compared px and at least `min_arrow_pixels` full px.

    Raises:
        ImageError: frames of different sizes.
    """
    mask = changed_pixels(baseline, frame, thresholds)
    needed = max(float(thresholds.min_new_pixels), min_arrow_pixels / frame.factor**2)
    if not mask.any():
        return Change(mask, 0, needed)
    count, _, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    largest = int(stats[1:, cv2.CC_STAT_AREA].max()) if count > 1 else 0
    return Change(mask, largest, needed)


def moved_fraction(previous: GreyFrame, frame: GreyFrame, thresholds: LandingThresholds) -> float:
    """The fraction (0..1) of compared px changed between two consecutive frames; the pair is
    still when it is below `still_fraction`.

    Raises:
        ImageError: frames of different sizes.
    """
    return float(changed_pixels(previous, frame, thresholds).mean())


def search_region(change: Change, frame: GreyFrame, thresholds: LandingThresholds) -> np.ndarray:
    """The full-resolution bool mask (H, W) where the newest arrow is searched: the changed
    compared px, widened by `margin_fraction` of the copy's shorter side and scaled up."""
    mask = change.mask.astype(np.uint8)
    radius = round(thresholds.margin_fraction * min(mask.shape))
    if radius > 0:
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))
        mask = np.asarray(cv2.dilate(mask, kernel), dtype=np.uint8)
    width, height = frame.size
    full = cv2.resize(mask, (width, height), interpolation=cv2.INTER_NEAREST)
    return np.asarray(full, dtype=bool)
