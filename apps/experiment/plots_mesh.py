"""Fig. 5 of a run on the robot: where one session's arrows met the target face, per algorithm
(the robot's ground truth; the flights themselves are not journaled)."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from archery.sim.geometry import INNER_RING_RADIUS, TARGET_DIAMETER

if TYPE_CHECKING:
    from archery.apps.experiment.config import AlgorithmRun

__all__ = ["impacts_figure", "plot_impacts"]


def plot_impacts(
    runs: Mapping[str, AlgorithmRun],
    labels: Mapping[str, str],
    path: Path,
    *,
    session: int = 0,
    title: str = "",
) -> None:
    """Fig. 5 of a run on the robot (`impacts_figure`) written to `path`."""
    fig = impacts_figure(runs, labels, session=session, title=title)  # selects Agg first
    import matplotlib.pyplot as plt

    fig.savefig(path)
    plt.close(fig)


def impacts_figure(
    runs: Mapping[str, AlgorithmRun],
    labels: Mapping[str, str],
    *,
    session: int = 0,
    title: str = "",
) -> Any:
    """One panel per algorithm: every impact of session `session` (cm from the centre) on the
    target's rings, coloured by rollout, its first hit ringed in red. The paper's learners
    (ARCHER, PoWER) share one scale; each baseline's panel is scaled to its own impacts."""
    import matplotlib

    from archery.apps.experiment.plots import split_baselines

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(runs)
    fig, axes = plt.subplots(
        1, len(names), figsize=(4.2 * len(names), 4.8), dpi=110, squeeze=False, layout="constrained"
    )
    face_cm = 100 * TARGET_DIAMETER / 2
    shown = None
    paper, _ = split_baselines(names)
    reaches: dict[str, float] = {}
    for ax, name in zip(axes[0], names, strict=True):
        run = runs[name]
        budget = run.thetas.shape[1]
        first_hit = int(run.rollouts_to_hit()[session])
        impacts = 100 * run.r_true[session]  # every rollout of the budget (cm)
        for ring_cm in (face_cm, 15.0, 10.0, 100 * INNER_RING_RADIUS):
            ax.add_patch(plt.Circle((0, 0), ring_cm, fill=False, color="0.35", lw=0.9))
        ax.add_patch(plt.Circle((0, 0), 100 * INNER_RING_RADIUS, color="gold", alpha=0.4))
        order = np.arange(1, budget + 1)
        shown = ax.scatter(*impacts.T, c=order, cmap="viridis", s=22, vmin=1, vmax=budget, zorder=2)
        if first_hit <= budget:
            ax.scatter(*impacts[first_hit - 1], s=150, facecolors="none", edgecolors="red", lw=1.6)
        ax.annotate("1", impacts[0], textcoords="offset points", xytext=(5, 5), fontsize=8)
        reaches[name] = max(face_cm, float(np.abs(impacts).max()) + 5)
        ax.set(aspect="equal")
        ax.set(xlabel="right of centre (cm)", ylabel="above centre (cm)")
        outcome = (
            f"first hit at rollout {first_hit} (red ring)" if first_hit <= budget else "no hit"
        )
        ax.set_title(f"{labels[name]}\nsession {session}: {outcome}")
    for ax, name in zip(axes[0], names, strict=True):
        reach = max(reaches[n] for n in (paper if name in paper else [name]))
        ax.set(xlim=(-reach, reach), ylim=(-reach, reach))
    if shown is not None:
        fig.colorbar(shown, ax=axes[0].tolist(), label="rollout", shrink=0.8)
    heading = "Impacts on the target of one session per algorithm"
    fig.suptitle(heading + (f"\n{title}" if title else ""))
    return fig
