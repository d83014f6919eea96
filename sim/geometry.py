"""Geometry of the archery range, in the iCub `root_link` frame (x backward, y right, z up; m).

The robot faces −x. The target plane is x = −distance; its centre sits straight ahead of the
nominal bow hand, so a level shot falls short below the centre and the learner must aim.
"""

from __future__ import annotations

import numpy as np

from archery.protocol import robotspec

__all__ = [
    "BOW_HAND",
    "INNER_RING_RADIUS",
    "START_THETA",
    "TARGET_DIAMETER",
    "TARGET_DISTANCE",
    "target_centre",
]

TARGET_DISTANCE = 2.2  # m, robot root to target plane (the paper's Fig. 7)
TARGET_DIAMETER = 0.50  # m
INNER_RING_RADIUS = robotspec.HIT_RADIUS  # m, a "hit" is ‖r‖ < this (the paper's Section IV)
BOW_HAND = np.array(robotspec.BOW_HAND)  # m, nominal left (bow) hand position
START_THETA = np.array(robotspec.NOMINAL_THETA)  # m, initial string-hand offset from the bow hand


def target_centre(distance: float = TARGET_DISTANCE) -> np.ndarray:
    """Centre of the target face (m, root frame) for a target `distance` metres ahead."""
    return np.array([-distance, BOW_HAND[1], BOW_HAND[2]])


# The reward vector r (the paper's 2-D "augmented reward") is the arrow's offset from the target
# centre on the target plane, in metres: r[0] to the robot's right (+y), r[1] up (+z).
