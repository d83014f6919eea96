"""Fig. 5 and Fig. 6 of the experiment read at a glance: the paper's learners on their own
scale, the baselines apart, no number on a marker."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import matplotlib.pyplot as plt
import pytest

from archery.apps.experiment.config import ExperimentConfig
from archery.apps.experiment.experiment import run_algorithm
from archery.apps.experiment.plots import convergence_figure, split_baselines, trajectories_figure
from archery.apps.experiment.plots_mesh import impacts_figure
from archery.protocol.theta import ThetaBox
from archery.services.learner.algorithms.registry import ALGORITHMS
from archery.sim.ballistic import BallisticWorld, Scenario

NAMES = ("archer", "power", "cma", "hill", "random")


#: θ box (m) wide enough that random search's arrows scatter far from the paper's learners'
WIDE = ThetaBox(low=(0.10, -0.12, -0.12), high=(0.30, 0.12, 0.12))


@pytest.fixture(scope="module")
def runs() -> dict[str, Any]:
    config = ExperimentConfig(sessions=8, rollouts=30, seed=1, algorithms=NAMES, bounds=WIDE)
    return {name: run_algorithm(config, name) for name in NAMES}


@pytest.fixture
def closing() -> Iterator[list[Any]]:
    figures: list[Any] = []
    yield figures
    for fig in figures:
        plt.close(fig)


def _labels() -> dict[str, str]:
    return {name: ALGORITHMS[name].label for name in NAMES}


def test_the_paper_learners_and_the_baselines_are_told_apart() -> None:
    assert split_baselines(["random", "archer", "cma", "power-metre", "hill", "archer-prior"]) == (
        ["archer", "power-metre", "archer-prior"],
        ["random", "cma", "hill"],
    )


def test_fig6_puts_the_baselines_on_their_own_log_panel(runs: dict, closing: list) -> None:
    fig = convergence_figure(runs, _labels())
    closing.append(fig)
    paper_ax, baseline_ax = fig.axes
    assert [line.get_label().split(":")[0] for line in paper_ax.lines[:2]] == [
        "ARCHER (safeguarded)",
        "PoWER",
    ]
    assert baseline_ax.get_yscale() == "log" and paper_ax.get_yscale() == "linear"
    # the paper's panel is scaled to ARCHER's and PoWER's central lines, not to random search's
    highest = max(float(line.get_ydata().max()) for line in paper_ax.lines[:2])
    assert paper_ax.get_ylim()[1] <= 1.3 * highest
    random_median = next(ln for ln in baseline_ax.lines if ln.get_label().startswith("random"))
    assert float(random_median.get_ydata().min()) > paper_ax.get_ylim()[1] / 2
    assert baseline_ax.get_ylim()[1] >= float(random_median.get_ydata().max())
    # one legend, under both panels
    renderer = fig.canvas.get_renderer()
    legend = fig.legends[0].get_window_extent(renderer)
    assert legend.y1 < baseline_ax.get_window_extent(renderer).y0


def test_fig6_of_the_paper_learners_alone_has_one_panel(runs: dict, closing: list) -> None:
    fig = convergence_figure({n: runs[n] for n in ("archer", "power")}, _labels())
    closing.append(fig)
    assert len(fig.axes) == 1 and fig.axes[0].get_yscale() == "linear"


def test_fig5_scales_the_paper_learners_together_and_each_baseline_alone(
    runs: dict, closing: list
) -> None:
    fig = trajectories_figure(BallisticWorld(Scenario()), runs, _labels())
    closing.append(fig)
    sides = {name: fig.axes[i] for i, name in enumerate(NAMES)}
    faces = {name: fig.axes[len(NAMES) + i] for i, name in enumerate(NAMES)}
    assert sides["archer"].get_ylim() == sides["power"].get_ylim()
    assert faces["archer"].get_xlim() == faces["power"].get_xlim()
    for name, ax in sides.items():  # each panel fits its arrows with a small margin
        drawn = [line.get_ydata() for line in ax.lines]
        low = min(float(min(y)) for y in drawn)
        high = max(float(max(y)) for y in drawn)
        ylim = ax.get_ylim()
        assert ylim[0] <= low and high <= ylim[1], name
        if name not in ("archer", "power"):
            assert ylim[1] - ylim[0] <= 1.2 * (high - low), name
    span = sides["archer"].get_ylim()[1] - sides["archer"].get_ylim()[0]
    random_span = sides["random"].get_ylim()[1] - sides["random"].get_ylim()[0]
    assert random_span > 2 * span  # random search's arrows did not set ARCHER's scale
    renderer = fig.canvas.get_renderer()
    for ax in faces.values():
        markers = [
            (x, y)
            for collection in ax.collections
            for x, y in collection.get_offset_transform().transform(collection.get_offsets())
        ]
        assert ax.texts
        for text in ax.texts:
            box = text.get_window_extent(renderer)
            assert not any(box.contains(x, y) for x, y in markers), text.get_text()


def test_fig5_on_the_robot_scales_the_paper_learners_together(runs: dict, closing: list) -> None:
    fig = impacts_figure(runs, _labels())
    closing.append(fig)
    panels = dict(zip(NAMES, fig.axes, strict=False))
    assert panels["archer"].get_xlim() == panels["power"].get_xlim()
    assert panels["archer"].get_ylim() == panels["power"].get_ylim()
    reach = {name: panels[name].get_xlim()[1] for name in NAMES}
    assert reach["random"] > 2 * reach["archer"]  # random search's impacts set only its own
    for name, ax in panels.items():  # each panel holds its impacts
        impacts = ax.collections[0].get_offsets()
        assert abs(impacts).max() <= reach[name], name
