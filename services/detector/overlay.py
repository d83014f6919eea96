"""Pictures of a detection, as in the paper's Fig. 9: the camera image and the pixels the colour
models keep, with a red cross at the estimated target centre, the fitted ring ellipses (green:
the inner rings, magenta: the coloured rings' outer boundary) and a blue circle at the arrow."""

from __future__ import annotations

import cv2
import numpy as np

from archery.services.detector.detect import Detection

__all__ = ["draw_overlay", "encode_png", "filtered_pixels"]

RED = (230, 20, 20)
BLUE = (20, 90, 255)
WHITE = (255, 255, 255)
GREEN = (40, 230, 90)
MAGENTA = (235, 40, 235)


def filtered_pixels(
    rgb: np.ndarray, target_m: np.ndarray, arrow_m: np.ndarray | None
) -> np.ndarray:
    """Fig. 9 (right): each pixel's colour where a model claims it, weighted by its membership
    (0..255), on black elsewhere. Only the claimed pixels (a few % of a frame) are weighted:
    the rest are black without arithmetic."""
    weight = target_m.astype(np.float32)
    if arrow_m is not None:
        weight = np.maximum(weight, arrow_m.astype(np.float32))
    out = np.zeros(rgb.shape, np.uint8)
    claimed = weight != 0
    shade = rgb[claimed].astype(np.float32) * (weight[claimed][:, None] / 255.0)
    out[claimed] = shade.astype(np.uint8)
    return out


def _marks(image: np.ndarray, detection: Detection) -> None:
    size = max(12, min(image.shape[:2]) // 40)
    thick = max(2, size // 6)
    for i, ring in enumerate(detection.rings):
        colour = MAGENTA if i == len(detection.rings) - 1 else GREEN
        (cx, cy), (w, h), angle = ring.cv_box()
        cv2.ellipse(
            image,
            (round(cx * 16), round(cy * 16)),
            (round(w * 8), round(h * 8)),
            angle,
            0,
            360,
            colour,
            max(1, thick // 2),
            cv2.LINE_AA,
            4,
        )
    if detection.target is not None:
        x, y = (round(v) for v in detection.target.px)
        cv2.drawMarker(image, (x, y), RED, cv2.MARKER_CROSS, 2 * size, thick, cv2.LINE_AA)
    if detection.arrow is not None:
        x, y = (round(v) for v in detection.arrow.px)
        cv2.circle(image, (x, y), size, BLUE, thick, cv2.LINE_AA)


def _caption(detection: Detection) -> str:
    if detection.r_m is not None:
        text = f"r = ({100 * detection.r_m[0]:+.1f} right, {100 * detection.r_m[1]:+.1f} up) cm"
    else:
        text = {"no_target": "no target seen", "no_arrow": "no arrow seen"}.get(
            detection.status, detection.status
        )
    if detection.target is not None:
        text += f"  target conf {detection.target.confidence:.2f}"
    if detection.arrow is not None:
        text += f"  arrow conf {detection.arrow.confidence:.2f}"
    return text


def draw_overlay(
    rgb: np.ndarray,
    detection: Detection,
    memberships: tuple[np.ndarray, np.ndarray | None] | None = None,
) -> np.ndarray:
    """The frame (RGB uint8) with the estimated centre (red cross), the arrow (blue circle) and a
    caption with r (cm) and the confidences; with `memberships` (the detector's maps), the
    filtered pixels are drawn beside it with the same marks, as in Fig. 9."""
    frame = np.ascontiguousarray(rgb).copy()
    _marks(frame, detection)
    if memberships is not None:
        right = filtered_pixels(rgb, *memberships)
        _marks(right, detection)
        gap = np.full((frame.shape[0], max(4, frame.shape[1] // 100), 3), 255, np.uint8)
        frame = np.ascontiguousarray(np.hstack([frame, gap, right]))
    scale = max(0.5, min(frame.shape[0], frame.shape[1]) / 900)
    height = int(44 * scale)
    band = frame[:height]
    band[:] = (0.35 * band).astype(np.uint8)
    cv2.putText(
        frame,
        _caption(detection),
        (int(12 * scale), int(32 * scale)),
        cv2.FONT_HERSHEY_SIMPLEX,
        0.9 * scale,
        WHITE,
        max(1, round(2 * scale)),
        cv2.LINE_AA,
    )
    return frame


def encode_png(rgb: np.ndarray) -> bytes:
    """PNG bytes of an RGB image."""
    ok, data = cv2.imencode(".png", np.ascontiguousarray(rgb[:, :, ::-1]))
    if not ok:
        raise ValueError(f"PNG encoding of a {rgb.shape} image failed")
    return data.tobytes()
