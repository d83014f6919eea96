"""Joint angles that put points of the hands at wanted positions: a small damped least-squares
IK on the MuJoCo scene, for the scripted whole shot (`sim.shot_script`).

A target is a point fixed in a body (its offset in the body's frame, m) and its wanted position
(m, root frame) or the point of another body it must meet; soft targets (weight < 1) are
followed in the first half of the iterations, the hard ones alone in the second. The solver
moves only the given parts' joints, within the world's software limits, on a scratch copy of
the state; the world's own state is never touched.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import mujoco
import numpy as np

from archery.sim.errors import CommandError
from archery.sim.scene import ScenePhysics

__all__ = ["PointTarget", "reach"]


@dataclass(frozen=True)
class PointTarget:
    """The point at `offset` (m, in `body`'s frame) is wanted at `position` (m, root frame);
    a `weight` below 1 makes the wish soft: it is followed as far as the others allow, and
    not held to the tolerance. With `meet` (a body and an offset in its frame, m) the point is
    wanted where that point of the other body is, wherever the solution puts it (`position`
    is then not used)."""

    body: str
    offset: np.ndarray
    position: np.ndarray
    weight: float = 1.0
    meet: tuple[str, np.ndarray] | None = None


def reach(
    physics: ScenePhysics,
    targets: Sequence[PointTarget],
    parts: Sequence[str],
    start: Mapping[str, np.ndarray],
    limits: Mapping[str, tuple[np.ndarray, np.ndarray]],
    *,
    tolerance: float = 2e-3,
    iterations: int = 300,
    damping: float = 0.05,
    others: Mapping[str, np.ndarray] | None = None,
) -> dict[str, np.ndarray]:
    """Joint angles (rad, per part) that put every target's point at its position.

    Args:
        physics: the scene; its model is used on a scratch `MjData` copied from its state.
        targets: the points and where they are wanted.
        parts: the parts whose joints may move (the others stay as in the scene).
        start: the starting angles (rad) of those parts.
        limits: each part's (lower, upper) software limits (rad).
        tolerance: largest accepted position error of any target (m).
        iterations: most solver iterations.
        damping: the damped least-squares λ (m).
        others: angles (rad) of parts that do not move, where they differ from the scene's.

    Raises:
        CommandError: no solution within `tolerance`; the message gives the residual (m).
    """
    model = physics.model
    data = mujoco.MjData(model)
    data.qpos[:] = physics.data.qpos
    for part, angles in (others or {}).items():
        data.qpos[physics.qpos_indices(part)] = angles
    qadr = np.concatenate([physics.qpos_indices(p) for p in parts])
    dadr = np.concatenate([physics.dof_indices(p) for p in parts])
    lower = np.concatenate([limits[p][0] for p in parts])
    upper = np.concatenate([limits[p][1] for p in parts])
    q = np.clip(np.concatenate([np.asarray(start[p], dtype=float) for p in parts]), lower, upper)
    bodies = [model.body(t.body).id for t in targets]
    jac, jac_meet = np.empty((3, model.nv)), np.empty((3, model.nv))
    worst = np.inf
    for iteration in range(iterations):
        soft = 1.0 if iteration < iterations // 2 else 0.0  # then the hard wishes alone
        data.qpos[qadr] = q
        mujoco.mj_kinematics(model, data)
        mujoco.mj_comPos(model, data)
        errors, rows, hard = [], [], []
        for target, body in zip(targets, bodies, strict=True):
            point = data.xpos[body] + data.xmat[body].reshape(3, 3) @ np.asarray(target.offset)
            mujoco.mj_jac(model, data, jac, None, point, body)
            row = jac[:, dadr].copy()
            wanted = np.asarray(target.position)
            if target.meet is not None:
                other = model.body(target.meet[0]).id
                rot = data.xmat[other].reshape(3, 3)
                wanted = data.xpos[other] + rot @ np.asarray(target.meet[1])
                mujoco.mj_jac(model, data, jac_meet, None, wanted, other)
                row -= jac_meet[:, dadr]
            miss = wanted - point
            weight = target.weight
            if weight >= 1.0:
                hard.append(float(np.linalg.norm(miss)))
            else:
                weight *= soft
            errors.append(weight * miss)
            rows.append(weight * row)
        error = np.concatenate(errors)
        worst = max(hard, default=0.0)
        if worst <= tolerance:
            break
        j = np.vstack(rows)
        step = j.T @ np.linalg.solve(j @ j.T + damping**2 * np.eye(j.shape[0]), error)
        q = np.clip(q + step, lower, upper)
    if worst > tolerance:
        wishes = [
            f"{t.body} to {t.meet[0] if t.meet else np.round(t.position, 3).tolist()}"
            for t in targets
            if t.weight >= 1.0
        ]
        raise CommandError(
            f"cannot reach {', '.join(wishes)}: position error {worst:.4f} m exceeds {tolerance} m"
        )
    out: dict[str, np.ndarray] = {}
    start_index = 0
    for part in parts:
        n = physics.qpos_indices(part).size
        out[part] = q[start_index : start_index + n].copy()
        start_index += n
    return out
