"""Tests of the one computation of the arrow's direction from θ (`protocol.direction`), used by
the controller's hand orientations, the bow and the MuJoCo arrow's launch."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from archery.protocol.direction import NoArrowDirection, arrow_direction
from archery.sim.arrow import launch_velocity
from archery.sim.ballistic import BallisticWorld, Scenario, ShotError
from archery.sim.bow import Bow

component = st.floats(-0.5, 0.5, allow_nan=False)


@settings(max_examples=50, deadline=None)
@given(st.tuples(component, component, component).filter(lambda t: np.linalg.norm(t) > 0.05))
def test_every_user_aims_along_minus_theta(theta_tuple: tuple[float, float, float]) -> None:
    theta = np.array(theta_tuple)
    a = arrow_direction(theta)
    assert np.linalg.norm(a) == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(a, -theta / np.linalg.norm(theta), atol=1e-15)
    bow = Bow()
    speed = bow.launch_speed(theta)
    np.testing.assert_allclose(bow.launch_velocity(theta), speed * a, atol=1e-12)
    np.testing.assert_allclose(launch_velocity(theta, bow), speed * a, atol=1e-12)


def test_coinciding_hands_raise_the_one_error_everywhere() -> None:
    zero = np.zeros(3)
    hand = np.array([-0.3, -0.1, 0.1])
    for call in (
        lambda: arrow_direction(zero),
        lambda: Bow().launch_velocity(zero),
        lambda: launch_velocity(hand - hand, Bow()),
    ):
        with pytest.raises(NoArrowDirection, match="string hand on the bow hand") as caught:
            call()
        assert caught.value.code == "bad_state"  # what the robot's release replied before
    # The analytic world still reports it as a θ it cannot shoot.
    with pytest.raises(ShotError, match="no arrow direction"):
        BallisticWorld(Scenario()).launch(np.zeros((1, 3)))
