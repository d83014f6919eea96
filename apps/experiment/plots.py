"""Figures of the simulation experiment: convergence (the paper's Fig. 6) and arrows (Fig. 5)."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from types import ModuleType
from typing import TYPE_CHECKING

import numpy as np

from apps.experiment.censored import count_stats, format_count
from sim.ballistic import BallisticWorld
from sim.geometry import BOW_HAND, INNER_RING_RADIUS, TARGET_DIAMETER

if TYPE_CHECKING:
    from apps.experiment.config import AlgorithmRun

__all__ = ["BANDS", "plot_convergence", "plot_trajectories"]

# What Fig. 6 draws over sessions: "median" (the line) with the interquartile band, or "mean"
# with ± one standard deviation (the band's lower edge clipped at 0 cm: a distance is ≥ 0).
BANDS = ("median", "mean")

_COLOURS = ("tab:blue", "tab:orange", "tab:green", "tab:purple", "tab:brown", "tab:pink")


def _pyplot() -> ModuleType:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_convergence(
    runs: Mapping[str, AlgorithmRun],
    labels: Mapping[str, str],
    path: Path,
    *,
    title: str = "",
    change_at: int | None = None,
    band: str = "median",
) -> None:
    """The arrow's distance to the centre (cm) vs rollout over sessions (Fig. 6): the median
    with the interquartile band (`band` "median", the default), or the mean ± std ("mean").

    Each label gives the median rollouts to hit and the sessions that hit; a median that is a
    session which never hit reads "> budget". With `change_at` (1-based rollout where the world
    changed) the change is marked and each label also gives the median rollouts to hit again.

    Raises:
        ValueError: `band` is not one of BANDS.
    """
    if band not in BANDS:
        raise ValueError(f"band must be one of {', '.join(BANDS)}, got {band!r}")
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(9.5, 5.2 + 0.25 * (len(runs) + 2)), dpi=120)
    top = 0.0
    for i, (name, run) in enumerate(runs.items()):
        distance = 100.0 * run.distances  # cm
        budget = distance.shape[1]
        if band == "median":
            low, centre, high = np.percentile(distance, [25, 50, 75], axis=0)
        else:
            centre, std = distance.mean(axis=0), distance.std(axis=0)
            low, high = np.maximum(centre - std, 0.0), centre + std
        top = max(top, float(centre.max()))
        rollout = np.arange(1, budget + 1)
        colour = _COLOURS[i % len(_COLOURS)]
        to_hit = count_stats(run.rollouts_to_hit(), budget)
        hits = len(distance) - to_hit["censored_sessions"]
        label = (
            f"{labels[name]}: median {format_count(to_hit, 'median')} rollouts to hit, "
            f"{hits}/{len(distance)} hit"
        )
        if change_at is not None:
            rehit = count_stats(run.rollouts_to_rehit(change_at), budget - change_at + 1)
            label += f", {format_count(rehit, 'median')} to re-hit"
        ax.plot(rollout, centre, color=colour, lw=2, label=label)
        ax.fill_between(rollout, low, high, color=colour, alpha=0.15)
    ax.axhline(100 * INNER_RING_RADIUS, color="red", ls="--", lw=1, label="innermost ring (5 cm)")
    if change_at is not None:
        ax.axvline(
            change_at, color="black", ls=":", lw=1.5, label=f"wind changes (rollout {change_at})"
        )
    ax.set_xlabel("rollout")
    ax.set_ylabel("distance of the arrow to the target centre (cm)")
    ax.set_xlim(1, max(run.distances.shape[1] for run in runs.values()))
    # The bands of sessions that ran away can be metres wide: keep the central lines readable.
    ax.set_ylim(0, 1.25 * top)
    ax.grid(alpha=0.3)
    # Below the axes: a curve that stays high (uniform random search) never hides under it.
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.12), fontsize=9)
    what = "median and interquartile range" if band == "median" else "mean ± std (clipped at 0)"
    ax.set_title(f"Speed of convergence: {what} over sessions" + (f"\n{title}" if title else ""))
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def plot_trajectories(
    world: BallisticWorld,
    runs: Mapping[str, AlgorithmRun],
    labels: Mapping[str, str],
    path: Path,
    *,
    session: int = 0,
    title: str = "",
) -> None:
    """One session per algorithm (Fig. 5): its arrows up to the first hit, the last one in red.

    Top row: the flights seen from the side (height vs distance). Bottom row: where the arrows
    met the target face, numbered by rollout. `title` (the scenario) goes under the heading.
    """
    plt = _pyplot()
    names = list(runs)
    fig, axes = plt.subplots(
        2,
        len(names),
        figsize=(4.2 * len(names), 8.6),
        dpi=110,
        squeeze=False,
        gridspec_kw={"height_ratios": [1.0, 1.3]},
        layout="constrained",
    )
    for ax in axes[0, 1:]:
        ax.sharey(axes[0, 0])
    centre = world.centre
    radius = TARGET_DIAMETER / 2
    for column, name in enumerate(names):
        run = runs[name]
        last = int(min(run.rollouts_to_hit()[session], run.thetas.shape[1]))
        side, face = axes[0, column], axes[1, column]
        for k in range(last):
            path_k = world.trajectory(run.thetas[session, k])
            final = k == last - 1
            side.plot(
                -path_k[:, 0],
                path_k[:, 2],
                color="red" if final else "0.55",
                lw=2.2 if final else 0.8,
                alpha=1.0 if final else 0.7,
                zorder=3 if final else 2,
            )
        side.plot([-centre[0]] * 2, [centre[2] - radius, centre[2] + radius], color="k", lw=4)
        side.plot(-BOW_HAND[0], BOW_HAND[2], "o", color="k", ms=4)
        side.set_xlabel("distance ahead of the robot (m)")
        side.set_ylabel("height (m)")
        side.grid(alpha=0.3)
        hit = run.rollouts_to_hit()[session] <= run.thetas.shape[1]
        outcome = f"hit at rollout {last}" if hit else f"no hit in {last} rollouts"
        side.set_title(f"{labels[name]}\nsession {session}: {outcome}")

        for ring in (radius, 0.15, 0.10, INNER_RING_RADIUS):
            face.add_patch(plt.Circle((0, 0), 100 * ring, fill=False, color="0.3", lw=1))
        face.add_patch(plt.Circle((0, 0), 100 * INNER_RING_RADIUS, color="gold", alpha=0.5))
        r = 100 * run.r_true[session, :last]
        face.plot(r[:, 0], r[:, 1], "-", color="0.75", lw=0.8, zorder=1)
        face.scatter(r[:-1, 0], r[:-1, 1], s=28, color="0.45", zorder=2)
        face.scatter(r[-1, 0], r[-1, 1], s=60, color="red", zorder=3)
        for k, (x, y) in enumerate(r, start=1):
            if k <= 8 or k == last:
                face.annotate(str(k), (x, y), textcoords="offset points", xytext=(4, 4), fontsize=8)
        limit = max(100 * radius, float(np.abs(r).max()) + 5)
        face.set_xlim(-limit, limit)
        face.set_ylim(-limit, limit)
        face.set_aspect("equal")
        face.set_xlabel("right of centre (cm)")
        face.set_ylabel("above centre (cm)")
        face.set_title("impacts on the target, by rollout")
    heading = "Arrow trajectories of one learning session per algorithm (final one in red)"
    fig.suptitle(heading + (f"\n{title}" if title else ""))
    fig.savefig(path)
    plt.close(fig)
