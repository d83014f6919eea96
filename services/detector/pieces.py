"""A disc cut into pieces by what lies across it: a thick arrow shaft over the gold, many
shafts and their shadows radiating from it. Each piece alone is a part of the disc (a half, a
wedge) whose fitted ellipse is wrong; the pieces of one disc lie within the occluders' width of
each other, so they are joined (transitively, from a seed piece) and their convex hull, which
a convex disc equals, is fitted instead. All sizes are pixels of the mask the outlines come
from.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import cv2
import numpy as np

__all__ = ["JOIN_GAP", "joined_hull"]

JOIN_GAP = 0.3  # widest gap bridged between pieces, as a fraction of the seed's diameter
_LEAST = 0.02  # smallest piece joined, as a fraction of the seed's area
_ROUNDS = 4  # joining rounds (pieces reached through pieces)


def _boxes_near(boxes: np.ndarray, box: np.ndarray, gap: float) -> np.ndarray:
    """Which of the (x0, y0, x1, y1) `boxes` (N, 4) come within `gap` px of `box`."""
    dx = np.maximum(0, np.maximum(boxes[:, 0] - box[2], box[0] - boxes[:, 2]))
    dy = np.maximum(0, np.maximum(boxes[:, 1] - box[3], box[1] - boxes[:, 3]))
    near: np.ndarray = np.hypot(dx, dy) <= gap
    return near


def joined_hull(
    outlines: Sequence[np.ndarray],
    areas: Sequence[float],
    seed: int,
    gap_fraction: float = JOIN_GAP,
) -> np.ndarray | None:
    """The convex hull (an outline, (M, 1, 2) int32) of piece `seed` and of the pieces within
    `gap_fraction` × its equivalent diameter of it or of a piece already joined, or None when
    no other piece joins it.

    Args:
        outlines: the pieces' outer contours (cv2.findContours).
        areas: their areas (px²).
        seed: the index of the piece to start from.
        gap_fraction: widest gap bridged, over the seed's equivalent diameter.
    """
    area = np.asarray(areas, dtype=np.float64)
    gap = gap_fraction * math.sqrt(4.0 * area[seed] / math.pi)
    rects = np.array([cv2.boundingRect(outline) for outline in outlines], dtype=np.int64)
    boxes = np.concatenate([rects[:, :2], rects[:, :2] + rects[:, 2:]], axis=1)
    open_ = area >= _LEAST * area[seed]
    open_[seed] = False
    group = [seed]
    for _ in range(_ROUNDS):
        box = np.array([*boxes[group, :2].min(axis=0), *boxes[group, 2:].max(axis=0)])
        near = np.flatnonzero(open_ & _boxes_near(boxes, box, gap))
        if len(near) == 0:
            break
        # exact distances on a crop around the group: the group drawn, distances from it
        margin = math.ceil(gap) + 1
        x0, y0 = box[0] - margin, box[1] - margin
        shape = (box[3] - box[1] + 2 * margin, box[2] - box[0] + 2 * margin)
        outside = np.ones(shape, np.uint8)
        cv2.drawContours(outside, [outlines[i] for i in group], -1, 0, cv2.FILLED,
                         offset=(-int(x0), -int(y0)))  # fmt: skip
        distance = cv2.distanceTransform(outside, cv2.DIST_L2, 3)
        joined = []
        for i in near.tolist():
            points = outlines[i].reshape(-1, 2) - (x0, y0)
            inside = (
                (points[:, 0] >= 0) & (points[:, 1] >= 0)
                & (points[:, 0] < shape[1]) & (points[:, 1] < shape[0])
            )  # fmt: skip
            points = points[inside]
            if len(points) and distance[points[:, 1], points[:, 0]].min() <= gap:
                joined.append(i)
        if not joined:
            break
        group += joined
        open_[joined] = False
    if len(group) < 2:
        return None
    points = np.concatenate([outlines[i].reshape(-1, 2) for i in group])
    return cv2.convexHull(points.astype(np.int32))
