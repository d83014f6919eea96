"""Inverse kinematics of iCub's arms as in the paper's Eq. 9: hard position, soft orientation/rest.

For one hand (or several hands at once) `IkSolver` computes

    q* = argmin  w1·Σ_hands eₙ(q)ᵀ Σn eₙ(q)  +  w2·(q̂ − q)ᵀ Σq (q̂ − q)
         s.t.    (x̂ − x(q))ᵀ Σx (x̂ − x(q)) < ε    and    q_min ≤ q ≤ q_max,

where eₙ(q) = log(R̂ · R(q)ᵀ) is the axis-angle (rad, root axes) of the rotation still needed: the
well-defined form of the paper's n̂ − n(q), equal to it for small errors. The method, a small SQP,
is told at `IkSolver._run`; the settings, targets and results are in `services.controller.ik_types`,
the orientation and curvature derivatives in `services.controller.ik_derivatives`.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import pinocchio as pin
import scipy.linalg.lapack

from archery.protocol.vectors import finite_vector
from archery.services.controller.errors import JointError, TargetError
from archery.services.controller.ik_derivatives import (
    orientation_residual,
    orientation_residual_jacobian,
    position_hessian_contraction,
)
from archery.services.controller.ik_types import (
    FrameJacobian,
    IkResult,
    IkSettings,
    OrientationTarget,
    OrientationTask,
    PositionTarget,
    PositionTask,
    RestTask,
    TargetsResult,
)
from archery.services.controller.model import ArmsModel, JointValues, check_arm, load_arms_model
from archery.services.controller.qp import solve_box_qp

__all__ = ["IkSolver"]

_LWA = pin.ReferenceFrame.LOCAL_WORLD_ALIGNED
_potrf = scipy.linalg.lapack.dpotrf
# Regularisation of the position equality rows (m² per unit multiplier): a priority-0 row is a
# penalty of weight 1e8; each priority level makes it 1000 times stiffer.
_BASE_SLACK = 1e-8
_PRIORITY_FACTOR = 1e-3
# Exact-penalty merit f + ρ·Σ‖Sx·(x̂ − x)‖ with ρ = twice the largest multiplier of the step
# (exactness asks ρ > ‖ν‖), and at least this (cost units per metre).
_MERIT_PENALTY = 1.0
_MIN_DAMPING = 1e-9
_MAX_DAMPING = 1e6


def _sqrt_psd(mat: np.ndarray) -> np.ndarray:
    """S with SᵀS = mat for a symmetric positive semi-definite matrix."""
    vals, vecs = np.linalg.eigh(mat)
    result: np.ndarray = (vecs * np.sqrt(np.clip(vals, 0.0, None))).T
    return result


@dataclass
class _Eval:
    """Everything one iteration needs at a posture (vectors over the active joints)."""

    hessian: np.ndarray  # Gauss–Newton Hessian of the cost
    gradient: np.ndarray  # minus the cost gradient
    eq_matrix: np.ndarray  # Sx·J per position target, stacked
    eq_rhs: np.ndarray  # Sx·(x̂ − x) per position target, stacked
    jacobians: list[FrameJacobian]  # of every hand in a position task
    cost: float  # Eq. 9 cost (rad²)
    violation: float  # Σ ‖Sx·(x̂ − x)‖ over position targets (m)
    feasible: bool


@functools.lru_cache(maxsize=8)
def _identity(n: int) -> np.ndarray:
    """Read-only n×n identity."""
    eye = np.eye(n)
    eye.setflags(write=False)
    return eye


class IkSolver:
    """Eq. 9 solver for iCub's hands (torso + arm chains) on the Pinocchio model.

    Not thread-safe (one Pinocchio `Data` per solver): give each thread its own solver.
    """

    def __init__(self, model: ArmsModel | None = None, settings: IkSettings | None = None) -> None:
        self.model = load_arms_model() if model is None else model
        self.settings = IkSettings() if settings is None else settings
        self._pin = self.model.model
        self._data = self._pin.createData()
        margin = self.settings.limit_margin
        self._lower = self.model.to_pinocchio(self.model.lower + margin)
        self._upper = self.model.to_pinocchio(self.model.upper - margin)
        sigma_q = np.ones(self.model.nq)
        for joint, weight in self.settings.sigma_q.items():
            sigma_q[self.model.index(joint)] = weight
        self._rest_sqrt = np.sqrt(self.settings.rest_weight * self.model.to_pinocchio(sigma_q))
        self._sqrt_x = _sqrt_psd(self.settings.sigma_x)
        self._sqrt_n = math.sqrt(self.settings.orientation_weight) * _sqrt_psd(
            self.settings.sigma_n
        )
        self._epsilon = self.settings.position_tolerance**2

    # ----------------------------------------------------------------------------- public API

    def solve(
        self,
        arm: str,
        position: Any,
        orientation: Any = None,
        *,
        q0: JointValues | None = None,
        rest: JointValues | None = None,
        use_torso: bool = True,
    ) -> IkResult:
        """Solve Eq. 9 for one hand.

        Args:
            arm: "left_arm" or "right_arm".
            position: x̂, desired hand position (m, root frame), a 3-vector.
            orientation: n̂ as an axis-angle 3-vector (rad, root axes) or a 3×3 rotation; None
                drops the orientation term.
            q0: warm start {joint: rad} or 17-vector (the current posture); missing joints take
                the home posture; values are clipped into the joint limits (less `limit_margin`).
            rest: q̂, rest posture (same forms; default the home posture).
            use_torso: solve torso + arm (10 joints) when True, the arm alone (7) when False
                (iKin's setDOF); the torso then keeps its q0 value.

        Raises:
            TargetError: a malformed position or orientation. JointError: bad arm, names or
            angles in q0/rest.
        """
        pos_target = PositionTarget(arm, finite_vector("position", position, TargetError))
        ori_targets = () if orientation is None else (OrientationTarget(arm, orientation),)
        chain = self.model.chain(arm, use_torso=use_torso)
        res = self.solve_targets((pos_target,), ori_targets, joints=chain, q0=q0, rest=rest)
        x, rot = self.hand_pose(res.q_vector, arm)
        orientation_out = np.asarray(pin.log3(rot))
        x.setflags(write=False)
        orientation_out.setflags(write=False)
        return IkResult(
            q=res.q,
            x=x,
            orientation=orientation_out,
            position_error_m=res.position_errors_m[0],
            orientation_error_rad=res.orientation_errors_rad[0] if ori_targets else 0.0,
            reachable=res.reachable,
            iterations=res.iterations,
        )

    def solve_targets(
        self,
        positions: Sequence[PositionTarget],
        orientations: Sequence[OrientationTarget] = (),
        *,
        joints: Sequence[str],
        q0: JointValues | None = None,
        rest: JointValues | None = None,
    ) -> TargetsResult:
        """Solve Eq. 9 with several hands at once, moving only `joints` (names).

        Position targets are hard constraints (each with the tolerance of the settings),
        orientation targets and the rest posture are the cost. If the start posture leads
        nowhere feasible, seeded random restarts follow; an unreachable target returns the
        posture closest to it with `reachable=False`.

        Raises:
            TargetError: no position target. JointError: unknown joint names or bad q0/rest.
        """
        if not positions:
            raise TargetError("at least one PositionTarget is needed (the hard constraint)")
        if not joints:
            raise JointError(
                f"joints must name at least one of {', '.join(self.model.joint_names)}"
            )
        idx = sorted({int(self.model.pin_index[self.model.index(j)]) for j in joints})
        active = np.array(idx, dtype=np.intp)
        q_start = self.model.to_pinocchio(self.model.clip(self.model.vector(q0)))
        q_start = np.clip(q_start, self._lower, self._upper)  # the margin's narrower range
        q_rest = self.model.to_pinocchio(self.model.vector(rest))
        frames = self.model.frame_ids
        pos_tasks = [
            PositionTask(
                frame=frames[t.arm],
                reference=None if t.relative_to is None else frames[t.relative_to],
                target=np.asarray(t.position),
                slack=_BASE_SLACK * _PRIORITY_FACTOR**t.priority,
            )
            for t in positions
        ]
        ori_tasks = [
            OrientationTask(
                frame=frames[t.arm],
                target=np.asarray(t.orientation),
                sqrt_weight=math.sqrt(t.weight) * self._sqrt_n,
            )
            for t in orientations
        ]
        q, iterations, ev = self._run(q_start, active, pos_tasks, ori_tasks, q_rest)
        if not ev.feasible and self.settings.restarts:
            # Joint limits can trap the local solver: retry from random in-limit postures of the
            # moving joints (seeded, so the same call gives the same answer).
            rng = np.random.default_rng(self.settings.seed)
            for _ in range(self.settings.restarts):
                q_try = q_start.copy()
                q_try[active] = rng.uniform(self._lower[active], self._upper[active])
                q_r, it_r, ev_r = self._run(q_try, active, pos_tasks, ori_tasks, q_rest)
                iterations += it_r
                if ev_r.feasible or ev_r.violation < ev.violation:
                    q, ev = q_r, ev_r
                if ev.feasible:
                    break
        pos_errors, ori_errors = self._errors(q, pos_tasks, ori_tasks)
        q_vec = self.model.from_pinocchio(q)
        q_vec.setflags(write=False)
        return TargetsResult(
            q=self.model.mapping(q_vec),
            q_vector=q_vec,
            position_errors_m=pos_errors,
            orientation_errors_rad=ori_errors,
            cost=float(ev.cost),
            reachable=bool(ev.feasible),
            iterations=iterations,
        )

    def hand_pose(self, q: JointValues, arm: str) -> tuple[np.ndarray, np.ndarray]:
        """Position (m) and rotation of `arm`'s hand frame in `root_link` at posture q (rad),
        computed with this solver's own Pinocchio data."""
        check_arm(arm)
        pin.forwardKinematics(self._pin, self._data, self.model.to_pinocchio(self.model.vector(q)))
        placement = pin.updateFramePlacement(self._pin, self._data, self.model.frame_ids[arm])
        return placement.translation.copy(), placement.rotation.copy()

    # ------------------------------------------------------------------------------- internals

    def _errors(
        self, q: np.ndarray, pos_tasks: list[PositionTask], ori_tasks: list[OrientationTask]
    ) -> tuple[tuple[float, ...], tuple[float, ...]]:
        model, data = self._pin, self._data
        pin.forwardKinematics(model, data, q)
        pos = []
        for task in pos_tasks:
            x = pin.updateFramePlacement(model, data, task.frame).translation
            if task.reference is not None:
                x = x - pin.updateFramePlacement(model, data, task.reference).translation
            pos.append(float(np.linalg.norm(task.target - x)))
        ori = []
        for ori_task in ori_tasks:
            rot = pin.updateFramePlacement(model, data, ori_task.frame).rotation
            ori.append(float(np.linalg.norm(orientation_residual(ori_task.target, rot))))
        return tuple(pos), tuple(ori)

    def _evaluate(
        self,
        q: np.ndarray,
        active: np.ndarray,
        pos_tasks: list[PositionTask],
        ori_tasks: list[OrientationTask],
        rest: RestTask,
    ) -> _Eval:
        """Residuals, Jacobians and the Gauss–Newton model at q (over the active joints)."""
        model, data = self._pin, self._data
        pin.computeJointJacobians(model, data, q)
        sqrt_x = self._sqrt_x
        n = active.size
        eq_matrix = np.empty((3 * len(pos_tasks), n))
        eq_rhs = np.empty(3 * len(pos_tasks))
        jacobians = []
        violation = 0.0
        feasible = True
        for k, task in enumerate(pos_tasks):
            x = pin.updateFramePlacement(model, data, task.frame).translation
            jac = pin.getFrameJacobian(model, data, task.frame, _LWA)[:, active]
            jacobians.append(FrameJacobian(k, 1.0, jac))
            lin = jac[:3]
            if task.reference is not None:
                x = x - pin.updateFramePlacement(model, data, task.reference).translation
                jac_ref = pin.getFrameJacobian(model, data, task.reference, _LWA)[:, active]
                jacobians.append(FrameJacobian(k, -1.0, jac_ref))
                lin = lin - jac_ref[:3]
            err = sqrt_x @ (task.target - x)
            sq = float(err @ err)
            feasible = feasible and sq < self._epsilon
            violation += math.sqrt(sq)
            eq_matrix[3 * k : 3 * k + 3] = sqrt_x @ lin
            eq_rhs[3 * k : 3 * k + 3] = err
        # Rest posture: residual Sq·(q̂ − q − dq), linear in the step.
        r_rest = rest.sqrt_weight * (rest.target - q[active])
        hessian = rest.hessian.copy()
        gradient = rest.sqrt_weight * r_rest
        cost = float(r_rest @ r_rest)
        for ori_task in ori_tasks:
            rot = pin.updateFramePlacement(model, data, ori_task.frame).rotation
            res = ori_task.sqrt_weight @ orientation_residual(ori_task.target, rot)
            jw = pin.getFrameJacobian(model, data, ori_task.frame, _LWA)[3:, active]
            a = ori_task.sqrt_weight @ orientation_residual_jacobian(ori_task.target, rot, jw)
            hessian += a.T @ a
            gradient -= a.T @ res
            cost += float(res @ res)
        return _Eval(hessian, gradient, eq_matrix, eq_rhs, jacobians, cost, violation, feasible)

    def _lagrangian_hessian(self, ev: _Eval, nu: np.ndarray, damping: float) -> np.ndarray:
        """Gauss–Newton Hessian + ν·(constraint curvature) + damping, if positive definite."""
        base = ev.hessian + damping * _identity(ev.hessian.shape[0])
        if not nu.any():
            return base
        full = base.copy()
        for fj in ev.jacobians:
            weights = fj.sign * (self._sqrt_x.T @ nu[3 * fj.task : 3 * fj.task + 3])
            full += position_hessian_contraction(weights, fj.jacobian)
        _, info = _potrf(full, lower=1)
        return full if info == 0 else base

    def _run(
        self,
        q: np.ndarray,
        active: np.ndarray,
        pos_tasks: list[PositionTask],
        ori_tasks: list[OrientationTask],
        q_rest: np.ndarray,
    ) -> tuple[np.ndarray, int, _Eval]:
        """SQP iterations from q (Pinocchio order); returns (q, iterations, evaluation at q).

        Each iteration solves a box-constrained QP in the joint step (`qp.py`): the linearised
        position rows are (regularised) equalities, so the position has priority over
        orientation and rest posture; the Hessian is Gauss–Newton for the cost plus the
        constraint curvature ν·∂²x/∂q² (from the multipliers ν), which restores fast
        convergence along the constraint. Steps are globalised by a per-joint trust region and
        Levenberg–Marquardt damping driven by an exact-penalty merit, with a second-order
        correction against the Maratos effect. All derivatives are analytic (Pinocchio
        Jacobians). The hand is driven to x̂ itself, the centre of the ε-ball, rather than to
        its surface: the cost given up is about ‖ν‖·√ε (≈ 1e-5 here).
        """
        s = self.settings
        lower = self._lower[active]
        upper = self._upper[active]
        slack = np.repeat([t.slack for t in pos_tasks], 3)
        n_pos = len(pos_tasks)
        rest_sqrt = self._rest_sqrt[active]
        rest = RestTask(q_rest[active], rest_sqrt, np.diag(rest_sqrt * rest_sqrt))
        eye = _identity(active.size)
        zeros = np.zeros(active.size)
        ev = self._evaluate(q, active, pos_tasks, ori_tasks, rest)
        best_q, best_ev = q, ev
        nu = np.zeros(3 * n_pos)
        rho = _MERIT_PENALTY
        lam = s.damping
        radius = s.max_step
        iterations = 0
        while iterations < s.max_iterations:
            iterations += 1
            qa = q[active]
            lb = np.maximum(lower - qa, -radius)
            ub = np.minimum(upper - qa, radius)
            hessian = self._lagrangian_hessian(ev, nu, lam)
            at_limit = (lb >= 0.0) | (ub <= 0.0)
            dq, nu_step = solve_box_qp(
                hessian, ev.gradient, ev.eq_matrix, ev.eq_rhs, slack, lb, ub, at_limit
            )
            nu_sq = (nu_step * nu_step).reshape(n_pos, 3).sum(axis=1)
            rho = max(_MERIT_PENALTY, 2.0 * math.sqrt(float(nu_sq.max())))
            merit = ev.cost + rho * ev.violation
            # Decrease of the merit that the QP model predicts for this step.
            lin_res = ev.eq_rhs - ev.eq_matrix @ dq
            lin_violation = float(np.sqrt((lin_res * lin_res).reshape(n_pos, 3).sum(axis=1)).sum())
            predicted = float(ev.gradient @ dq - 0.5 * dq @ hessian @ dq) + rho * (
                ev.violation - lin_violation
            )
            q_new = q.copy()
            q_new[active] = np.minimum(np.maximum(qa + dq, lower), upper)
            ev_new = self._evaluate(q_new, active, pos_tasks, ori_tasks, rest)
            actual = merit - (ev_new.cost + rho * ev_new.violation)
            if actual < 0.25 * predicted and ev_new.violation > ev.violation:
                # Second-order correction: pull the trial point back onto the linearised
                # constraint with the least joint motion (cures the Maratos effect).
                corr, _ = solve_box_qp(
                    eye,
                    zeros,
                    ev.eq_matrix,
                    ev_new.eq_rhs,
                    slack,
                    lb - dq,
                    ub - dq,
                )
                q_soc = q.copy()
                q_soc[active] = np.minimum(np.maximum(qa + dq + corr, lower), upper)
                ev_soc = self._evaluate(q_soc, active, pos_tasks, ori_tasks, rest)
                actual_soc = merit - (ev_soc.cost + rho * ev_soc.violation)
                if actual_soc > actual:
                    q_new, ev_new, dq, actual = q_soc, ev_soc, dq + corr, actual_soc
            nu = nu_step
            ratio = actual / predicted if predicted > 0 else (1.0 if actual >= 0 else -1.0)
            step_size = float(np.abs(dq).max())
            if ratio < 0.25:
                lam *= 10.0
                radius = max(0.5 * step_size, 1e-6)
            elif ratio > 0.75:
                lam = max(lam * 0.1, _MIN_DAMPING)
                radius = min(max(radius, 2.0 * step_size), s.max_step)
            if actual < 0 or (actual == 0 and predicted > 0):
                if lam > _MAX_DAMPING:
                    break  # no descent left: a local minimum of the merit
                continue
            change = ev.cost - ev_new.cost
            q, ev = q_new, ev_new
            if ev.feasible or ev.violation < best_ev.violation:
                best_q, best_ev = q, ev
            small_step = step_size < s.step_tolerance
            if ev.feasible and (small_step or abs(change) < s.cost_tolerance):
                break
            if not ev.feasible and small_step and abs(change) < s.cost_tolerance:
                break  # stalled outside the constraint: the closest pose from here
        if ev.feasible:
            return q, iterations, ev
        return best_q, iterations, best_ev
