"""Calibration pixels: the user's marks on one image, as points, rectangles or polygons.

PIXELS.json: `{"target": [[x, y], ...], "arrow": [[x, y], ...]}` with x the pixel column and y
the row; an entry may instead be `{"rect": [x, y, w, h]}` or `{"polygon": [[x, y], ...]}`
(every pixel inside). "arrow" may be absent for a target-only model.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from archery.protocol.text import shown
from archery.services.detector.colour_model import ColourModel
from archery.services.detector.detect import WHITE_SIDE, downscale
from archery.services.detector.errors import CalibrationError
from archery.services.detector.whitebalance import estimate_white

__all__ = ["MarkedFit", "fit_from_marks", "load_pixels", "parse_pixels", "sample_pixels"]


def _is_number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and np.isfinite(value)


def _entry_mask(entry: Any, shape: tuple[int, int], where: str) -> np.ndarray:
    height, width = shape
    mask = np.zeros((height, width), np.uint8)
    if isinstance(entry, list | tuple) and len(entry) == 2 and all(_is_number(v) for v in entry):
        x, y = round(entry[0]), round(entry[1])
        if not (0 <= x < width and 0 <= y < height):
            raise CalibrationError(
                f"{where}: point {shown(entry)} is outside the {width}x{height} image (x in "
                f"0..{width - 1}, y in 0..{height - 1}); were the pixels marked on another image?"
            )
        mask[y, x] = 1
    elif isinstance(entry, dict) and "rect" in entry:
        rect = entry["rect"]
        if not (
            isinstance(rect, list)
            and len(rect) == 4
            and all(_is_number(v) for v in rect)
            and rect[2] > 0
            and rect[3] > 0
        ):
            raise CalibrationError(
                f"{where}: rect must be [x, y, w, h] with w, h > 0, got {shown(rect)}"
            )
        x, y, w, h = (round(v) for v in rect)
        if x < 0 or y < 0 or x + w > width or y + h > height:
            raise CalibrationError(f"{where}: rect {shown(rect)} leaves the {width}x{height} image")
        mask[y : y + h, x : x + w] = 1
    elif isinstance(entry, dict) and "polygon" in entry:
        vertices = entry["polygon"]
        if (
            not isinstance(vertices, list)
            or len(vertices) < 3
            or not all(
                isinstance(v, list) and len(v) == 2 and all(_is_number(c) for c in v)
                for v in vertices
            )
        ):
            raise CalibrationError(
                f"{where}: a polygon needs ≥ 3 [x, y] vertices, got {shown(vertices)}"
            )
        points = np.asarray(vertices, dtype=np.float64)
        if np.any(points < 0) or np.any(points > [width - 1, height - 1]):
            raise CalibrationError(
                f"{where}: polygon {shown(vertices)} leaves the {width}x{height} image"
            )
        cv2.fillPoly(mask, [np.round(points).astype(np.int32)], 1)
        if not mask.any():
            raise CalibrationError(f"{where}: polygon {shown(entry['polygon'])} covers no pixel")
    else:
        raise CalibrationError(
            f"{where}: {shown(entry)} is not a point [x, y], {{'rect': [x, y, w, h]}} or "
            f"{{'polygon': [[x, y], ...]}}"
        )
    return mask


def sample_pixels(rgb: np.ndarray, entries: list[Any], name: str) -> np.ndarray:
    """RGB values (N, 3) of the marked pixels of one object (each pixel once).

    Raises:
        CalibrationError: no entries, a malformed entry, or one outside the image.
    """
    if not isinstance(entries, list) or not entries:
        raise CalibrationError(f"no calibration pixels for the {name}: mark some on the image")
    mask = np.zeros(rgb.shape[:2], np.uint8)
    for i, entry in enumerate(entries):
        mask |= _entry_mask(entry, rgb.shape[:2], f"{name}[{i}]")
    return rgb[mask > 0]


def parse_pixels(data: Any, where: str = "calibration pixels") -> dict[str, list[Any]]:
    """Check PIXELS.json content (also accepted: an object holding it under "calibration").

    Returns:
        {"target": entries} plus "arrow": entries when the set has an arrow.

    Raises:
        CalibrationError: not an object, no "target", an unknown key.
    """
    if isinstance(data, dict) and "target" not in data and "calibration" in data:
        data = data["calibration"]
    if not isinstance(data, dict):
        raise CalibrationError(
            f"{where}: expected {{'target': [[x, y], ...], 'arrow': [...]}} ('arrow' optional), "
            f"got {type(data).__name__}"
        )
    unknown = set(data) - {"target", "arrow", "note"}
    if unknown:
        raise CalibrationError(
            f"{where}: unknown keys {shown(sorted(unknown))}; valid: target, arrow (and a free "
            "'note')"
        )
    if "target" not in data:
        raise CalibrationError(f"{where}: no 'target' pixels; the target set is required")
    marks = {"target": data["target"]}
    if data.get("arrow") is not None:
        marks["arrow"] = data["arrow"]
    return marks


def load_pixels(path: str | Path) -> dict[str, list[Any]]:
    """Read PIXELS.json (see `parse_pixels`).

    Raises:
        CalibrationError: unreadable, not JSON, or not a valid set.
    """
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise CalibrationError(f"cannot read calibration pixels {str(path)!r}: {exc}") from None
    return parse_pixels(data, str(path))


@dataclass(frozen=True)
class MarkedFit:
    """A colour model fitted from an image's marked pixels, and how many pixels of each."""

    model: ColourModel
    target_pixels: int
    arrow_pixels: int


def fit_from_marks(
    rgb: np.ndarray, marks: dict[str, Any], *, max_components: int = 5, seed: int = 0
) -> MarkedFit:
    """Fit the colour model from the pixels `marks` names (`parse_pixels`) in the HxWx3 RGB
    image, with the image's white (`whitebalance.estimate_white`) as its calibration white.

    Raises:
        CalibrationError: a mark outside the image, too few pixels, or colours that overlap.
    """
    target = sample_pixels(rgb, marks["target"], "target")
    arrow = sample_pixels(rgb, marks["arrow"], "arrow") if "arrow" in marks else None
    white = estimate_white(downscale(rgb, WHITE_SIDE)[0])
    model = ColourModel.fit(
        target, arrow, max_components=max_components, seed=seed, white_rgb=white
    )
    return MarkedFit(model, len(target), 0 if arrow is None else len(arrow))
