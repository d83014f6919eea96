"""White balance: the colour of the scene's white, and the channel gains that map one frame's
white onto the calibration frame's (von Kries), so the UV colour model holds under other light.

The white is estimated from the frame itself: the median RGB of its bright, nearly grey pixels
(a target face's paper, a wall; at least half as bright as the frame's brightest, so that a
dark backdrop filling most of the frame is not taken for it), found iteratively so that a
tinted white (warm light) is still recognised as white. Gains are clipped to a plausible
range; a frame without such pixels has no estimate and is taken as it is.
"""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["MAX_GAIN", "apply_gains", "estimate_white", "white_gains"]

MAX_GAIN = 4.0  # largest (and 1/smallest) gain per channel
_GREY_SPREAD = 0.22  # (max − min) / max of a channel triple still called grey, after balance
_MAX_TINT = 0.7  # (max − min) / max of the warmest or coldest white accepted (≈ 2500 K)
_MIN_FRACTION = 0.01  # fewest white pixels, as a fraction of the frame
_BRIGHT_SHARE = 0.5  # a white is at least this share of the frame's brightest luma (p99)


def estimate_white(rgb: np.ndarray) -> np.ndarray | None:
    """RGB (float, 0..255) of the frame's white, or None when the frame shows too little of it.

    Args:
        rgb: an RGB uint8 image (H, W, 3), ideally downscaled (cost ∝ pixels).
    """
    pixels = np.asarray(rgb, dtype=np.float32).reshape(-1, 3)
    luma = pixels @ np.array([0.299, 0.587, 0.114], np.float32)
    # the brighter part of the frame, but never much darker than its brightest (a white face
    # on a dark boss is a small part of the frame: the boss must not pass for its white)
    low, top = np.percentile(luma, [60, 99])
    bright = pixels[(luma >= max(float(low), _BRIGHT_SHARE * float(top))) & (luma > 20)]
    if len(bright) < _MIN_FRACTION * len(pixels):
        return None
    # start from the bright pixels' median colour (grey world), so a strong tint is undone
    white = np.median(bright, axis=0) / max(float(np.median(bright)), 1.0)
    chosen = bright
    for _ in range(4):
        balanced = bright / white
        top = balanced.max(axis=1)
        spread = (top - balanced.min(axis=1)) / np.maximum(top, 1.0)
        candidates = bright[spread < _GREY_SPREAD]
        if len(candidates) < _MIN_FRACTION * len(pixels):
            break
        chosen = candidates
        white = np.median(chosen, axis=0) / max(float(np.median(chosen)), 1.0)
    white_rgb = np.median(chosen, axis=0).astype(np.float64)
    if (white_rgb.max() - white_rgb.min()) / max(white_rgb.max(), 1.0) > _MAX_TINT:
        return None  # a saturated colour, not a tinted white: the frame shows no white
    return white_rgb


def white_gains(reference: np.ndarray | None, white: np.ndarray | None) -> np.ndarray | None:
    """Per-channel gains (3,) that map `white` onto `reference`, or None if either is unknown."""
    if reference is None or white is None or np.any(np.asarray(white) <= 0):
        return None
    gains: np.ndarray = np.clip(
        np.asarray(reference, float) / np.asarray(white, float), 1 / MAX_GAIN, MAX_GAIN
    )
    return gains


def apply_gains(rgb: np.ndarray, gains: np.ndarray) -> np.ndarray:
    """RGB uint8 image with each channel multiplied by its gain (saturated at 255)."""
    matrix = np.diag(np.asarray(gains, np.float64))
    return cv2.transform(np.ascontiguousarray(rgb, dtype=np.uint8), matrix)  # saturates
