"""Draw a detection on its frame as in the paper's Fig. 9: a cross at the target centre, a circle
at the arrow tip, and r in centimetres."""

from __future__ import annotations

import cv2
import numpy as np

from services.detector.detect import Detection

__all__ = ["draw_overlay", "encode_png"]


def draw_overlay(rgb: np.ndarray, detection: Detection) -> np.ndarray:
    """A copy of the RGB frame with the estimated centre (red cross) and arrow (blue circle)."""
    out = np.ascontiguousarray(rgb).copy()
    size = max(12, min(out.shape[:2]) // 40)
    thick = max(2, size // 6)
    if detection.target is not None:
        x, y = (int(round(v)) for v in detection.target.px)
        cv2.drawMarker(out, (x, y), (255, 0, 0), cv2.MARKER_CROSS, 2 * size, thick)
    if detection.arrow is not None:
        x, y = (int(round(v)) for v in detection.arrow.px)
        cv2.circle(out, (x, y), size, (0, 80, 255), thick)
    if detection.r_m is not None:
        text = f"r = ({100 * detection.r_m[0]:+.1f}, {100 * detection.r_m[1]:+.1f}) cm"
    else:
        text = {"no_target": "no target seen", "no_arrow": "no arrow seen"}.get(
            detection.status, detection.status
        )
    scale = out.shape[0] / 900
    cv2.putText(
        out,
        text,
        (20, int(50 * scale) + 10),
        cv2.FONT_HERSHEY_SIMPLEX,
        1.2 * scale,
        (255, 255, 255),
        max(1, int(3 * scale)),
        cv2.LINE_AA,
    )
    return out


def encode_png(rgb: np.ndarray) -> bytes:
    """PNG bytes of an RGB image."""
    ok, data = cv2.imencode(".png", np.ascontiguousarray(rgb[:, :, ::-1]))
    if not ok:
        raise ValueError("PNG encoding failed")
    return data.tobytes()
