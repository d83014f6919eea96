"""Detection of the target centre m_T and the arrow tip m_A in a frame, and r in metres.

The paper's Eq. 7 as printed weights every pixel alike (`eq7_centroid` says why and what is
kept of it); the centre comes from the geometry of the face instead (`services.detector.target`,
`rings`: `Detector.detect`), the tip from Eq. 7's weighted centroid (`Detector._find_arrow`),
and r from both with the face's known size (`Detector.from_fit`, which states the reward's
convention). docs/detector.md tells the method.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from archery.protocol.errors import ConfigError
from archery.protocol.text import shown
from archery.services.detector.colour_model import ColourModel
from archery.services.detector.errors import ImageError
from archery.services.detector.rings import Ellipse
from archery.services.detector.target import FaceFit, colour_groups, find_face, merge_faces
from archery.services.detector.whitebalance import apply_gains, estimate_white, white_gains

__all__ = [
    "MAX_IMAGE_SIDE",
    "MIN_IMAGE_SIDE",
    "Detection",
    "Detector",
    "DetectorSettings",
    "Seen",
    "check_image",
    "eq7_centroid",
]

log = logging.getLogger("archery.detector")
MIN_IMAGE_SIDE = 32  # px
MAX_IMAGE_SIDE = 8192  # px
ANALYSIS_SIDE = 240  # px: the block-averaged arrow map's shorter side
FACE_SIDE = 360  # px: the downscaled frame's shorter side for the face and its rings
FACE_SPREAD = 12.0  # UV levels: added standard deviation of the target colours for the face
CHROMA_GAINS = (0.6, 1.5)  # chroma scales of the frame against the calibration also tried
WASHED_GAINS = (1.0, 0.8, 0.65, 0.5)  # chroma scales of a face washed out in places by a sheen
SURE = 0.75  # a face this confident is not searched for again under the white balance
WHITE_SIDE = 64  # px: the shorter side of the copy the white is estimated on


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
    min_target_fraction: float = 1e-4
    min_target_confidence: float = 0.5
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
                    f"detector setting {name} = {shown(value)} is outside [{low:g}, {high:g}]"
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
        rings: the fitted ring ellipses (px, inner → outer; the last is the coloured rings'
            outer boundary), empty without a target.
        gains: the white balance (RGB channel gains) the face was found under, None: as is.
    """

    target: Seen | None
    arrow: Seen | None
    r_m: tuple[float, float] | None
    metres_per_px: np.ndarray | None
    status: str
    rings: tuple[Ellipse, ...] = ()
    gains: tuple[float, float, float] | None = None

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


def eq7_centroid(weights: np.ndarray) -> tuple[float, float] | None:
    """The plain Eq. 7 centre Σ w(x) x / Σ w(x) over the image (px: column, row), or None if
    Σ w = 0.

    The paper's Eq. 7 estimates an object's centre as a likelihood-weighted sum of pixel
    positions. As printed it divides each pixel's term by that pixel's own total likelihood
    S_xy, which gives every pixel the weight 1 (the centre of the whole image, whatever it
    shows). This is what the method means: a weighted centroid normalised over the image, with
    w(x) the pixel's membership of the object's colour model.
    """
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


def _nonzero_blocks(image: np.ndarray, s: int) -> tuple[np.ndarray, int, int] | None:
    """The part of `_block_mean(image, s)` that holds its non-zero blocks, and its corner
    (column, row in blocks); None when every block of a uint8 map is zero.

    The rest of the block map is zero (blocks of zero pixels), so it is neither averaged nor
    searched. The part starts on an even block row and column: the 2×2 tiles of OpenCV's
    connected-component labelling then fall as on the whole map, so labels, their order and
    their stats are those of the whole map (shifted by the corner). Only a uint8 map (the
    tables' memberships) is cut: its block means are integer arithmetic, the same wherever
    the part starts; a float map's depend on where its rows start (vectorised sums), so its
    part is the whole map.
    """
    if image.dtype != np.uint8:
        return _block_mean(image, s), 0, 0
    x, y, w, h = cv2.boundingRect(image)  # the non-zero pixels (0, 0, 0, 0 for none)
    rows, cols = image.shape[0] // s, image.shape[1] // s
    bx0, by0 = (x // s) & ~1, (y // s) & ~1
    bx1, by1 = min(cols, -(-(x + w) // s)), min(rows, -(-(y + h) // s))
    if w == 0 or bx1 <= x // s or by1 <= y // s:
        return None  # nothing, or only in the remainders the block map drops
    part = image[by0 * s : by1 * s, bx0 * s : bx1 * s]
    return _block_mean(part, s), bx0, by0


def _chroma_scaled(table: np.ndarray, gain: float) -> np.ndarray:
    """A flat [U + 256·V] table for frames whose chroma is `gain` times the calibration's:
    entry (u, v) is the original's at 128 + (u − 128, v − 128) / gain (nearest level)."""
    levels = np.clip(np.round(128 + (np.arange(256) - 128) / gain), 0, 255).astype(np.int64)
    return np.ascontiguousarray(table[levels[None, :] + 256 * levels[:, None]].ravel())


def downscale(image: np.ndarray, side: int = FACE_SIDE) -> tuple[np.ndarray, float]:
    """The image (H, W[, C]) area-averaged so that its shorter side is about `side` px (never
    enlarged), and the factor (full-resolution px per downscaled px)."""
    height, width = image.shape[:2]
    factor = min(height, width) / side
    if factor <= 1.0:
        return image, 1.0
    size = (max(1, round(width / factor)), max(1, round(height / factor)))
    small = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
    return small, width / size[0]


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
        loose = model.widened(FACE_SPREAD**2)
        face_table = np.ascontiguousarray(loose.tables()[0].T).ravel()
        component_table = np.ascontiguousarray(loose.component_table().T).ravel()
        self._groups = colour_groups(model.target.means, model.target.weights)
        # the face tables for frames whose chroma is scaled (exposure, gamma): first as is
        self._face_tables = [face_table] + [_chroma_scaled(face_table, a) for a in CHROMA_GAINS]
        # and each scale's components (the ring colours of a pixel)
        self._component_tables = [component_table] + [
            _chroma_scaled(component_table, a) for a in CHROMA_GAINS
        ]
        # last, for a sheen washing part of the face: each colour at its best paler scale
        washed = np.stack([_chroma_scaled(face_table, a) for a in WASHED_GAINS])
        best = washed.argmax(axis=0)
        self._face_tables.append(np.ascontiguousarray(washed.max(axis=0)))
        components = np.stack([_chroma_scaled(component_table, a) for a in WASHED_GAINS])
        self._component_tables.append(
            np.ascontiguousarray(np.take_along_axis(components, best[None], axis=0)[0])
        )
        self._white = None if model.white_rgb is None else np.asarray(model.white_rgb)
        self.has_arrow_model = model.arrow is not None

    @staticmethod
    def _uv_index(rgb: np.ndarray) -> np.ndarray:
        """U + 256·V per pixel (uint16, flat) of an RGB uint8 image."""
        yuv = cv2.cvtColor(rgb, cv2.COLOR_RGB2YUV)
        height, width = yuv.shape[:2]
        # bytes 1 and 2 of each 3-byte YUV pixel, read as one little-endian uint16: U + 256·V
        return np.ndarray((height * width,), dtype="<u2", buffer=yuv, offset=1, strides=(3,))

    def memberships(self, rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """Per-pixel membership (uint8, 0..255) of the target and of the arrow (None for a
        target-only model), by one table look-up per pixel."""
        rgb = check_image(rgb)
        height, width = rgb.shape[:2]
        both = self._table.take(self._uv_index(rgb)).view(np.uint8).reshape(height, width, 2)
        target, arrow = cv2.split(both)
        return target, arrow if self.has_arrow_model else None

    def gains(self, rgb: np.ndarray) -> np.ndarray | None:
        """Channel gains mapping this frame's white onto the calibration frame's (None: the
        model has no white, or the frame shows none)."""
        return white_gains(self._white, estimate_white(downscale(check_image(rgb), WHITE_SIDE)[0]))

    def detect(self, rgb: np.ndarray, region: np.ndarray | None = None) -> Detection:
        """Detect in an RGB uint8 image (H, W, 3); the arrow's tip only where `region` (bool,
        H × W; None: anywhere) is True, the face on the whole frame.

        Real photographs break the plain Eq. 7 centroid: arrow holes and ring lines punch gaps
        in the target, distractors share its colours (a yellow logo letter, a pin), a tight
        colour cluster (yellow) outweighs a broad one (blue), light changes move the colours,
        and an oblique view shifts a centroid. So the centre comes from the face's geometry
        (`target.find_face`, `rings`): the region of target colour is fitted with a robust
        ellipse, the model's Gaussians (one colour per ring) give the nested ring discs, whose
        concentric ellipses validate each other and give the centre extrapolated to radius 0.
        The confidence says how much of the face and of its colours was seen; below
        `min_target_confidence` the target is reported as not seen.

        The face is searched on a copy downscaled to `FACE_SIDE` px (shorter side), as the frame
        is and under colour corrections (`_search`); in a large image where none is seen, again
        at twice the resolution (until the copy is within 2.5× of the image).

        Raises:
            ImageError: not an RGB uint8 image with sides of 32..8192 px, or a region of
                another size.
        """
        rgb = check_image(rgb)
        if region is not None and region.shape != rgb.shape[:2]:
            raise ImageError(f"a search region of shape {region.shape} for a frame {rgb.shape[:2]}")
        side = FACE_SIDE
        while True:
            small, factor = downscale(rgb, side)
            face, best_gains = self._search(small)
            seen = face is not None and face.confidence >= self.settings.min_target_confidence
            # a large image may hold a small face: look again at twice the resolution
            if seen or factor < 2.5:
                break
            side *= 2
        arrow_m = None
        if self.has_arrow_model:
            full = rgb if best_gains is None else apply_gains(rgb, best_gains)
            arrow_m = self.memberships(full)[1]
            if region is not None and arrow_m is not None:
                arrow_m = np.where(region, arrow_m, np.uint8(0))
        found = self.from_fit(face, factor, arrow_m)
        if best_gains is None:
            return found
        red, green, blue = (float(g) for g in best_gains)  # white_gains: one per channel
        return dataclasses.replace(found, gains=(red, green, blue))

    def _search(self, small: np.ndarray) -> tuple[FaceFit | None, np.ndarray | None]:
        """The face in a downscaled frame, as it is and under colour corrections, and the
        white-balance gains it was found with (None: as it is).

        The frame is looked at as it is, white-balanced to the calibration's white
        (`whitebalance`), with its chroma scaled and, last, with each colour taken at its best
        paler scale (a sheen of sun washes part of a face out); rings found under different
        corrections are joined (`merge_faces`).
        """
        fits: list[tuple[FaceFit, np.ndarray | None]] = []

        def best() -> FaceFit | None:
            return max((f for f, _ in fits), key=lambda f: f.confidence, default=None)

        def unsure() -> bool:
            found = best()
            return found is None or found.confidence < SURE

        def add(fit: FaceFit | None, gains: np.ndarray | None) -> None:
            if fit is not None:
                fits.append((fit, gains))

        add(self._face(small, None), None)
        gains = None
        if self._white is not None and unsure():
            gains = white_gains(self._white, estimate_white(downscale(small, WHITE_SIDE)[0]))
            if gains is not None:
                add(self._face(apply_gains(small, gains), gains), gains)
        if unsure():  # other chroma scales, on the better-balanced copy (balanced if none)
            found = best()
            option = gains if found is None else next(g for f, g in fits if f is found)
            image = small if option is None else apply_gains(small, option)
            add(self._face(image, option, len(self._face_tables), first=1), option)
        face = best()
        best_gains = next((g for f, g in fits if f is face), None)
        if face is not None and face.confidence < SURE:
            for other, _ in fits:  # rings seen under one correction complete another's
                merged = merge_faces(face, other) if other is not face else None
                if merged is not None and merged.confidence > face.confidence:
                    face = merged
        return face, best_gains

    def _face(
        self, small: np.ndarray, gains: np.ndarray | None, tables: int = 1, first: int = 0
    ) -> FaceFit | None:
        """The most confident face in a downscaled RGB frame (already multiplied by `gains`,
        if any), with the face tables `first` … `tables` − 1 (as is, then other chroma
        scales)."""
        index = self._uv_index(np.ascontiguousarray(small))
        best: FaceFit | None = None
        for table, component_table in zip(
            self._face_tables[first:tables], self._component_tables[first:tables], strict=True
        ):
            components = component_table.take(index).reshape(small.shape[:2])
            fit = find_face(
                table.take(index).reshape(small.shape[:2]),
                components,
                self._groups,
                close_fraction=self.settings.close_fraction,
                min_fraction=self.settings.min_target_fraction,
                needed_confidence=self.settings.min_target_confidence,
            )
            if fit is not None and (best is None or fit.confidence > best.confidence):
                best = fit
            if best is not None and best.confidence >= SURE:
                break
        return best

    def from_fit(self, fit: FaceFit | None, factor: float, arrow_m: np.ndarray | None) -> Detection:
        """The detection from a face fit on a map `factor` times smaller than the frame.

        Reward vector: the paper writes r = m_T − m_A in image terms. The mesh's convention is
        the arrow's offset from the centre, r[0] to the robot's right and r[1] up, in metres on
        the target plane; the camera looks at the face from the robot's side, so image columns
        grow to the right and rows grow downwards. Hence r = M (m_A − m_T) with the image-row
        sign flipped, where M maps pixels to metres: the outer ring (a disc of known diameter D
        on the face, imaged as the ellipse A·(unit disc), A = R diag(a, b) Rᵀ in px) gives
        M = (D/2) A⁻¹, which also undoes the foreshortening of an oblique view.
        """
        arrow = self._find_arrow(arrow_m) if arrow_m is not None else None
        s = self.settings
        if fit is None or fit.confidence < s.min_target_confidence:
            if fit is not None:
                log.debug("face of confidence %.2f is below the threshold", fit.confidence)
            return Detection(None, arrow, None, None, "no_target")
        shift = 0.5 * factor - 0.5  # downscaled pixel i covers full pixels i·f … (i + 1)·f − 1
        rings = tuple(e.scaled(factor, shift) for e in fit.ellipses)
        centre = np.array(fit.centre) * factor + shift
        outer = rings[-1]
        # the coloured disc of diameter D imaged as the ellipse A·(unit disc): M = (D/2)·A⁻¹
        metres = 0.5 * s.coloured_diameter_m * np.linalg.inv(outer.semi_axes_matrix())
        area = round(math.pi * outer.axes[0] * outer.axes[1] / 4)
        target = Seen(
            px=(float(centre[0]), float(centre[1])), confidence=fit.confidence, pixels=area
        )
        if arrow is None:
            return Detection(target, None, None, metres, "no_arrow", rings)
        face = metres @ (np.asarray(arrow.px) - centre)  # (right, down) on the face, m
        return Detection(target, arrow, (float(face[0]), float(-face[1])), metres, "ok", rings)

    def _find_arrow(self, membership: np.ndarray) -> Seen | None:
        """The arrow tip m_A: the plain weighted centroid (Eq. 7) of arrow membership at full
        resolution, over the strongest arrow-coloured blob (None: none strong enough, or one too
        large for a tip)."""
        s = self.settings
        height, width = membership.shape
        block = max(1, min(height, width) // ANALYSIS_SIDE)
        blocks = _nonzero_blocks(membership, block)  # the whole map's non-zero part
        if blocks is None:
            return None
        small, bx0, by0 = blocks
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
        x0, y0, w, h = (int(v) * block for v in stats[label, :4])  # px from the part's corner
        blob = labels[y0 // block : (y0 + h) // block, x0 // block : (x0 + w) // block] == label
        keep = np.kron(blob, np.ones((block, block), dtype=bool)) if block > 1 else blob
        x0, y0 = x0 + bx0 * block, y0 + by0 * block  # px of the frame
        weights = np.where(keep, membership[y0 : y0 + h, x0 : x0 + w], 0).astype(np.float32)
        centre = eq7_centroid(weights)
        if centre is None:
            return None
        rest = float(evidence.sum()) - float(evidence[best])
        strength = min(1.0, float(evidence[best]) / (4.0 * s.min_arrow_pixels))
        confidence = strength * float(evidence[best]) / (float(evidence[best]) + rest)
        return Seen(px=(x0 + centre[0], y0 + centre[1]), confidence=confidence, pixels=area)
