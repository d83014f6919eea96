"""The bow model shared by the analytic world and the MuJoCo scene.

A linear-spring bow: the string hand pulls the string a draw length d beyond the bow's brace
height b (the string's rest distance from the bow hand). The stored energy ½·k·d² is given to the
arrow with efficiency η, so the launch speed is v = d·sqrt(η·k/m), with k the bow stiffness (N/m),
m the arrow mass (kg). The arrow leaves from the bow hand along the direction from the string hand
to the bow hand, i.e. along −θ for θ = p_string − p_bow.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from archery.protocol.direction import arrow_direction

__all__ = ["Bow", "BowError"]


class BowError(ValueError):
    """An invalid bow parameter or hand configuration."""


@dataclass(frozen=True)
class Bow:
    """A linear-spring bow.

    Attributes:
        stiffness: k, draw force per metre of draw (N/m).
        brace_height: b, string-to-bow-hand distance at rest (m).
        arrow_mass: m (kg).
        efficiency: η, fraction of the stored energy given to the arrow (0..1].
    """

    stiffness: float = 300.0
    brace_height: float = 0.08
    arrow_mass: float = 0.02
    efficiency: float = 0.8

    def __post_init__(self) -> None:
        for name in ("stiffness", "brace_height", "arrow_mass", "efficiency"):
            value = getattr(self, name)
            if not math.isfinite(value) or value <= 0:
                raise BowError(f"bow {name} must be a positive finite number, got {value!r}")
        if self.efficiency > 1:
            raise BowError(f"bow efficiency must be in (0, 1], got {self.efficiency!r}")

    def draw(self, theta: np.ndarray) -> float:
        """Draw length d = max(0, ‖θ‖ − b) in metres for θ = p_string − p_bow (m)."""
        return max(0.0, float(np.linalg.norm(theta)) - self.brace_height)

    def launch_speed(self, theta: np.ndarray) -> float:
        """Launch speed (m/s) for the hand offset θ (m): d·sqrt(η·k/m) with d = `draw(θ)`."""
        return self.speed_for_draw(self.draw(theta))

    def speed_for_draw(self, draw: float) -> float:
        """Launch speed (m/s) for a draw length d (m, ≥ 0: how far the string's nocking point
        was pulled from its rest): d·sqrt(η·k/m)."""
        if not math.isfinite(draw) or draw < 0:
            raise BowError(f"the draw length must be a finite number of metres >= 0, got {draw!r}")
        return draw * math.sqrt(self.efficiency * self.stiffness / self.arrow_mass)

    def launch_velocity(self, theta: np.ndarray) -> np.ndarray:
        """Launch velocity vector (m/s) along −θ/‖θ‖ (`protocol.direction.arrow_direction`), in
        θ's frame, for θ a finite 3-vector (m).

        Raises:
            NoArrowDirection: the hands coincide (‖θ‖ ≈ 0).
        """
        velocity: np.ndarray = arrow_direction(theta) * self.launch_speed(theta)
        return velocity
