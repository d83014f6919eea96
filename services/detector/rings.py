"""Ring geometry: robust ellipse fits to the boundaries of the target's nested colour discs.

A target face is concentric circles; any view of it (oblique, perspective) images each as an
ellipse. `fit_disc` fits a disc's outer boundary robustly (its docstring says against what);
under perspective the centres of the ring ellipses are not the image of the face's centre, so
`nested_centre` extrapolates it to radius 0 from the nested ellipses. All coordinates are pixels
(x: column, y: row) of the image the masks come from.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

__all__ = [
    "Ellipse",
    "centre_spread",
    "fit_disc",
    "nested_centre",
    "perimeter_support",
    "radial_position",
]

_BINS = 36  # angular bins of the perimeter for `support`
_MIN_POINTS = 8  # fewest boundary points for a fit


@dataclass(frozen=True)
class Ellipse:
    """An image ellipse: centre (px), full axis lengths (px), angle (degrees, OpenCV's
    convention: the first axis turned by `angle` from the x axis towards y), the fraction of its
    perimeter supported by boundary points (0..1) and the RMS of the inliers' distances (px)."""

    centre: tuple[float, float]
    axes: tuple[float, float]
    angle: float
    support: float = 1.0
    residual: float = 0.0

    @property
    def radius(self) -> float:
        """Geometric mean of the semi-axes (px)."""
        return 0.5 * math.sqrt(max(self.axes[0] * self.axes[1], 0.0))

    @property
    def ratio(self) -> float:
        """Minor over major axis (1 for a circle)."""
        return min(self.axes) / max(max(self.axes), 1e-9)

    def scaled(self, factor: float, offset: float = 0.0) -> Ellipse:
        """The same ellipse in an image `factor` times larger, pixel centres shifted by `offset`
        (px of the larger image)."""
        return Ellipse(
            centre=(self.centre[0] * factor + offset, self.centre[1] * factor + offset),
            axes=(self.axes[0] * factor, self.axes[1] * factor),
            angle=self.angle,
            support=self.support,
            residual=self.residual * factor,
        )

    def moved(self, dx: float, dy: float) -> Ellipse:
        """The same ellipse shifted by (dx, dy) px."""
        centre = (self.centre[0] + dx, self.centre[1] + dy)
        return Ellipse(centre, self.axes, self.angle, self.support, self.residual)

    def box(self, shape: tuple[int, int], margin: int = 2) -> tuple[int, int, int, int]:
        """(x0, y0, x1, y1) px of its bounding box grown by `margin`, clipped to an image of
        `shape` (height, width)."""
        a, b = self.axes[0] / 2, self.axes[1] / 2
        t = math.radians(self.angle)
        half_w = math.hypot(a * math.cos(t), b * math.sin(t)) + margin
        half_h = math.hypot(a * math.sin(t), b * math.cos(t)) + margin
        x0 = max(0, math.floor(self.centre[0] - half_w))
        y0 = max(0, math.floor(self.centre[1] - half_h))
        x1 = min(shape[1], math.ceil(self.centre[0] + half_w) + 1)
        y1 = min(shape[0], math.ceil(self.centre[1] + half_h) + 1)
        return x0, y0, max(x0, x1), max(y0, y1)

    def semi_axes_matrix(self) -> np.ndarray:
        """A = R diag(a, b) Rᵀ (px), which maps the unit disc onto the ellipse."""
        t = math.radians(self.angle)
        rotation = np.array([[math.cos(t), -math.sin(t)], [math.sin(t), math.cos(t)]])
        shape: np.ndarray = rotation @ np.diag([self.axes[0] / 2, self.axes[1] / 2]) @ rotation.T
        return shape

    def to_dict(self) -> dict[str, Any]:
        """JSON form (px, degrees)."""
        return {
            "centre_px": [round(self.centre[0], 2), round(self.centre[1], 2)],
            "axes_px": [round(self.axes[0], 2), round(self.axes[1], 2)],
            "angle_deg": round(self.angle, 2),
            "support": round(self.support, 3),
        }

    def cv_box(self) -> tuple[tuple[float, float], tuple[float, float], float]:
        """The ((cx, cy), (w, h), angle) box that cv2.ellipse draws."""
        return self.centre, self.axes, self.angle


def radial_position(ellipse: Ellipse, points: np.ndarray) -> np.ndarray:
    """ρ of points (N, 2) px: 1 on the ellipse, 0 at its centre (the radius of the concentric,
    similar ellipse through each point, over the ellipse's)."""
    inverse = np.linalg.inv(ellipse.semi_axes_matrix())
    local = (np.asarray(points, dtype=np.float64) - ellipse.centre) @ inverse.T
    return np.hypot(local[:, 0], local[:, 1])


def perimeter_support(ellipse: Ellipse, points: np.ndarray) -> float:
    """Fraction of the ellipse's perimeter, in angular bins (eccentric anomaly), holding one of
    the points (N, 2) px."""
    inverse = np.linalg.inv(ellipse.semi_axes_matrix())
    local = (points - ellipse.centre) @ inverse.T
    phase = np.arctan2(local[:, 1], local[:, 0])
    bins = np.floor((phase + math.pi) / (2 * math.pi) * _BINS).astype(int) % _BINS
    return len(np.unique(bins)) / _BINS


def _fit(points: np.ndarray) -> Ellipse | None:
    if len(points) < _MIN_POINTS:
        return None
    (cx, cy), (w, h), angle = cv2.fitEllipse(points.astype(np.float32))
    if not all(math.isfinite(v) for v in (cx, cy, w, h, angle)) or min(w, h) <= 1.0:
        return None
    return Ellipse((float(cx), float(cy)), (float(w), float(h)), float(angle))


def fit_disc(
    filled: np.ndarray, offset: tuple[int, int] = (0, 0), shape: tuple[int, int] | None = None
) -> Ellipse | None:
    """Robust ellipse fit to the outer boundary of a filled region (uint8 mask, nonzero inside).

    The boundary is fitted with `cv2.fitEllipse` on the points of its convex hull (arrow shafts
    and holes notch a disc inwards: the hull removes the notches), then refitted on the inliers
    only (fletchings and distractors touching the disc bulge outwards: they leave the inliers).
    Points on the image border belong to no ring and are dropped, so a face cut by the border
    is fitted from the arc that is visible, and `support` (the fraction of the perimeter that
    has inliers) says how much of the ring was seen.

    Args:
        filled: the region, possibly a crop of a larger image.
        offset: (x, y) of the crop's corner in the image (px).
        shape: (height, width) of the whole image, whose border points are dropped; None: the
            crop is the whole image.

    Returns:
        The ellipse in image coordinates, or None when too little boundary is left.
    """
    height, width = shape if shape is not None else filled.shape[:2]
    contours, _ = cv2.findContours(filled, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    if not contours:
        return None
    outline = max(contours, key=cv2.contourArea)
    hull = cv2.convexHull(outline)
    canvas = np.zeros_like(filled)
    cv2.drawContours(canvas, [hull], -1, 1, thickness=cv2.FILLED)
    dense, _ = cv2.findContours(canvas, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    points = max(dense, key=len).reshape(-1, 2).astype(np.float64) + offset
    inside = (
        (points[:, 0] > 1) & (points[:, 1] > 1) & (points[:, 0] < width - 2)
        & (points[:, 1] < height - 2)
    )  # fmt: skip
    points = points[inside]
    ellipse = _fit(points)
    if ellipse is None:
        return None
    inliers = points
    for tolerance in (0.08, 0.05, 0.04):
        rho = radial_position(ellipse, points)
        tol = max(tolerance, 1.5 / max(ellipse.radius, 1.0))
        keep = np.abs(rho - 1.0) < tol
        if keep.sum() < _MIN_POINTS:
            break
        refit = _fit(points[keep])
        if refit is None:
            break
        ellipse, inliers = refit, points[keep]
    rho = radial_position(ellipse, inliers)
    residual = float(np.sqrt(np.mean((rho - 1.0) ** 2))) * ellipse.radius
    return Ellipse(
        ellipse.centre, ellipse.axes, ellipse.angle, perimeter_support(ellipse, inliers), residual
    )


def nested_centre(ellipses: list[Ellipse], side: float | None = None) -> tuple[float, float]:
    """The image of the common centre of concentric rings (px), from their ellipses.

    Each ellipse centre is displaced from it by an amount ∝ radius² (the perspective shift of a
    circle's centre), so the centres are fitted as c(r) = c₀ + d·r², weighted by support², and
    c₀ returned. One ellipse: its centre; two: the inner one's (too few to extrapolate safely),
    unless they are farther apart than perspective can shift them (a circle of image radius r
    is shifted by at most r²/(2f), and a camera's focal length f is at least half the image's
    longer `side` px): the rest is fit noise, and the centre is moved towards the outer one's
    by half of it.
    """
    if len(ellipses) == 2 and side:
        inner, outer = sorted(ellipses, key=lambda e: e.radius)
        apart = math.dist(inner.centre, outer.centre)
        perspective = outer.radius**2 / side
        if apart > perspective:
            share = 0.5 * (1.0 - perspective / apart)
            return (
                inner.centre[0] + share * (outer.centre[0] - inner.centre[0]),
                inner.centre[1] + share * (outer.centre[1] - inner.centre[1]),
            )
    if len(ellipses) < 3:
        inner = min(ellipses, key=lambda e: e.radius)
        return inner.centre
    r2 = np.array([e.radius**2 for e in ellipses])
    centres = np.array([e.centre for e in ellipses])
    weights = np.array([max(e.support, 0.05) ** 2 for e in ellipses])
    design = np.stack([np.ones_like(r2), r2 / r2.max()], axis=1) * np.sqrt(weights)[:, None]
    solution, *_ = np.linalg.lstsq(design, centres * np.sqrt(weights)[:, None], rcond=None)
    c0 = solution[0]
    inner = min(ellipses, key=lambda e: e.radius)
    # the shift at the inner ring is a small part of its radius; more means a bad fit
    if np.hypot(*(c0 - inner.centre)) > 0.25 * inner.radius:
        return inner.centre
    return float(c0[0]), float(c0[1])


def centre_spread(ellipses: list[Ellipse]) -> float:
    """How far the ellipses' centres stray from the perspective model c(r) = c₀ + d·r² that
    concentric rings follow: the largest distance of a centre from the fitted line (px) over
    the largest radius; 0 for fewer than three ellipses (two always fit it)."""
    if len(ellipses) < 3:
        return 0.0
    r2 = np.array([e.radius**2 for e in ellipses])
    centres = np.array([e.centre for e in ellipses])
    design = np.stack([np.ones_like(r2), r2 / r2.max()], axis=1)
    solution, *_ = np.linalg.lstsq(design, centres, rcond=None)
    misfit = np.hypot(*(centres - design @ solution).T)
    return float(misfit.max()) / max(e.radius for e in ellipses)
