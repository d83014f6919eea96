"""Detection of the target centre m_T and the arrow tip m_A in a frame, and r in metres.

The paper's Eq. 7 estimates an object's centre as a likelihood-weighted sum of pixel positions.
As printed it divides each pixel's term by that pixel's own total likelihood S_xy, which gives
every pixel the weight 1 (the centre of the whole image, whatever it shows). We implement what
the method means: a weighted centroid m = Σ w(x) x / Σ w(x), normalised over the image, with
w(x) the pixel's membership of the object's colour model (`eq7_centroid` is that plain form).

Real photographs break the plain version (4–74 px off on the four photos of benchmarks/RESULTS.md,
more than 2 % of the diameter on three): arrow holes and ring lines
punch gaps in the target, distractors share its colours (a yellow logo letter, a pin), and a
tight colour cluster (yellow) has a higher likelihood than a broad one (blue), which drags the
centroid towards one ring. So the target's weights are made robust in four steps, all
O(pixels):
1. each pixel goes to the more likely model, and only above a likelihood floor (the 256×256 UV
   tables of `ColourModel.tables`), so background does not pull the centroid;
2. only the largest connected region of target colour counts (distractors are separate blobs);
3. holes inside that region (arrow holes, ring lines, the arrow itself) are filled;
4. membership saturates: every pixel of the filled region weighs 1, whatever its density, so a
   colour the calibration happens to favour cannot pull the centre towards its ring.
Steps 2–3 run on the membership map averaged over s×s blocks (s ≈ shorter side / 240), which
keeps a frame's cost a few milliseconds; the centroid is then that of the filled region at
block resolution, with sub-block precision from the region's size.
The region's mean membership measures how well the colours match the calibration and enters
the confidence: under a colour shift (warmer light) the centre stays usable but is reported with
less confidence, and below a threshold as not seen.

The arrow tip m_A is the plain weighted centroid (Eq. 7) of arrow membership at full
resolution, over the strongest arrow-coloured blob.

Reward vector: the paper writes r = m_T − m_A in image terms. The mesh's convention is the
arrow's offset from the centre, r[0] to the robot's right and r[1] up, in metres on the target
plane; the camera looks at the face from the robot's side, so image columns grow to the right
and rows grow downwards. Hence r = M (m_A − m_T) with the image-row sign flipped, where M maps
pixels to metres: the filled target region (a disc of known diameter D on the face, imaged as
an ellipse of second-moment matrix C in px²) gives M = (D/4) C^(-1/2), which also undoes the
foreshortening of an oblique view.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from protocol.errors import ConfigError
from services.detector.colour_model import ColourModel, rgb_to_uv_exact
from services.detector.errors import ImageError

__all__ = [
    "MAX_IMAGE_SIDE",
    "MIN_IMAGE_SIDE",
    "Detection",
    "Detector",
    "DetectorSettings",
    "Seen",
    "check_image",
    "eq7_centroid",
    "exact_memberships",
]

log = logging.getLogger("archery.detector")
MIN_IMAGE_SIDE = 32  # px
MAX_IMAGE_SIDE = 8192  # px
ANALYSIS_SIDE = 240  # px: the block-averaged map's shorter side for the region analysis


@dataclass(frozen=True)
class DetectorSettings:
    """Detection settings.

    Attributes:
        target_diameter_m: diameter of the whole target face (m).
        coloured_fraction: diameter of the calibrated colour region over the face's diameter
            (yellow + red + blue rings of a 5- or 10-ring face: 0.6).
        min_target_fraction: smallest target region, as a fraction of the image's pixels.
        min_target_confidence: below this the target is reported as not seen.
        min_arrow_pixels: smallest arrow-tip evidence (px of full membership).
        max_arrow_fraction: largest arrow-tip region, as a fraction of the image (a larger one
            means the arrow's colour model also covers the scene: reported as not seen).
        close_fraction: closing kernel size over the image's shorter side (bridges ring lines).
    """

    target_diameter_m: float = 0.50
    coloured_fraction: float = 0.6
    min_target_fraction: float = 5e-4
    min_target_confidence: float = 0.6
    min_arrow_pixels: float = 6.0
    max_arrow_fraction: float = 0.01
    close_fraction: float = 0.01

    def __post_init__(self) -> None:
        checks = {
            "target_diameter_m": (self.target_diameter_m, 0.01, 10.0),
            "coloured_fraction": (self.coloured_fraction, 0.01, 1.0),
            "min_target_fraction": (self.min_target_fraction, 0.0, 0.5),
            "min_target_confidence": (self.min_target_confidence, 0.0, 1.0),
            "min_arrow_pixels": (self.min_arrow_pixels, 1.0, 1e6),
            "max_arrow_fraction": (self.max_arrow_fraction, 0.0, 1.0),
            "close_fraction": (self.close_fraction, 0.0, 0.2),
        }
        for name, (value, low, high) in checks.items():
            if not (
                isinstance(value, int | float)
                and not isinstance(value, bool)
                and math.isfinite(value)
                and low <= value <= high
            ):
                raise ConfigError(
                    f"detector setting {name} = {value!r} is outside [{low:g}, {high:g}]"
                )

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
    """What one frame shows.

    Attributes:
        target, arrow: what was seen of each (None: not seen).
        r_m: arrow − centre on the target plane (m): r[0] to the right (image columns), r[1]
            up (against image rows) — the mesh's reward-vector convention; None unless both
            were seen.
        metres_per_px: the 2×2 map M from an image offset (px: column, row) to a face offset
            (m: right, down), from the target region; None without a target.
        status: "ok", "no_target" or "no_arrow".
    """

    target: Seen | None
    arrow: Seen | None
    r_m: tuple[float, float] | None
    metres_per_px: np.ndarray | None
    status: str

    def to_json(self) -> dict[str, Any]:
        """The offline `archery detect` output."""
        return {
            "target": self.target.to_dict() if self.target else None,
            "arrow": self.arrow.to_dict() if self.arrow else None,
            "r_m": [round(v, 5) for v in self.r_m] if self.r_m else None,
        }


def check_image(rgb: Any) -> np.ndarray:
    """Return `rgb` as a contiguous RGB uint8 (H, W, 3) array.

    Raises:
        ImageError: another type, dtype or shape, or a side outside 32..8192 px.
    """
    if not isinstance(rgb, np.ndarray):
        raise ImageError(f"expected an RGB image as a numpy array, got {type(rgb).__name__}")
    if rgb.dtype != np.uint8:
        raise ImageError(f"expected an 8-bit RGB image (uint8), got dtype {rgb.dtype}")
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ImageError(
            f"expected a colour image of shape (H, W, 3), got {rgb.shape}: colour detection "
            f"needs the U and V channels (a grey image has none)"
        )
    height, width = rgb.shape[:2]
    if min(height, width) < MIN_IMAGE_SIDE or max(height, width) > MAX_IMAGE_SIDE:
        raise ImageError(
            f"image of {width}x{height} px: each side must be {MIN_IMAGE_SIDE}..{MAX_IMAGE_SIDE} px"
        )
    return np.ascontiguousarray(rgb)


def exact_memberships(model: ColourModel, rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(target, arrow) memberships 0..255 (float32) of every pixel, from the GMMs themselves.

    The reference the tables are checked against: unrounded UV, densities evaluated per pixel
    (cost grows with the number of components).
    """
    target, arrow = model.memberships(rgb_to_uv_exact(check_image(rgb)))
    return (target * 255).astype(np.float32), (arrow * 255).astype(np.float32)


def eq7_centroid(weights: np.ndarray) -> tuple[float, float] | None:
    """The plain Eq. 7 centre Σ w(x) x / Σ w(x) over the image (px: column, row), or None if
    Σ w = 0."""
    moments = cv2.moments(np.asarray(weights, dtype=np.float32))
    if moments["m00"] <= 0:
        return None
    return moments["m10"] / moments["m00"], moments["m01"] / moments["m00"]


def _block_mean(image: np.ndarray, s: int) -> np.ndarray:
    """Mean over s×s blocks (the right and bottom remainders dropped)."""
    if s == 1:
        return image
    height, width = image.shape
    crop = image[: height - height % s, : width - width % s]
    return cv2.resize(crop, (width // s, height // s), interpolation=cv2.INTER_AREA)


def _ellipse_overlap(filled: np.ndarray, moments: dict[str, float]) -> float:
    """Intersection over union of a binary region and the ellipse of its second moments (an
    ellipse, the image of a disc, scores ≈ 1; half a disc ≈ 0.8; an arc less)."""
    area = moments["m00"]
    centre = (moments["m10"] / area, moments["m01"] / area)
    cov = np.array([[moments["mu20"], moments["mu11"]], [moments["mu11"], moments["mu02"]]]) / area
    eigenvalues, vectors = np.linalg.eigh(cov)
    semi = 2.0 * np.sqrt(np.maximum(eigenvalues, 0.0))  # a filled ellipse: variance = semi²/4
    pad = math.ceil(float(semi.max())) + 2
    canvas = np.zeros((filled.shape[0] + 2 * pad, filled.shape[1] + 2 * pad), np.uint8)
    angle = math.degrees(math.atan2(vectors[1, 0], vectors[0, 0]))
    cv2.ellipse(
        canvas,
        ((centre[0] + pad, centre[1] + pad), (2 * semi[0], 2 * semi[1]), angle),
        1,
        thickness=cv2.FILLED,
    )
    region = np.zeros_like(canvas)
    region[pad : pad + filled.shape[0], pad : pad + filled.shape[1]] = filled
    union = int(np.count_nonzero(canvas | region))
    return int(np.count_nonzero(canvas & region)) / union if union else 0.0


class Detector:
    """Finds the target centre and the arrow tip with a `ColourModel`; cost O(pixels)."""

    def __init__(self, model: ColourModel, settings: DetectorSettings | None = None) -> None:
        self.model = model
        self.settings = settings or DetectorSettings()
        target_table, arrow_table = model.tables()  # indexed [U, V]
        # one 16-bit entry per (U, V): target membership in the low byte, arrow in the high
        # byte, at flat index U + 256·V (see `memberships`)
        both = target_table.astype(np.uint16) | (arrow_table.astype(np.uint16) << 8)
        self._table = np.ascontiguousarray(both.T).ravel()
        self.has_arrow_model = model.arrow is not None

    def memberships(self, rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """Per-pixel membership (uint8, 0..255) of the target and of the arrow (None for a
        target-only model), by one table look-up per pixel."""
        rgb = check_image(rgb)
        yuv = cv2.cvtColor(rgb, cv2.COLOR_RGB2YUV)
        height, width = yuv.shape[:2]
        # bytes 1 and 2 of each 3-byte YUV pixel, read as one little-endian uint16: U + 256·V
        index = np.ndarray((height * width,), dtype="<u2", buffer=yuv, offset=1, strides=(3,))
        both = self._table.take(index).view(np.uint8).reshape(height, width, 2)
        target, arrow = cv2.split(both)
        return target, arrow if self.has_arrow_model else None

    def detect(self, rgb: np.ndarray) -> Detection:
        """Detect in an RGB uint8 image (H, W, 3).

        Raises:
            ImageError: not an RGB uint8 image with sides of 32..8192 px.
        """
        return self.locate(*self.memberships(rgb))

    def locate(self, target_m: np.ndarray, arrow_m: np.ndarray | None) -> Detection:
        """Detect from membership maps (0..255; uint8 from the tables or float from
        `exact_memberships`); `arrow_m` None for a target-only model."""
        target, centre, metres = self._find_target(target_m)
        arrow = self._find_arrow(arrow_m) if arrow_m is not None else None
        if target is None or centre is None or metres is None:
            return Detection(None, arrow, None, None, "no_target")
        if arrow is None:
            return Detection(target, None, None, metres, "no_arrow")
        face = metres @ (np.asarray(arrow.px) - centre)  # (right, down) on the face, m
        return Detection(target, arrow, (float(face[0]), float(-face[1])), metres, "ok")

    def _find_target(
        self, membership: np.ndarray
    ) -> tuple[Seen | None, np.ndarray | None, np.ndarray | None]:
        s = self.settings
        height, width = membership.shape
        block = max(1, min(height, width) // ANALYSIS_SIDE)
        small = _block_mean(membership, block)
        mask = (small > 31).astype(np.uint8)  # an eighth of the block is surely target
        size = max(3, round(min(small.shape) * s.close_fraction) | 1)
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size))
        closed = cv2.morphologyEx(mask, cv2.MORPH_CLOSE, kernel)
        count, labels, stats, _ = cv2.connectedComponentsWithStats(closed, connectivity=8)
        if count < 2:
            return None, None, None
        largest = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
        smallest = s.min_target_fraction * membership.size / (block * block)
        if stats[largest, cv2.CC_STAT_AREA] < smallest:
            return None, None, None
        x0, y0, w, h = (int(v) for v in stats[largest, :4])
        if x0 == 0 or y0 == 0 or x0 + w == small.shape[1] or y0 + h == small.shape[0]:
            log.debug("the target region touches the image border: cut, its centre unknown")
            return None, None, None
        region = (labels[y0 : y0 + h, x0 : x0 + w] == largest).astype(np.uint8)
        contours, _ = cv2.findContours(region, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        outline = max(contours, key=cv2.contourArea)
        filled = np.zeros_like(region)
        cv2.drawContours(filled, [outline], -1, 1, thickness=cv2.FILLED)
        # weights: every block of the filled region counts fully (membership saturated, holes
        # filled); partial memberships would let the colour calibration bias the centre
        moments = cv2.moments(filled, binaryImage=True)
        area = float(moments["m00"])
        if area <= 0:
            return None, None, None
        # block (i, j) covers full-resolution pixels i·s … i·s + s − 1: its centre is i·s + (s−1)/2
        cx = (x0 + moments["m10"] / area) * block + 0.5 * (block - 1)
        cy = (y0 + moments["m01"] / area) * block + 0.5 * (block - 1)
        cov = np.array([[moments["mu20"], moments["mu11"]], [moments["mu11"], moments["mu02"]]])
        cov = cov / area * block * block + np.eye(2) * (block * block - 1) / 12.0  # px²
        eigenvalues, vectors = np.linalg.eigh(cov)
        if eigenvalues[0] <= 0:
            return None, None, None
        # a disc of diameter D has second moments D²/16 per axis: M = (D/4) C^(-1/2)
        inv_sqrt = vectors @ np.diag(eigenvalues**-0.5) @ vectors.T
        metres = 0.25 * s.coloured_diameter_m * inv_sqrt
        # confidence: how elliptic the region is (a cut or occluded disc, an arc or a blotch
        # scores low) and how well its pixels match the calibrated colours (a colour shift, e.g.
        # warmer light, lowers it)
        solidity = area / max(cv2.contourArea(cv2.convexHull(outline)), 1.0)
        # IoU with the moment ellipse: ≈ 0.97 for a whole disc at block resolution, 0.81 for
        # half a disc; mapped so that a disc missing a large part cannot be reported as seen
        ellipticity = min(1.0, max(0.0, (_ellipse_overlap(filled, moments) - 0.75) / 0.2))
        agreement = float(small[y0 : y0 + h, x0 : x0 + w][filled > 0].mean()) / 255.0
        confidence = min(1.0, solidity) * ellipticity * min(1.0, agreement / 0.8)
        if confidence < s.min_target_confidence:
            log.debug("target region of confidence %.2f is below the threshold", confidence)
            return None, None, None
        seen = Seen(px=(cx, cy), confidence=confidence, pixels=round(area * block * block))
        return seen, np.array([cx, cy]), metres

    def _find_arrow(self, membership: np.ndarray) -> Seen | None:
        s = self.settings
        height, width = membership.shape
        block = max(1, min(height, width) // ANALYSIS_SIDE)
        small = _block_mean(membership, block)
        mask = (small > 0).astype(np.uint8)
        count, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
        if count < 2:
            return None
        evidence = np.bincount(labels.ravel(), weights=small.ravel(), minlength=count)[1:]
        evidence *= block * block / 255.0  # full-membership pixels per blob
        best = int(np.argmax(evidence))
        label = best + 1
        if evidence[best] < s.min_arrow_pixels:
            return None
        area = int(stats[label, cv2.CC_STAT_AREA]) * block * block
        if area > s.max_arrow_fraction * membership.size:
            log.warning(
                "arrow-coloured region of %d px is too large for a tip (max %.0f): the arrow "
                "model covers the scene; calibrate again",
                area,
                s.max_arrow_fraction * membership.size,
            )
            return None
        # the tip: Eq. 7's weighted centroid at full resolution over the blob's blocks
        x0, y0, w, h = (int(v) * block for v in stats[label, :4])
        blob = labels[y0 // block : (y0 + h) // block, x0 // block : (x0 + w) // block] == label
        keep = np.kron(blob, np.ones((block, block), dtype=bool)) if block > 1 else blob
        weights = np.where(keep, membership[y0 : y0 + h, x0 : x0 + w], 0).astype(np.float32)
        centre = eq7_centroid(weights)
        if centre is None:
            return None
        rest = float(evidence.sum()) - float(evidence[best])
        strength = min(1.0, float(evidence[best]) / (4.0 * s.min_arrow_pixels))
        confidence = strength * float(evidence[best]) / (float(evidence[best]) + rest)
        return Seen(px=(x0 + centre[0], y0 + centre[1]), confidence=confidence, pixels=area)
