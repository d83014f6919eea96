"""Numbers beside a plot's markers that never sit on a marker or on each other.

`place_labels` tries, for each label in the order given, a ring of offsets around its point
(nearest first) and keeps the first whose text box, as the figure's renderer lays it out
(display pixels), misses every marker disc, every label placed before it and the axes' edges;
a label with no free place is left out (the caller's colour scale still tells the order).
Call it once the figure's layout is final (after `tight_layout`, colour bars added), since
the check is made in display pixels.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["Label", "marker_discs", "overlaps_disc", "place_labels"]

# offsets tried around a point, in units of (marker radius + gap): right-up first, as a reader
# expects a number, then the other seven directions, then twice as far
_DIRECTIONS = ((1, 1), (1, -1), (-1, 1), (-1, -1), (1, 0), (-1, 0), (0, 1), (0, -1))
_GAP_PX = 2.0  # between a marker's edge and its label


@dataclass(frozen=True)
class Label:
    """A label to place: its text at `xy` (data coordinates) beside a marker of `radius_px`."""

    text: str
    xy: tuple[float, float]
    radius_px: float
    fontsize: float = 8.0
    weight: str = "normal"


def marker_discs(ax: Any) -> np.ndarray:
    """The marker discs drawn in `ax` so far: rows (x px, y px, radius px) in display pixels.

    Scatter markers (`PathCollection`, size = area in pt²) and line markers (`Line2D` with a
    marker, `markersize` in pt) count; the radius is half the marker's size, converted with
    the figure's dpi, plus half the edge width.
    """
    from matplotlib.collections import PathCollection
    from matplotlib.lines import Line2D

    px_per_pt = ax.figure.dpi / 72.0
    rows: list[np.ndarray] = []
    for artist in ax.get_children():
        if isinstance(artist, PathCollection) and artist.get_visible():
            offsets = np.asarray(artist.get_offsets(), dtype=float).reshape(-1, 2)
            if not len(offsets):
                continue
            count = len(offsets)
            sizes = np.broadcast_to(np.asarray(artist.get_sizes(), dtype=np.float64), (count,))
            widths = np.broadcast_to(np.asarray(artist.get_linewidth(), dtype=np.float64), (count,))
            radius = (0.5 * np.sqrt(sizes) + 0.5 * widths) * px_per_pt
            points = artist.get_offset_transform().transform(offsets)
            rows.append(np.column_stack([points, radius]))
        elif isinstance(artist, Line2D) and artist.get_visible():
            marker = artist.get_marker()
            if marker in (None, "", "None", " ", "none"):
                continue
            data = np.column_stack(artist.get_data()).astype(float)
            data = data[np.isfinite(data).all(axis=1)]
            if not len(data):
                continue
            radius = (artist.get_markersize() / 2 + artist.get_markeredgewidth() / 2) * px_per_pt
            points = artist.get_transform().transform(data)
            rows.append(np.column_stack([points, np.full(len(points), radius)]))
    return np.vstack(rows) if rows else np.empty((0, 3))


def overlaps_disc(box: Any, discs: np.ndarray) -> bool:
    """Whether the rectangle `box` (a matplotlib `Bbox` in display px) meets any disc."""
    if not len(discs):
        return False
    nearest_x = np.clip(discs[:, 0], box.x0, box.x1)
    nearest_y = np.clip(discs[:, 1], box.y0, box.y1)
    return bool((np.hypot(discs[:, 0] - nearest_x, discs[:, 1] - nearest_y) < discs[:, 2]).any())


def place_labels(
    ax: Any, labels: Sequence[Label], renderer: Any | None = None, *, over_markers: bool = False
) -> list[Any]:
    """Annotate `ax` with each label where it covers no marker and no other label; returns the
    annotations placed (labels with no free place are skipped). `over_markers`: where markers
    cover the plot (thousands of rollouts), a label may lie on them, on a white box, and misses
    only the other labels."""
    renderer = renderer or ax.figure.canvas.get_renderer()
    discs = np.empty((0, 3)) if over_markers else marker_discs(ax)
    frame = ax.get_window_extent(renderer)
    taken: list[Any] = []
    placed = []
    px_per_pt = ax.figure.dpi / 72.0
    for label in labels:
        for reach in (1.0, 2.2):
            spot = _first_free(
                ax, label, reach, px_per_pt, renderer, discs, frame, taken, over_markers
            )
            if spot is not None:
                annotation, box = spot
                taken.append(box)
                placed.append(annotation)
                break
    return placed


def _first_free(
    ax: Any,
    label: Label,
    reach: float,
    px_per_pt: float,
    renderer: Any,
    discs: np.ndarray,
    frame: Any,
    taken: list[Any],
    boxed: bool = False,
) -> tuple[Any, Any] | None:
    """The first annotation of `label` at `reach` that is free, with its box; None if none."""
    distance_pt = reach * (label.radius_px + _GAP_PX) / px_per_pt
    for dx, dy in _DIRECTIONS:
        norm = math.hypot(dx, dy)
        offset = (distance_pt * dx / norm, distance_pt * dy / norm)
        annotation = ax.annotate(
            label.text,
            label.xy,
            textcoords="offset points",
            xytext=offset,
            fontsize=label.fontsize,
            weight=label.weight,
            ha="left" if dx > 0 else "right" if dx < 0 else "center",
            va="bottom" if dy > 0 else "top" if dy < 0 else "center",
            zorder=6,
            bbox={"boxstyle": "round,pad=0.15", "fc": "white", "alpha": 0.85, "lw": 0}
            if boxed
            else None,
        )
        box = annotation.get_window_extent(renderer)
        inside = (
            box.x0 >= frame.x0 and box.x1 <= frame.x1 and box.y0 >= frame.y0 and box.y1 <= frame.y1
        )
        if (
            inside
            and not overlaps_disc(box, discs)
            and not any(box.overlaps(other) for other in taken)
        ):
            return annotation, box
        annotation.remove()
    return None
