"""An inner ring from the arcs where its colours meet the next ring's, shaped like the outer ring.

Arrows, their fletchings and shadows can cut a ring's disc into so many pieces that no piece,
nor their hull, is the disc. Its boundary is still seen in arcs: wherever the ring's colours
touch the next ring's. A face's rings are concentric circles; seen under a view that is
nearly affine over the face, every ring is imaged as an ellipse of the outer ring's shape,
scaled and shifted. So the outer ellipse's map to the unit circle turns the arcs into arcs of
one circle, fitted robustly (what covers the face leaves gaps, not outliers; the edges of
fletchings in ring colours are outliers). All positions are pixels of the map they come from.
"""

from __future__ import annotations

import math
from dataclasses import replace

import cv2
import numpy as np

from archery.services.detector.rings import Ellipse, perimeter_support, radial_position

__all__ = ["ring_from_arcs"]

_FEWEST = 12  # fewest boundary points for a fit
_TOLERANCES = (0.12, 0.07, 0.05)  # inlier band (fraction of the outer radius), loose → tight
_MODE_BINS = 20  # histogram bins of the points' distances from the outer centre (over its radius)
_CROSS = np.ones((3, 3), np.uint8)


def _circle(points: np.ndarray) -> tuple[float, float, float] | None:
    """Algebraic circle fit (x² + y² + D x + E y + F = 0) to points (N, 2): centre, radius."""
    design = np.column_stack([points, np.ones(len(points))])
    target = -(points**2).sum(axis=1)
    solution, *_ = np.linalg.lstsq(design, target, rcond=None)
    cx, cy = -solution[0] / 2, -solution[1] / 2
    squared = cx * cx + cy * cy - solution[2]
    if not math.isfinite(squared) or squared <= 0:
        return None
    return float(cx), float(cy), math.sqrt(squared)


def ring_from_arcs(
    outer: Ellipse, disc: np.ndarray, rest: np.ndarray, kernel: np.ndarray
) -> Ellipse | None:
    """The ellipse bounding `disc` (uint8 mask: the ring's colours and those inside it) where
    it meets `rest` (the next rings' colours), of `outer`'s shape (axis ratio and angle), or
    None when too little boundary is seen; its support is the share of the circle's
    perimeter with boundary points on it (0..1).

    Args:
        outer: the outer ring's ellipse, in the masks' pixels.
        disc: the ring's cumulative disc, same shape as `rest`.
        rest: the target colours outside it.
        kernel: how far apart (a structuring element) the two may be and still touch (the
            line printed between rings).
    """
    edge = cv2.subtract(disc, cv2.erode(disc, _CROSS))  # the disc's edge pixels
    touching = cv2.bitwise_and(edge, cv2.dilate(rest, kernel))
    ys, xs = np.nonzero(touching)
    if len(xs) < _FEWEST:
        return None
    inverse = np.linalg.inv(outer.semi_axes_matrix())
    local = (np.stack([xs, ys], axis=1) - np.asarray(outer.centre)) @ inverse.T
    # start from the circle about the outer centre at the commonest distance; refit on inliers
    distance = np.hypot(local[:, 0], local[:, 1])
    counts, edges = np.histogram(distance, bins=_MODE_BINS, range=(0.0, 1.0))
    peak = int(np.argmax(counts))
    centre, radius = np.zeros(2), float(edges[peak] + edges[peak + 1]) / 2
    for tolerance in _TOLERANCES:
        keep = np.abs(np.hypot(*(local - centre).T) - radius) < tolerance
        if keep.sum() < _FEWEST:
            return None
        fitted = _circle(local[keep])
        if fitted is None:
            return None
        centre, radius = np.array(fitted[:2]), fitted[2]
    keep = np.abs(np.hypot(*(local - centre).T) - radius) < _TOLERANCES[-1]
    if keep.sum() < _FEWEST or not 0.05 < radius < 1.0:
        return None
    middle = outer.semi_axes_matrix() @ centre + np.asarray(outer.centre)
    ring = Ellipse(
        (float(middle[0]), float(middle[1])),
        (outer.axes[0] * radius, outer.axes[1] * radius),
        outer.angle,
    )
    inliers = np.stack([xs, ys], axis=1)[keep].astype(np.float64)
    residual = float(np.sqrt(np.mean((radial_position(ring, inliers) - 1.0) ** 2))) * ring.radius
    return replace(ring, support=perimeter_support(ring, inliers), residual=residual)
