"""θ, the archery task's policy parameter, typed once: `Theta` on the wire, `ThetaBox` for a box of
θ, and `THETA_BOX`, the θ the controller's archery posture accepts.

θ = p_string − p_bow (m; `root_link`: x backward, y right, z up) is the string hand's position
relative to the bow hand; the arrow flies along −θ/‖θ‖ (`protocol.direction`). `Theta` is 3
finite floats, both checked as θ is decoded and never as a message holding it is built (its
sender's build is not where θ enters). A process checks θ once, where it enters: a service where
the RPC server decodes the verb's `Args`, a program where it parses its flags, a Gymnasium
environment where it checks an action. `ThetaBox` is the box type of the learners' search box,
the controller's (its `status` tells it), a `start` request's `scenario.bounds`, the Gymnasium
action space; finite, low < high per axis, checked when built or decoded.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Annotated

import msgspec
import numpy as np
from msgspec import Meta

from archery.protocol.messages import FiniteFloat
from archery.protocol.text import shown

__all__ = ["THETA_BOX", "THETA_SIZE", "Theta", "ThetaBox"]

THETA_SIZE = 3  # components of θ: x, y, z (m)

#: θ on the wire: 3 finite floats, m, checked as they are decoded (where θ enters a process),
#: not as a struct holding them is built (where θ leaves one).
Theta = Annotated[
    list[FiniteFloat],
    Meta(min_length=THETA_SIZE, max_length=THETA_SIZE, description="θ, string − bow hand, m"),
]


class ThetaBox(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """A box of θ (m): `low` and `high`, 3 finite numbers each, low < high on every axis.

    Built from any 3 numbers per side (a list, a tuple, a numpy array); they are kept as a list
    of floats, so equal boxes compare equal and a box encodes as `{"low": [...], "high": [...]}`.

    Raises:
        ValueError: a side is not 3 finite numbers, or low >= high on some axis (the message
            names the box); decoding turns it into a `msgspec.ValidationError` naming the field.
    """

    low: Theta
    high: Theta

    def __post_init__(self) -> None:
        sides = []
        for name in ("low", "high"):
            value = getattr(self, name)
            try:
                side = np.array(value, dtype=float)
            except (TypeError, ValueError, OverflowError):
                side = np.array([math.nan])
            if side.shape != (THETA_SIZE,) or not np.all(np.isfinite(side)):
                raise ValueError(
                    f"θ box {name} must be {THETA_SIZE} finite numbers (m), got {shown(value)}"
                )
            sides.append(side)
        low, high = sides
        if not np.all(low < high):
            raise ValueError(
                f"θ box low={low.tolist()}, high={high.tolist()} m must have low < high on "
                "every axis"
            )
        msgspec.structs.force_setattr(self, "low", low.tolist())
        msgspec.structs.force_setattr(self, "high", high.tolist())

    def contains(self, theta: Sequence[float] | np.ndarray) -> bool:
        """True if θ (m, 3 finite numbers) lies inside the box, its faces included."""
        th = np.asarray(theta, dtype=float)
        return bool(np.all(th >= self.low) and np.all(th <= self.high))

    def clip(self, theta: Sequence[float] | np.ndarray) -> np.ndarray:
        """θ (m) clipped into the box, a new float array."""
        result: np.ndarray = np.clip(np.asarray(theta, dtype=float), self.low, self.high)
        return result

    def outside(self, name: str, theta: Sequence[float] | np.ndarray) -> str:
        """The message for a θ outside the box: `name`, θ and the box (m)."""
        values = np.asarray(theta, dtype=float).tolist()
        return f"{name} {values} m lies outside the θ box low={self.low}, high={self.high} m"


#: The θ box of the archery posture (m, per axis: x 0.12..0.24, y −0.02..0.06, z −0.07..0.01;
#: ‖θ‖ 0.12..0.26 m, arrow within 38° of −x): the controller's posture
#: accepts these θ (its `status` tells the box), the learners search in it by default, and
#: `archery imitate` checks --theta against it. Verified reachable on a 9×9×9 grid from the
#: reference posture, relative position within the 0.1 mm IK tolerance (worst 0.03 mm);
#: tests/test_posture.py checks corners, centre, random points and a warm path.
THETA_BOX = ThetaBox(low=[0.12, -0.02, -0.07], high=[0.24, 0.06, 0.01])
