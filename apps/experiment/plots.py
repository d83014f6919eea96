"""Figures of the simulation experiment: convergence (the paper's Fig. 6) and arrows (Fig. 5)."""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from pathlib import Path
from types import ModuleType
from typing import TYPE_CHECKING, Any

import numpy as np

from archery.apps.experiment.censored import count_stats, format_count
from archery.services.learner.algorithms.baselines import CmaEs, HillClimber, RandomSearch
from archery.services.learner.algorithms.registry import ALGORITHMS
from archery.services.learner.label_placement import Label, place_labels
from archery.sim.ballistic import BallisticWorld
from archery.sim.geometry import BOW_HAND, INNER_RING_RADIUS, TARGET_DIAMETER

if TYPE_CHECKING:
    from archery.apps.experiment.config import AlgorithmRun

__all__ = [
    "BANDS",
    "convergence_figure",
    "is_baseline",
    "plot_convergence",
    "plot_trajectories",
    "split_baselines",
    "trajectories_figure",
]

# What Fig. 6 draws over sessions: "median" (the line) with the interquartile band, or "mean"
# with ± one standard deviation (the band's lower edge clipped at 0 cm: a distance is ≥ 0).
BANDS = ("median", "mean")

_COLOURS = ("tab:blue", "tab:orange", "tab:green", "tab:purple", "tab:brown", "tab:pink")


def _pyplot() -> ModuleType:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def is_baseline(name: str) -> bool:
    """Whether algorithm `name` is one of the baselines (CMA-ES, the hill climber, random
    search) rather than a learner the paper compares (ARCHER, PoWER and their variants)."""
    algorithm = ALGORITHMS.get(name)
    return algorithm is not None and issubclass(algorithm.cls, (CmaEs, HillClimber, RandomSearch))


def split_baselines(names: Iterable[str]) -> tuple[list[str], list[str]]:
    """(the paper's learners, the baselines) among `names`, each in the order given."""
    names = list(names)
    return [n for n in names if not is_baseline(n)], [n for n in names if is_baseline(n)]


def plot_convergence(
    runs: Mapping[str, AlgorithmRun],
    labels: Mapping[str, str],
    path: Path,
    *,
    title: str = "",
    change_at: int | None = None,
    band: str = "median",
) -> None:
    """Fig. 6 (`convergence_figure`) written to `path`."""
    plt = _pyplot()
    fig = convergence_figure(runs, labels, title=title, change_at=change_at, band=band)
    fig.savefig(path)
    plt.close(fig)


def convergence_figure(
    runs: Mapping[str, AlgorithmRun],
    labels: Mapping[str, str],
    *,
    title: str = "",
    change_at: int | None = None,
    band: str = "median",
) -> Any:
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
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    paper, baselines = split_baselines(runs)
    groups = [g for g in (paper, baselines) if g]
    fig, axes = plt.subplots(
        len(groups),
        1,
        figsize=(9.5, 2.2 + 3.6 * len(groups) + 0.25 * (len(runs) + 2)),
        dpi=120,
        sharex=True,
        squeeze=False,
    )
    colour_of = {name: _COLOURS[i % len(_COLOURS)] for i, name in enumerate(runs)}
    budget = max(run.distances.shape[1] for run in runs.values())
    for ax, group in zip(axes[:, 0], groups, strict=True):
        log = group is baselines and bool(paper)
        tops, bottoms = [], []
        for name in group:
            run = runs[name]
            distance = 100.0 * run.distances  # cm
            n_rollouts = distance.shape[1]
            if band == "median":
                low, centre, high = np.percentile(distance, [25, 50, 75], axis=0)
            else:
                centre, std = distance.mean(axis=0), distance.std(axis=0)
                low, high = np.maximum(centre - std, 0.0), centre + std
            tops.append(float(centre.max()))
            bottoms.append(float(np.min(centre)))
            rollout = np.arange(1, n_rollouts + 1)
            to_hit = count_stats(run.rollouts_to_hit(), n_rollouts)
            hits = len(distance) - to_hit["censored_sessions"]
            label = (
                f"{labels[name]}: median {format_count(to_hit, 'median')} rollouts to hit, "
                f"{hits}/{len(distance)} hit"
            )
            if change_at is not None:
                rehit = count_stats(run.rollouts_to_rehit(change_at), n_rollouts - change_at + 1)
                label += f", {format_count(rehit, 'median')} to re-hit"
            ax.plot(rollout, centre, color=colour_of[name], lw=2, label=label)
            ax.fill_between(rollout, low, high, color=colour_of[name], alpha=0.15)
        ax.axhline(
            100 * INNER_RING_RADIUS, color="red", ls="--", lw=1, label="innermost ring (5 cm)"
        )
        if change_at is not None:
            ax.axvline(
                change_at,
                color="black",
                ls=":",
                lw=1.5,
                label=f"wind changes (rollout {change_at})",
            )
        # The bands of sessions that ran away can be metres wide: keep the central lines readable.
        top = max(1.25 * max(tops), 1.5 * 100 * INNER_RING_RADIUS)
        if log:  # the baselines span 5 cm to a metre: a log axis keeps each readable
            ax.set_yscale("log")
            ax.set_ylim(max(0.5 * min(bottoms), 0.5), 1.6 * max(tops))
            ax.yaxis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
            ax.yaxis.set_major_formatter(FuncFormatter(lambda value, _: f"{value:g}"))
            ax.yaxis.set_minor_formatter(NullFormatter())  # the 1-2-5 majors are labels enough
        else:
            ax.set_ylim(0, top)
        ax.set_ylabel("distance to the centre (cm)")
        ax.grid(alpha=0.3, which="both" if log else "major")
        if len(groups) > 1:
            ax.set_title(
                "the paper's learners" if group is paper else "baselines (log scale)", fontsize=10
            )
    axes[-1, 0].set_xlabel("rollout")
    axes[-1, 0].set_xlim(1, budget)
    what = "median and interquartile range" if band == "median" else "mean ± std (clipped at 0)"
    fig.suptitle(f"Speed of convergence: {what} over sessions" + (f"\n{title}" if title else ""))
    # One legend under both panels: a curve that stays high never hides under it.
    entries: dict[str, object] = {}
    for ax in axes[:, 0]:
        for handle, text in zip(*ax.get_legend_handles_labels(), strict=True):
            entries.setdefault(text, handle)
    legend_height = (0.25 * len(entries) + 0.3) / fig.get_figheight()  # fig fraction
    fig.legend(list(entries.values()), list(entries), loc="lower center", fontsize=9, frameon=True)
    fig.tight_layout(rect=(0, legend_height, 1, 1))
    return fig


def plot_trajectories(
    world: BallisticWorld,
    runs: Mapping[str, AlgorithmRun],
    labels: Mapping[str, str],
    path: Path,
    *,
    session: int = 0,
    title: str = "",
) -> None:
    """Fig. 5 (`trajectories_figure`) written to `path`."""
    plt = _pyplot()
    fig = trajectories_figure(world, runs, labels, session=session, title=title)
    fig.savefig(path)
    plt.close(fig)


def trajectories_figure(
    world: BallisticWorld,
    runs: Mapping[str, AlgorithmRun],
    labels: Mapping[str, str],
    *,
    session: int = 0,
    title: str = "",
) -> Any:
    """One session per algorithm (Fig. 5): its arrows up to the first hit, the last one in red.

    Top row: the flights seen from the side (height vs distance). Bottom row: where the arrows
    met the target face, numbered by rollout. `title` (the scenario) goes under the heading.
    Each row's panels of the paper's learners (ARCHER, PoWER) share one scale fitted to their
    arrows, so the two compare at a glance; each baseline's panel is scaled to its own arrows
    (random search's fly metres off and would flatten the others).
    """
    plt = _pyplot()
    names = list(runs)
    paper, _ = split_baselines(names)
    fig, axes = plt.subplots(
        2,
        len(names),
        figsize=(4.2 * len(names), 8.6),
        dpi=110,
        squeeze=False,
        gridspec_kw={"height_ratios": [1.0, 1.3]},
        layout="constrained",
    )
    centre = world.centre
    radius = TARGET_DIAMETER / 2
    heights: dict[str, tuple[float, float]] = {}  # lowest, highest point drawn (m)
    reaches: dict[str, float] = {}  # the face panel's half width (cm)
    face_labels: dict[str, list[Label]] = {}
    for column, name in enumerate(names):
        run = runs[name]
        last = int(min(run.rollouts_to_hit()[session], run.thetas.shape[1]))
        side, face = axes[0, column], axes[1, column]
        low, high = centre[2] - radius, centre[2] + radius
        for k in range(last):
            path_k = world.trajectory(run.thetas[session, k])
            low, high = min(low, float(path_k[:, 2].min())), max(high, float(path_k[:, 2].max()))
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
        px = fig.dpi / 72.0
        face_labels[name] = [
            Label(
                str(k),
                (float(x), float(y)),
                radius_px=0.5 * math.sqrt(60 if k == last else 28) * px,
            )
            for k, (x, y) in sorted(enumerate(r, start=1), key=lambda kxy: kxy[0] != last)
            if k <= 8 or k == last
        ]
        heights[name] = (low, high)
        reaches[name] = max(100 * radius, float(np.abs(r).max()) + 5)
        face.set_aspect("equal")
        face.set_xlabel("right of centre (cm)")
        face.set_ylabel("above centre (cm)")
        face.set_title("impacts on the target, by rollout")
    for column, name in enumerate(names):
        group = paper if name in paper else [name]
        low = min(heights[n][0] for n in group)
        high = max(heights[n][1] for n in group)
        margin = 0.08 * (high - low)
        axes[0, column].set_ylim(low - margin, high + margin)
        reach = max(reaches[n] for n in group)
        axes[1, column].set(xlim=(-reach, reach), ylim=(-reach, reach))
    heading = "Arrow trajectories of one learning session per algorithm (final one in red)"
    fig.suptitle(heading + (f"\n{title}" if title else ""))
    fig.canvas.draw()  # the constrained layout, final before the numbers are placed
    fig.set_layout_engine("none")
    for column, name in enumerate(names):
        place_labels(axes[1, column], face_labels[name])
    return fig
