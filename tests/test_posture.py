"""Tests of the archery posture: hand orientations from θ and the two-hand IK solve."""

from __future__ import annotations

import inspect
import itertools
import math

import msgspec
import numpy as np
import pinocchio as pin
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from archery.apps.experiment.config import ExperimentConfig
from archery.mesh.rpc_server import bad_args_message
from archery.protocol.direction import NoArrowDirection, arrow_direction
from archery.protocol.errors import ConfigError
from archery.protocol.theta import THETA_BOX, ThetaBox
from archery.protocol.verbs.controller import POSTURE, PostureArgs
from archery.services.controller.errors import JointError, TargetError
from archery.services.controller.ik_types import IkSettings
from archery.services.controller.posture import ArcheryPosture, PostureConfig, hand_orientations
from archery.services.learner.algorithms.base import Learner

UP = np.array([0.0, 0.0, 1.0])


@pytest.fixture(scope="module")
def posture() -> ArcheryPosture:
    return ArcheryPosture()


def box_thetas(config: PostureConfig, rng: np.random.Generator, n_random: int) -> list[np.ndarray]:
    low, high = np.array(config.theta_box.low), np.array(config.theta_box.high)
    corners = [np.array(c) for c in itertools.product(*zip(low, high, strict=True))]
    centre = [(low + high) / 2, config.nominal_theta]
    random = [rng.uniform(low, high) for _ in range(n_random)]
    return corners + centre + random


def check_posture(posture: ArcheryPosture, theta: np.ndarray, result) -> None:
    model = posture.model
    q = model.vector(result.q)
    assert np.all(q >= model.lower) and np.all(q <= model.upper)
    x_left, r_left = model.hand_pose(q, "left_arm")
    x_right, r_right = model.hand_pose(q, "right_arm")
    np.testing.assert_allclose(result.theta_achieved, x_right - x_left, atol=1e-12)
    np.testing.assert_allclose(result.bow_hand, x_left, atol=1e-12)
    assert result.relative_error_m == pytest.approx(np.linalg.norm(theta - (x_right - x_left)))
    assert result.relative_error_m <= 1e-3
    assert result.bow_hand_error_m <= 1e-3
    assert result.reachable
    np.testing.assert_allclose(
        result.arrow_direction, arrow_direction(x_right - x_left), atol=1e-12
    )
    want_left, want_right = hand_orientations(theta)
    angle_left = np.linalg.norm(pin.log3(want_left @ r_left.T))
    angle_right = np.linalg.norm(pin.log3(want_right @ r_right.T))
    assert result.left_orientation_error_rad == pytest.approx(angle_left, abs=1e-9)
    assert result.right_orientation_error_rad == pytest.approx(angle_right, abs=1e-9)


# ------------------------------------------------------------------------------ orientations


@settings(max_examples=100, deadline=None)
@given(
    theta=st.tuples(st.floats(0.05, 0.3), st.floats(-0.15, 0.15), st.floats(-0.15, 0.15)).map(
        np.array
    )
)
def test_hand_orientations_follow_the_paper(theta: np.ndarray) -> None:
    left, right = hand_orientations(theta)
    a = arrow_direction(theta)
    np.testing.assert_allclose(a, -theta / np.linalg.norm(theta))
    for rot in (left, right):
        np.testing.assert_allclose(rot.T @ rot, np.eye(3), atol=1e-12)
        assert np.linalg.det(rot) == pytest.approx(1.0)
    # Left palm perpendicular to the arrow, facing the target (palm normal is −z of the frame).
    np.testing.assert_allclose(-left[:, 2], a, atol=1e-12)
    # Right fingers (+x) along the arrow.
    np.testing.assert_allclose(right[:, 0], a, atol=1e-12)
    # Bow vertical, zero roll: the grip axis (y) lies in the vertical plane through the arrow,
    # perpendicular to it, thumbs (−y) up; both hands share it.
    for rot in (left, right):
        y = rot[:, 1]
        assert y @ a == pytest.approx(0.0, abs=1e-12)
        assert y @ np.cross(a, UP) == pytest.approx(0.0, abs=1e-12)
        assert -y @ UP > 0


def test_coinciding_hands_never_reach_the_orientations(posture: ArcheryPosture) -> None:
    """θ = 0 has no arrow direction: the box refuses it where θ enters, and a box whose θ
    could come near it is refused when the posture is configured."""
    with pytest.raises(TargetError, match="outside the configured box"):
        posture.solve(np.zeros(3))
    with pytest.raises(ConfigError, match="low x must be > 0"):
        PostureConfig(theta_box=ThetaBox(low=(0.0, -0.01, -0.01), high=(0.1, 0.01, 0.01)))
    with pytest.raises(NoArrowDirection, match="string hand on the bow hand"):
        arrow_direction(np.zeros(3))  # the launch's, which measures θ


def test_a_posture_box_keeps_every_arrow_off_vertical() -> None:
    """A vertical arrow leaves "bow vertical" without meaning: the posture's box is checked
    once, when the controller is configured, so a θ inside it is never checked for it again."""
    tall = ThetaBox(low=(0.001, -0.01, -0.2), high=(0.1, 0.01, 0.2))
    with pytest.raises(ConfigError, match="within 1° of vertical"):
        PostureConfig(theta_box=tall, nominal_theta=(0.05, 0.0, 0.0))
    for corner in itertools.product(*zip(THETA_BOX.low, THETA_BOX.high, strict=True)):
        a = arrow_direction(np.array(corner))
        assert abs(a @ UP) < math.cos(math.radians(50))  # the box's arrows: within 40° of level


def test_a_malformed_theta_is_refused_where_the_request_is_decoded() -> None:
    """θ's size and finiteness are the contract's (`PostureArgs`), checked once on decoding:
    the posture core takes the decoded θ as it is."""
    for theta, why in (
        ([0.17, math.nan, -0.03], "finite"),
        ([0.17, math.inf, -0.03], "finite"),
        ([0.17, 0.03], "length"),
        ([0.17, 0.03, -0.03, 0.0], "length"),
    ):
        with pytest.raises(msgspec.ValidationError) as info:
            msgspec.convert({"theta": theta}, PostureArgs)
        assert why in bad_args_message(POSTURE, info.value)
    assert msgspec.convert({"theta": [0.17, 0.03, -0.03]}, PostureArgs).theta == [0.17, 0.03, -0.03]


def test_the_theta_box_is_defined_once() -> None:
    """The posture's default box is the contract's θ box (`protocol.theta.THETA_BOX`), and so
    is the learners' and the analytic experiment's default."""
    learner_box = inspect.signature(Learner.__init__).parameters["bounds"].default
    for box in (PostureConfig().theta_box, learner_box, ExperimentConfig().bounds):
        assert box is THETA_BOX


# ------------------------------------------------------------------------------------- posture


def test_reference_posture_reaches_the_nominal_bow_hand(posture: ArcheryPosture) -> None:
    model = posture.model
    x_left, _ = model.hand_pose(posture.reference, "left_arm")
    x_right, _ = model.hand_pose(posture.reference, "right_arm")
    np.testing.assert_allclose(x_left, posture.config.bow_hand, atol=1e-4)
    np.testing.assert_allclose(x_right - x_left, posture.config.nominal_theta, atol=1e-4)


def test_relative_position_is_met_over_the_theta_box(posture: ArcheryPosture) -> None:
    """Corners, centre and random points of the configured θ box, each solved from the
    reference posture, meet the relative position to 1 mm (in fact to micrometres)."""
    for theta in box_thetas(posture.config, np.random.default_rng(0), n_random=12):
        check_posture(posture, theta, posture.solve(theta))


def test_warm_started_path_through_the_box(posture: ArcheryPosture) -> None:
    """A learner's sequence of θ, each solve starting from the previous posture."""
    config = posture.config
    rng = np.random.default_rng(1)
    theta = config.nominal_theta.copy()
    q = None
    for _ in range(25):
        theta = config.theta_box.clip(theta + rng.normal(0.0, 0.005, 3))
        result = posture.solve(theta, q0=q)
        check_posture(posture, theta, result)
        if q is not None:  # small θ steps give small joint motions
            moved = posture.model.vector(result.q) - posture.model.vector(q)
            assert np.max(np.abs(moved)) < 0.5
        q = result.q


def test_theta_outside_the_box_is_rejected(posture: ArcheryPosture) -> None:
    config = posture.config
    for axis in range(3):
        low = config.nominal_theta.copy()
        low[axis] = config.theta_box.low[axis] - 1e-3
        with pytest.raises(TargetError, match="outside the configured box"):
            posture.solve(low)
        high = config.nominal_theta.copy()
        high[axis] = config.theta_box.high[axis] + 1e-3
        with pytest.raises(TargetError, match="outside the configured box"):
            posture.solve(high)
    with pytest.raises(JointError, match="unknown joint"):
        posture.solve(config.nominal_theta, q0={"neck_yaw": 0.0})


def test_locked_torso_keeps_the_start_torso(posture: ArcheryPosture) -> None:
    locked = ArcheryPosture(PostureConfig(use_torso=False, reference_starts=8))
    torso = ("torso_yaw", "torso_roll", "torso_pitch")
    theta = np.array([0.18, 0.02, -0.04])
    start = dict(posture.model.mapping(locked.reference)) | {"torso_yaw": 0.1}
    result = locked.solve(theta, q0=start)
    assert all(result.q[j] == start[j] for j in torso)
    check_posture(locked, theta, result)


def test_unreachable_bow_hand_is_a_config_error() -> None:
    fast = IkSettings(restarts=0, max_iterations=20)
    with pytest.raises(ConfigError, match="bow hand"):
        ArcheryPosture(PostureConfig(bow_hand=(-1.0, 0.0, 0.1), reference_starts=2, ik=fast))


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"theta_box": ((0.1, 0.0, 0.0), (0.2, 0.1, 0.1))}, "must be a ThetaBox"),
        (
            {"theta_box": ThetaBox(low=(-0.1, -0.1, -0.1), high=(0.2, 0.1, 0.1))},
            "low x must be > 0",
        ),
        ({"nominal_theta": (0.3, 0.0, 0.0)}, "nominal_theta"),
        ({"bow_hand": (0.0, np.nan, 0.0)}, "bow_hand"),
        ({"bow_hand": (0.0, 0.0)}, "bow_hand"),
        ({"reference_starts": 0}, "reference_starts"),
    ],
)
def test_config_validation(kwargs: dict, match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        PostureConfig(**kwargs)
