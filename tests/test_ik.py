"""Tests of the controller's kinematic model, its QP and the Eq. 9 inverse-kinematics solver."""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from archery.protocol.errors import ArcheryError, BadRequest, ConfigError
from archery.protocol.parts import PARTS
from archery.protocol.robotspec import HOME_POSTURE
from archery.services.controller.errors import ControllerError, JointError, TargetError
from archery.services.controller.ik import IkSolver
from archery.services.controller.ik_derivatives import (
    orientation_residual,
    orientation_residual_jacobian,
    position_hessian_contraction,
)
from archery.services.controller.ik_types import (
    IkSettings,
    OrientationTarget,
    PositionTarget,
    as_rotation,
)
from archery.services.controller.model import JOINT_NAMES, ArmsModel, load_arms_model
from archery.services.controller.qp import solve_box_qp

ARMS = ("left_arm", "right_arm")


@pytest.fixture(scope="module")
def model() -> ArmsModel:
    return load_arms_model()


@pytest.fixture(scope="module")
def solver(model: ArmsModel) -> IkSolver:
    return IkSolver(model)


def random_posture(model: ArmsModel, rng: np.random.Generator) -> np.ndarray:
    return rng.uniform(model.lower, model.upper)


def _hand_jacobian(model: ArmsModel, q: np.ndarray, arm: str) -> np.ndarray:
    """6×17 Jacobian of `arm`'s hand frame as the IK takes it from Pinocchio: rows (ẋ m/s,
    ω rad/s) in root axes (LOCAL_WORLD_ALIGNED), columns in `JOINT_NAMES` order (rad/s)."""
    jac = pin.computeFrameJacobian(
        model.model,
        model.data,
        model.to_pinocchio(model.vector(q)),
        model.frame_ids[arm],
        pin.ReferenceFrame.LOCAL_WORLD_ALIGNED,
    )
    return jac[:, model.pin_index].copy()


def in_limits(model: ArmsModel, q: np.ndarray) -> bool:
    return bool(np.all(q >= model.lower) and np.all(q <= model.upper))


# ----------------------------------------------------------------------------------- the model


def test_model_joints_follow_protocol_order_and_urdf_limits(model: ArmsModel) -> None:
    assert model.joint_names == PARTS["torso"] + PARTS["left_arm"] + PARTS["right_arm"]
    assert model.nq == 17 == model.model.nq
    full = pin.buildModelFromUrdf(model.urdf_path)
    for i, name in enumerate(model.joint_names):
        jid = full.getJointId(name)
        idx = full.joints[jid].idx_q
        assert model.lower[i] == full.lowerPositionLimit[idx]
        assert model.upper[i] == full.upperPositionLimit[idx]
    assert np.all(model.lower < model.upper)
    assert in_limits(model, model.vector(HOME_POSTURE))


def test_model_vector_mapping_round_trip_and_errors(model: ArmsModel) -> None:
    q = random_posture(model, np.random.default_rng(0))
    assert np.array_equal(model.vector(model.mapping(q)), q)
    partial = model.vector({"l_elbow": 1.0})
    assert partial[model.index("l_elbow")] == 1.0
    assert partial[model.index("r_elbow")] == HOME_POSTURE["r_elbow"]
    with pytest.raises(JointError, match="l_knee"):
        model.vector({"l_knee": 0.0})
    with pytest.raises(JointError, match="NaN"):
        model.vector({"l_elbow": float("nan")})
    with pytest.raises(JointError, match=r"shape \(17,\)"):
        model.vector(np.zeros(7))
    with pytest.raises(JointError, match="left_arm"):
        model.chain("left_leg")


def test_hand_frames_face_forward_at_home(model: ArmsModel) -> None:
    """At the home posture both hands are in front of the hips, left hand on the left (−y)."""
    x_left, _ = model.hand_pose(HOME_POSTURE, "left_arm")
    x_right, _ = model.hand_pose(HOME_POSTURE, "right_arm")
    assert x_left[1] < 0 < x_right[1]
    assert x_left[0] < 0 and x_right[0] < 0  # forward is −x
    np.testing.assert_allclose(x_left * [1, -1, 1], x_right, atol=0.01)  # mirror images


# ------------------------------------------------------------------ Jacobians vs finite differences


@pytest.mark.parametrize("arm", ARMS)
def test_hand_jacobian_matches_finite_differences(model: ArmsModel, arm: str) -> None:
    rng = np.random.default_rng(1)
    h = 1e-6
    for _ in range(5):
        q = random_posture(model, rng)
        jac = _hand_jacobian(model, q, arm)
        _, r0 = model.hand_pose(q, arm)
        numeric = np.zeros((6, model.nq))
        for i in range(model.nq):
            dq = np.zeros(model.nq)
            dq[i] = h
            xp, rp = model.hand_pose(q + dq, arm)
            xm, rm = model.hand_pose(q - dq, arm)
            numeric[:3, i] = (xp - xm) / (2 * h)
            numeric[3:, i] = (pin.log3(rp @ r0.T) - pin.log3(rm @ r0.T)) / (2 * h)
        np.testing.assert_allclose(jac, numeric, atol=1e-7)


@pytest.mark.parametrize("arm", ARMS)
def test_orientation_residual_jacobian_matches_finite_differences(
    model: ArmsModel, arm: str
) -> None:
    rng = np.random.default_rng(2)
    h = 1e-6
    for _ in range(5):
        q = random_posture(model, rng)
        target = pin.exp3(rng.normal(size=3) * 0.8)
        _, rot = model.hand_pose(q, arm)
        analytic = orientation_residual_jacobian(target, rot, _hand_jacobian(model, q, arm)[3:])
        numeric = np.zeros((3, model.nq))
        for i in range(model.nq):
            dq = np.zeros(model.nq)
            dq[i] = h
            _, rp = model.hand_pose(q + dq, arm)
            _, rm = model.hand_pose(q - dq, arm)
            diff = orientation_residual(target, rp) - orientation_residual(target, rm)
            numeric[:, i] = diff / (2 * h)
        np.testing.assert_allclose(analytic, numeric, atol=1e-6)


@pytest.mark.parametrize("arm", ARMS)
def test_position_hessian_contraction_matches_finite_differences(
    model: ArmsModel, arm: str
) -> None:
    """The constraint curvature used in the SQP Hessian is w·∂²x/∂q² (Pinocchio column order)."""
    rng = np.random.default_rng(3)
    h = 1e-6
    order = np.argsort(model.pin_index)  # Pinocchio column k is JOINT_NAMES[order[k]]

    def weighted_gradient(q_pin: np.ndarray, w: np.ndarray) -> np.ndarray:
        jac = _hand_jacobian(model, model.from_pinocchio(q_pin), arm)[:, order]
        return w @ jac[:3]

    for _ in range(3):
        q_pin = model.to_pinocchio(random_posture(model, rng))
        w = rng.normal(size=3)
        jac = _hand_jacobian(model, model.from_pinocchio(q_pin), arm)[:, order]
        analytic = position_hessian_contraction(w, jac)
        numeric = np.zeros((model.nq, model.nq))
        for i in range(model.nq):
            dq = np.zeros(model.nq)
            dq[i] = h
            numeric[i] = (weighted_gradient(q_pin + dq, w) - weighted_gradient(q_pin - dq, w)) / (
                2 * h
            )
        np.testing.assert_allclose(analytic, numeric, atol=1e-7)
        np.testing.assert_allclose(analytic, analytic.T)


# ---------------------------------------------------------------------------------------- the QP


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(2, 12), m=st.integers(0, 3))
def test_box_qp_meets_kkt_conditions(seed: int, n: int, m: int) -> None:
    rng = np.random.default_rng(seed)
    a = rng.normal(size=(n + 2, n))
    hessian = a.T @ a + 0.1 * np.eye(n)
    gradient = rng.normal(size=n) * 3
    eq_matrix = rng.normal(size=(m, n))
    eq_rhs = rng.normal(size=m)
    slack = np.full(m, 1e-3)
    lower = -rng.uniform(0, 1, size=n)
    upper = rng.uniform(0, 1, size=n)
    hint = rng.random(n) < 0.2
    lower[hint & (rng.random(n) < 0.5)] = 0.0
    upper[hint & (lower < 0)] = 0.0
    x, nu = solve_box_qp(hessian, gradient, eq_matrix, eq_rhs, slack, lower, upper, hint)
    assert np.all(x >= lower) and np.all(x <= upper)
    np.testing.assert_allclose(nu, (eq_matrix @ x - eq_rhs) / slack, rtol=1e-6, atol=1e-6)
    # Gradient of ½xᵀHx − gᵀx + ½‖Cx − c‖²/s: zero on free variables, pointing out of the box
    # (non-negative at a lower bound, non-positive at an upper bound) on bound ones.
    grad = hessian @ x - gradient + eq_matrix.T @ nu
    at_lower = np.isclose(x, lower, atol=1e-12)
    at_upper = np.isclose(x, upper, atol=1e-12)
    free = ~at_lower & ~at_upper
    scale = 1.0 + np.abs(gradient).max() + np.abs(nu).max(initial=0.0)
    assert np.all(np.abs(grad[free]) <= 1e-8 * scale)
    assert np.all(grad[at_lower & ~at_upper] >= -1e-8 * scale)
    assert np.all(grad[at_upper & ~at_lower] <= 1e-8 * scale)


# ------------------------------------------------------------------------------------ the solver


@pytest.mark.parametrize("arm", ARMS)
@pytest.mark.parametrize("use_torso", [True, False])
def test_solves_random_reachable_targets_to_a_millimetre(
    model: ArmsModel, solver: IkSolver, arm: str, use_torso: bool
) -> None:
    rng = np.random.default_rng(10 + use_torso)
    for _ in range(15):
        q_true = random_posture(model, rng)
        x, rot = model.hand_pose(q_true, arm)
        q0 = model.clip(q_true + rng.normal(0, 0.1, model.nq))
        if not use_torso:  # the torso is locked, so the target must be reachable with q0's torso
            q_true[:3] = q0[:3]
            x, rot = model.hand_pose(q_true, arm)
        res = solver.solve(arm, x, rot, q0=q0, use_torso=use_torso)
        q = model.vector(res.q)
        assert res.reachable
        assert res.position_error_m <= 1e-3
        x_reached, rot_reached = model.hand_pose(q, arm)
        np.testing.assert_allclose(res.x, x_reached)
        assert np.linalg.norm(x_reached - x) == pytest.approx(res.position_error_m)
        np.testing.assert_allclose(pin.exp3(res.orientation), rot_reached, atol=1e-9)
        assert in_limits(model, q)
        other = "right_arm" if arm == "left_arm" else "left_arm"
        moved = [model.index(j) for j in model.chain(arm, use_torso=use_torso)]
        still = [i for i in range(model.nq) if i not in moved]
        np.testing.assert_array_equal(q[still], q0[still])
        assert set(model.chain(other, use_torso=False)).isdisjoint(
            model.joint_names[i] for i in moved
        )


@pytest.mark.parametrize("arm", ARMS)
def test_orientation_cost_decreases_to_the_target_orientation(model: ArmsModel, arm: str) -> None:
    """Without a rest posture the target orientation is exactly reachable (it was generated by
    forward kinematics), so the orientation error falls from the warm start's to ~0."""
    exact = IkSolver(model, IkSettings(rest_weight=0.0))
    rng = np.random.default_rng(20)
    for _ in range(15):
        q_true = random_posture(model, rng)
        x, rot = model.hand_pose(q_true, arm)
        q0 = model.clip(q_true + rng.normal(0, 0.1, model.nq))
        _, rot0 = model.hand_pose(q0, arm)
        start_error = np.linalg.norm(orientation_residual(rot, rot0))
        res = exact.solve(arm, x, rot, q0=q0)
        assert res.reachable
        assert res.orientation_error_rad < start_error
        assert res.orientation_error_rad < 1e-3


def test_rest_posture_term_pulls_towards_rest(model: ArmsModel, solver: IkSolver) -> None:
    """Position only: the redundancy goes to the rest posture, so the result is nearer to it
    than the warm start is (Eq. 9 with w1 = 0)."""
    rng = np.random.default_rng(21)
    rest = model.vector(HOME_POSTURE)
    chain = [model.index(j) for j in model.chain("left_arm")]
    for _ in range(10):
        q_true = random_posture(model, rng)
        x, _ = model.hand_pose(q_true, "left_arm")
        res = solver.solve("left_arm", x, q0=q_true, rest=rest)
        q = model.vector(res.q)
        assert res.reachable
        assert res.orientation_error_rad == 0.0
        assert np.linalg.norm((q - rest)[chain]) <= np.linalg.norm((q_true - rest)[chain]) + 1e-9


@pytest.mark.parametrize("arm", ARMS)
def test_unreachable_target_gives_closest_pose_and_flag(model: ArmsModel, arm: str) -> None:
    solver = IkSolver(model, IkSettings(restarts=2))
    rng = np.random.default_rng(30)
    # Hand positions over many random postures: the result must be at least as close as any.
    samples = np.array([model.hand_pose(random_posture(model, rng), arm)[0] for _ in range(3000)])
    for target in ([-1.0, 0.0, 0.2], [0.0, 0.0, 1.2], [0.5, 0.6, -0.5]):
        res = solver.solve(arm, target)
        q = model.vector(res.q)
        assert not res.reachable
        assert in_limits(model, q)
        x, _ = model.hand_pose(q, arm)
        distance = float(np.linalg.norm(x - target))
        assert res.position_error_m == pytest.approx(distance)
        assert distance <= np.linalg.norm(samples - target, axis=1).min() + 1e-3


@settings(max_examples=40, deadline=None)
@given(
    target=st.tuples(*[st.floats(-1.5, 1.5)] * 3),
    seed=st.integers(0, 2**16),
    arm=st.sampled_from(ARMS),
)
def test_joint_limits_are_never_violated(
    target: tuple[float, float, float], seed: int, arm: str
) -> None:
    model = load_arms_model()
    solver = IkSolver(model, IkSettings(restarts=0, max_iterations=30))
    rng = np.random.default_rng(seed)
    q0 = rng.uniform(model.lower - 0.5, model.upper + 0.5)  # even from outside the limits
    res = solver.solve(arm, target, pin.exp3(rng.normal(size=3)), q0=q0)
    assert in_limits(model, model.vector(res.q))
    assert res.reachable == (res.position_error_m < solver.settings.position_tolerance)


def test_bad_inputs_raise_clear_errors(solver: IkSolver) -> None:
    ok = [-0.25, -0.1, 0.05]
    with pytest.raises(TargetError, match="finite"):
        solver.solve("left_arm", [np.nan, 0.0, 0.0])
    with pytest.raises(TargetError, match="3-vector"):
        solver.solve("left_arm", [0.1, 0.2])
    with pytest.raises(TargetError, match="3-vector"):
        solver.solve("left_arm", "here")
    with pytest.raises(TargetError, match="rotation"):
        solver.solve("left_arm", ok, np.ones((3, 3)))
    with pytest.raises(TargetError, match="shape"):
        solver.solve("left_arm", ok, np.zeros(4))
    with pytest.raises(TargetError, match="finite"):
        solver.solve("left_arm", ok, [0.0, np.inf, 0.0])
    with pytest.raises(JointError, match="valid arms"):
        solver.solve("left_leg", ok)
    with pytest.raises(JointError, match="r_elbow"):
        solver.solve("left_arm", ok, q0={"r_elbow": np.nan})
    with pytest.raises(JointError, match="unknown joint"):
        solver.solve("left_arm", ok, rest={"neck_pitch": 0.0})
    with pytest.raises(TargetError, match="PositionTarget"):
        solver.solve_targets((), joints=JOINT_NAMES)
    with pytest.raises(TargetError, match="other arm"):
        PositionTarget("left_arm", ok, relative_to="left_arm")
    with pytest.raises(ConfigError, match="priority"):
        PositionTarget("left_arm", ok, priority=5)
    with pytest.raises(ConfigError, match="weight"):
        OrientationTarget("left_arm", [0.0, 0.0, 0.0], weight=-1.0)
    for error in (TargetError, JointError):
        assert issubclass(error, ControllerError) and issubclass(error, ValueError)
        assert issubclass(error, ArcheryError) and error.code
    assert issubclass(ConfigError, ArcheryError) and issubclass(ConfigError, ValueError)
    assert issubclass(TargetError, BadRequest) and issubclass(JointError, BadRequest)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"orientation_weight": -1.0}, "orientation_weight"),
        ({"rest_weight": float("nan")}, "rest_weight"),
        ({"position_tolerance": 0.0}, "position_tolerance"),
        ({"max_iterations": 0}, "max_iterations"),
        ({"restarts": -1}, "restarts"),
        ({"sigma_x": np.eye(2)}, "sigma_x"),
        ({"sigma_n": -np.eye(3)}, "sigma_n"),
        ({"sigma_n": [[1, 1, 0], [0, 1, 0], [0, 0, 1]]}, "symmetric"),
        ({"sigma_q": {"l_elbow": -2.0}}, "sigma_q"),
    ],
)
def test_settings_validation(kwargs: dict, match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        IkSettings(**kwargs)


def test_unknown_sigma_q_joint_is_rejected(model: ArmsModel) -> None:
    with pytest.raises(JointError, match="l_knee"):
        IkSolver(model, IkSettings(sigma_q={"l_knee": 1.0}))


def test_results_are_deterministic_and_read_only(model: ArmsModel, solver: IkSolver) -> None:
    x, rot = model.hand_pose(random_posture(model, np.random.default_rng(40)), "right_arm")
    first = solver.solve("right_arm", x, rot)
    second = IkSolver(model).solve("right_arm", x, rot)
    assert dict(first.q) == dict(second.q)
    assert first.iterations == second.iterations
    with pytest.raises(TypeError):
        first.q["r_elbow"] = 0.0  # type: ignore[index]  # read-only: the test writes on purpose
    with pytest.raises(ValueError):
        first.x[0] = 0.0
    np.testing.assert_array_equal(solver.hand_pose(first.q, "right_arm")[0], first.x)
    np.testing.assert_allclose(model.hand_pose(first.q, "right_arm")[0], first.x, atol=1e-15)
    axis_angle = solver.solve("right_arm", x, pin.log3(rot))
    assert dict(axis_angle.q) == pytest.approx(dict(first.q))
    np.testing.assert_allclose(as_rotation(pin.log3(rot)), rot, atol=1e-12)


def test_position_weighting_sigma_x_defines_the_constraint(model: ArmsModel) -> None:
    """With Σx = diag(1, 1, 0) the height is free: only x and y are constrained."""
    solver = IkSolver(model, IkSettings(sigma_x=np.diag([1.0, 1.0, 0.0])))
    x, _ = model.hand_pose(HOME_POSTURE, "left_arm")
    target = x + np.array([-0.02, 0.01, 0.5])  # far too high, but height does not count
    res = solver.solve("left_arm", target)
    assert res.reachable
    np.testing.assert_allclose(res.x[:2], target[:2], atol=1e-4)
    assert abs(res.x[2] - target[2]) > 0.1
