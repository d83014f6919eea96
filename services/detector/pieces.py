"""A disc cut into pieces by what lies across it: a thick arrow shaft over the gold, many
shafts and their shadows radiating from it. Each piece alone is a part of the disc (a half, a
wedge) whose fitted ellipse is wrong; the pieces of one disc lie within the occluders' width of
each other, so they are joined (transitively, from a seed piece) and their convex hull, which
a convex disc equals, is fitted instead. All sizes are pixels of the mask.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

__all__ = ["JOIN_GAP", "joined_hull"]

JOIN_GAP = 0.2  # widest gap bridged between pieces, as a fraction of the seed's diameter
_LEAST = 0.02  # smallest piece joined, as a fraction of the seed's area
_ROUNDS = 4  # joining rounds (pieces reached through pieces)


def joined_hull(
    labels: np.ndarray, areas: np.ndarray, seed: int, gap_fraction: float = JOIN_GAP
) -> np.ndarray | None:
    """The filled convex hull (uint8 mask of `labels`' shape) of piece `seed` and the pieces
    within `gap_fraction` × its equivalent diameter of it or of a piece already joined, or None
    when no other piece joins it.

    Args:
        labels: connected-component labels of a mask (0: background).
        areas: pixel count per label (index 0: the background's).
        seed: the label to start from.
        gap_fraction: widest gap bridged, over the seed's equivalent diameter.
    """
    gap = gap_fraction * math.sqrt(4.0 * float(areas[seed]) / math.pi)
    big = areas >= _LEAST * areas[seed]
    big[0] = False
    group = np.zeros(len(areas), bool)
    group[seed] = True
    for _ in range(_ROUNDS):
        outside = np.where(group[labels], 0, 1).astype(np.uint8)
        distance = cv2.distanceTransform(outside, cv2.DIST_L2, 3)
        near = np.unique(labels[(distance <= gap) & (labels > 0)])
        new = near[big[near] & ~group[near]]
        if len(new) == 0:
            break
        group[new] = True
    if group.sum() < 2:
        return None
    ys, xs = np.nonzero(group[labels])
    hull = cv2.convexHull(np.stack([xs, ys], axis=1).astype(np.int32))
    filled = np.zeros(labels.shape, np.uint8)
    cv2.drawContours(filled, [hull], -1, 1, cv2.FILLED)
    return filled
