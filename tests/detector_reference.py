"""The detector's reference path, for the tests and benchmarks that check the fast one against
it: memberships from the GMMs themselves (no lookup tables) and detection from given membership
maps (outer boundary only)."""

from __future__ import annotations

import numpy as np

from archery.services.detector.colour_model import ColourModel, rgb_to_uv_exact
from archery.services.detector.detect import Detection, Detector, check_image, downscale
from archery.services.detector.target import find_face

__all__ = ["exact_memberships", "locate"]


def exact_memberships(model: ColourModel, rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(target, arrow) memberships 0..255 (float32) of every pixel, from the GMMs themselves.

    The reference the tables are checked against: unrounded UV, densities evaluated per pixel
    (cost grows with the number of components).
    """
    target, arrow = model.memberships(rgb_to_uv_exact(check_image(rgb)))
    return (target * 255).astype(np.float32), (arrow * 255).astype(np.float32)


def locate(detector: Detector, target_m: np.ndarray, arrow_m: np.ndarray | None) -> Detection:
    """Detect from membership maps (0..255; uint8 from the tables or float from
    `exact_memberships`); `arrow_m` None for a target-only model. Only the outer boundary of
    the face is fitted (no ring components)."""
    small, factor = downscale(np.asarray(target_m, dtype=np.float32))
    member = np.clip(np.round(small), 0, 255).astype(np.uint8)
    fit = find_face(
        member,
        close_fraction=detector.settings.close_fraction,
        min_fraction=detector.settings.min_target_fraction,
    )
    return detector.from_fit(fit, factor, arrow_m)
