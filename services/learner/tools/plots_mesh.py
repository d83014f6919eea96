"""Fig. 5 of a run on the robot: where one session's arrows met the target face, per algorithm
(the robot's ground truth; the flights themselves are not journaled)."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from sim.geometry import INNER_RING_RADIUS, TARGET_DIAMETER

if TYPE_CHECKING:
    from services.learner.tools.experiment import AlgorithmRun

__all__ = ["plot_impacts"]


def plot_impacts(
    runs: Mapping[str, AlgorithmRun],
    labels: Mapping[str, str],
    path: Path,
    *,
    session: int = 0,
    title: str = "",
) -> None:
    """One panel per algorithm: session `session`'s impacts (cm from the centre) up to its first
    hit, joined in rollout order and numbered, the last one in red, on the target's rings."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(runs)
    fig, axes = plt.subplots(
        1, len(names), figsize=(4.2 * len(names), 4.8), dpi=110, squeeze=False, layout="constrained"
    )
    face_cm = 100 * TARGET_DIAMETER / 2
    for ax, name in zip(axes[0], names, strict=True):
        run = runs[name]
        budget = run.thetas.shape[1]
        first_hit = int(run.rollouts_to_hit()[session])
        last = min(first_hit, budget)
        impacts = 100 * run.r_true[session, :last]
        for ring_cm in (face_cm, 15.0, 10.0):
            ax.add_patch(plt.Circle((0, 0), ring_cm, fill=False, color="0.3", lw=1))
        ax.add_patch(plt.Circle((0, 0), 100 * INNER_RING_RADIUS, color="gold", alpha=0.5))
        ax.plot(impacts[:, 0], impacts[:, 1], "-", color="0.75", lw=0.8, zorder=1)
        ax.scatter(impacts[:-1, 0], impacts[:-1, 1], s=24, color="0.45", zorder=2)
        ax.scatter(impacts[-1, 0], impacts[-1, 1], s=60, color="red", zorder=3)
        for k, (x, y) in enumerate(impacts, start=1):
            if k <= 8 or k == last:
                ax.annotate(str(k), (x, y), textcoords="offset points", xytext=(4, 4), fontsize=8)
        reach = max(face_cm, float(np.abs(impacts).max()) + 5)
        ax.set_xlim(-reach, reach)
        ax.set_ylim(-reach, reach)
        ax.set_aspect("equal")
        ax.set_xlabel("right of centre (cm)")
        ax.set_ylabel("above centre (cm)")
        outcome = f"hit at rollout {first_hit}" if first_hit <= budget else f"no hit in {budget}"
        ax.set_title(f"{labels[name]}\nsession {session}: {outcome}")
    heading = "Impacts on the target of one session per algorithm (final one in red)"
    fig.suptitle(heading + (f"\n{title}" if title else ""))
    fig.savefig(path)
    plt.close(fig)
