"""Detection of the target centre m_T and the arrow tip m_A in a frame, and r in metres.

The paper's Eq. 7 estimates an object's centre as a likelihood-weighted sum of pixel positions.
As printed it divides each pixel's term by that pixel's own total likelihood S_xy, which gives
every pixel the weight 1 (the centre of the whole image, whatever it shows). We implement what
the method means: a weighted centroid m = Σ w(x) x / Σ w(x), normalised over the image, with
w(x) the pixel's membership of the object's colour model.

Real photographs break the plain version (measured 15–96 px off): arrow holes and ring lines
punch gaps in the target, distractors share its colours (a yellow logo letter, a pin), and a
tight colour cluster (yellow) has a higher likelihood than a broad one (blue), which drags the
centroid towards one ring. So the weights are made robust in four steps, all O(pixels):
1. each pixel goes to the more likely model, and only above a likelihood floor (the 256×256 UV
   tables of `ColourModel.tables`), so background does not pull the centroid;
2. only the largest connected region of target colour counts (distractors are separate blobs);
3. holes inside that region (arrow holes, ring lines, the arrow itself) are filled;
4. membership saturates: every pixel of the filled region weighs 1, whatever its density, so a
   colour the calibration happens to favour cannot pull the centre towards its ring.
The pixels' mean membership then measures how well the colours match the calibration and
enters the confidence: under a colour shift (warmer light) the centre stays usable but is
reported with less confidence, and below a threshold as not seen.
The region's size in the image gives the scale: the calibrated colours span a known diameter on
the face (by default the blue ring's outer edge, 0.6 of the 50 cm target).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from services.detector.colour_model import ColourModel
from services.detector.errors import ImageError

__all__ = ["Detection", "Detector", "DetectorSettings", "Seen"]

log = logging.getLogger("archery.detector")


@dataclass(frozen=True)
class DetectorSettings:
    """Detection settings.

    Attributes:
        target_diameter_m: diameter of the whole target face (m).
        coloured_fraction: diameter of the calibrated colour region over the face's diameter
            (yellow + red + blue rings of a 5- or 10-ring face: 0.6).
        min_target_fraction: smallest target region, as a fraction of the image's pixels.
        min_target_confidence: below this the target is reported as not seen.
        min_arrow_pixels: smallest arrow-tip region (px).
        max_arrow_fraction: largest arrow-tip region, as a fraction of the image (a larger one
            means the arrow's colour model also covers the scene: reported as not seen).
        close_fraction: closing kernel size over the image's shorter side (bridges ring lines).
    """

    target_diameter_m: float = 0.50
    coloured_fraction: float = 0.6
    min_target_fraction: float = 5e-4
    min_target_confidence: float = 0.6
    min_arrow_pixels: int = 6
    max_arrow_fraction: float = 0.01
    close_fraction: float = 0.01

    def __post_init__(self) -> None:
        checks = {
            "target_diameter_m": (self.target_diameter_m, 0.01, 10.0),
            "coloured_fraction": (self.coloured_fraction, 0.01, 1.0),
            "min_target_fraction": (self.min_target_fraction, 0.0, 0.5),
            "min_target_confidence": (self.min_target_confidence, 0.0, 1.0),
            "min_arrow_pixels": (self.min_arrow_pixels, 1, 100000),
            "max_arrow_fraction": (self.max_arrow_fraction, 0.0, 1.0),
            "close_fraction": (self.close_fraction, 0.0, 0.2),
        }
        for name, (value, low, high) in checks.items():
            if not (
                isinstance(value, int | float) and math.isfinite(value) and low <= value <= high
            ):
                raise ImageError(f"{name} = {value!r} is outside [{low}, {high}]")

    @property
    def coloured_diameter_m(self) -> float:
        """Diameter of the calibrated colour region on the face (m)."""
        return self.target_diameter_m * self.coloured_fraction


@dataclass(frozen=True)
class Seen:
    """An object found in the image: centre (px: column, row), confidence 0..1, area (px)."""

    px: tuple[float, float]
    confidence: float
    pixels: int

    def to_dict(self) -> dict[str, Any]:
        """JSON form: {"px": [x, y], "confidence": c}."""
        return {
            "px": [round(self.px[0], 2), round(self.px[1], 2)],
            "confidence": round(self.confidence, 3),
        }


@dataclass(frozen=True)
class Detection:
    """What one frame shows. `r_m` = arrow − centre on the target plane (m): r[0] to the right
    (image columns), r[1] up (against image rows) — the mesh's reward-vector convention."""

    target: Seen | None
    arrow: Seen | None
    r_m: tuple[float, float] | None
    metres_per_px: tuple[float, float] | None
    status: str  # "ok", "no_target", "no_arrow"

    def to_json(self) -> dict[str, Any]:
        """The offline `archery detect` output."""
        return {
            "target": self.target.to_dict() if self.target else None,
            "arrow": self.arrow.to_dict() if self.arrow else None,
            "r_m": [round(v, 5) for v in self.r_m] if self.r_m else None,
        }


class Detector:
    """Finds the target centre and the arrow tip with a `ColourModel`; cost O(pixels)."""

    def __init__(self, model: ColourModel, settings: DetectorSettings | None = None) -> None:
        self.model = model
        self.settings = settings or DetectorSettings()
        target_table, arrow_table = model.tables()
        self._target_table = target_table.ravel()
        self._arrow_table = arrow_table.ravel()
        self.has_arrow_model = model.arrow is not None

    def memberships(self, rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per-pixel membership (uint8, 0..255) of the target and of the arrow, by table look-up."""
        rgb = _check_image(rgb)
        yuv = cv2.cvtColor(rgb, cv2.COLOR_RGB2YUV)
        index = (yuv[:, :, 1].astype(np.uint16) << 8) | yuv[:, :, 2]
        return self._target_table[index], self._arrow_table[index]

    def detect(self, rgb: np.ndarray) -> Detection:
        """Detect in an RGB uint8 image (H, W, 3).

        Raises:
            ImageError: not an RGB uint8 image of at least 32×32 px.
        """
        target_m, arrow_m = self.memberships(rgb)
        target, scale = self._find_target(target_m)
        arrow = self._find_arrow(arrow_m) if self.has_arrow_model else None
        if target is None:
            return Detection(None, arrow, None, None, "no_target")
        if arrow is None:
            return Detection(target, None, None, scale, "no_arrow")
        assert scale is not None
        dx = (arrow.px[0] - target.px[0]) * scale[0]
        dy = -(arrow.px[1] - target.px[1]) * scale[1]
        return Detection(target, arrow, (dx, dy), scale, "ok")

    def _find_target(
        self, membership: np.ndarray
    ) -> tuple[Seen | None, tuple[float, float] | None]:
        s = self.settings
        height, width = membership.shape
        mask = (membership > 0).astype(np.uint8)
        size = max(3, round(min(height, width) * s.close_fraction) | 1)
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size))
        closed = cv2.morphologyEx(mask, cv2.MORPH_CLOSE, kernel)
        count, labels, stats, _ = cv2.connectedComponentsWithStats(closed, connectivity=8)
        if count < 2:
            return None, None
        largest = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
        if stats[largest, cv2.CC_STAT_AREA] < s.min_target_fraction * height * width:
            return None, None
        x0, y0, w, h = (int(v) for v in stats[largest, :4])
        region = (labels[y0 : y0 + h, x0 : x0 + w] == largest).astype(np.uint8)
        contours, _ = cv2.findContours(region, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        outline = max(contours, key=cv2.contourArea)
        filled = np.zeros_like(region)
        cv2.drawContours(filled, [outline], -1, 1, thickness=cv2.FILLED)
        # weights: every pixel of the filled region counts fully (membership saturated, holes
        # filled); partial memberships would let the colour calibration bias the centre
        moments = cv2.moments(filled, binaryImage=True)
        if moments["m00"] <= 0:
            return None, None
        cx, cy = moments["m10"] / moments["m00"], moments["m01"] / moments["m00"]
        width_px = 4 * math.sqrt(max(moments["mu20"], 1e-9) / moments["m00"])
        height_px = 4 * math.sqrt(max(moments["mu02"], 1e-9) / moments["m00"])
        # confidence: how disc-like the region is (an arc or a blotch scores low) and how well
        # its pixels match the calibrated colours (a colour shift, e.g. warmer light, lowers it)
        area = float(moments["m00"])
        solidity = area / max(cv2.contourArea(cv2.convexHull(outline)), 1.0)
        roundness = min(1.0, area / max(math.pi * width_px * height_px / 4, 1.0))
        agreement = float(membership[y0 : y0 + h, x0 : x0 + w][filled > 0].mean()) / 255.0
        confidence = min(1.0, solidity) * roundness * min(1.0, agreement / 0.8)
        if confidence < s.min_target_confidence:
            return None, None
        seen = Seen(px=(x0 + cx, y0 + cy), confidence=confidence, pixels=int(area))
        scale = (s.coloured_diameter_m / width_px, s.coloured_diameter_m / height_px)
        return seen, scale

    def _find_arrow(self, membership: np.ndarray) -> Seen | None:
        mask = (membership > 0).astype(np.uint8)
        count, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
        if count < 2:
            return None
        largest = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
        area = int(stats[largest, cv2.CC_STAT_AREA])
        if area < self.settings.min_arrow_pixels:
            return None
        if area > self.settings.max_arrow_fraction * membership.size:
            log.warning(
                "arrow-coloured region of %d px is too large for a tip (max %.0f): the arrow "
                "model covers the scene; calibrate again",
                area,
                self.settings.max_arrow_fraction * membership.size,
            )
            return None
        x0, y0, w, h = (int(v) for v in stats[largest, :4])
        region = labels[y0 : y0 + h, x0 : x0 + w] == largest
        weights = np.where(region, membership[y0 : y0 + h, x0 : x0 + w], 0).astype(np.float32)
        moments = cv2.moments(weights)
        cx, cy = moments["m10"] / moments["m00"], moments["m01"] / moments["m00"]
        rest = int(stats[1:, cv2.CC_STAT_AREA].sum()) - area
        confidence = min(1.0, area / (4 * self.settings.min_arrow_pixels)) * area / (area + rest)
        return Seen(px=(x0 + cx, y0 + cy), confidence=confidence, pixels=area)


def _check_image(rgb: Any) -> np.ndarray:
    if not isinstance(rgb, np.ndarray) or rgb.dtype != np.uint8:
        raise ImageError(f"expected an RGB uint8 image, got {getattr(rgb, 'dtype', type(rgb))}")
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ImageError(f"expected an RGB image of shape (H, W, 3), got {rgb.shape}")
    if rgb.shape[0] < 32 or rgb.shape[1] < 32:
        raise ImageError(f"image of {rgb.shape[1]}x{rgb.shape[0]} px is too small (min 32x32)")
    return np.ascontiguousarray(rgb)
