"""bench_prior's range table: archer-prior on targets from 1.5 to 5 m with drag and a side wind,
this tree beside an earlier one (`benchmarks.trees`) in the same run.

Each tree runs the same workload in a child process with its own packages first on the path:
for every distance, `--sessions` ballistic sessions of archer-prior (its nominal model: 2.2 m,
no drag, no wind) with a budget of `--rollouts`; rollouts to the 5 cm ring are deterministic
for a seed, so one run per tree is the measurement (the wall time is printed as an aside).
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.trees import env_for

__all__ = ["AIRS", "DISTANCES", "range_rows", "range_table"]

DISTANCES = (1.5, 2.0, 2.5, 3.0, 3.4, 4.0, 4.5, 5.0)  # m
# (label, drag (1/m), wind (m/s)): the wind-change scenario's air, and the gusty one.
AIRS = (
    ("drag 0.05/m + side wind 0,3,0 m/s", 0.05, (0.0, 3.0, 0.0)),
    ("drag 0.1/m + side wind 0,6,0 m/s", 0.1, (0.0, 6.0, 0.0)),
)

# Run in the tree under test (only names both trees have): one JSON list of rows on stdout.
WORKLOAD = """
import json, sys
import numpy as np
from archery.apps.experiment.config import ExperimentConfig
from archery.apps.experiment.experiment import run_algorithm
from archery.sim.ballistic import Scenario
spec = json.loads(sys.argv[1])
rows = []
for distance in spec["distances"]:
    scenario = Scenario(distance=distance, drag=spec["drag"], wind=tuple(spec["wind"]))
    config = ExperimentConfig(
        algorithms=("archer-prior",), sessions=spec["sessions"], rollouts=spec["rollouts"],
        seed=spec["seed"], scenario=scenario,
    )
    run = run_algorithm(config, "archer-prior")
    rows.append({
        "distance_m": distance,
        "rollouts_to_hit": run.rollouts_to_hit().tolist(),
        "first_cm": (100 * run.distances[:, 0]).tolist(),
        "second_cm": (100 * run.distances[:, min(1, spec["rollouts"] - 1)]).tolist(),
        "wall_s": run.wall_time,
    })
print(json.dumps(rows))
"""


def range_rows(
    tree: Path,
    *,
    drag: float,
    wind: tuple[float, float, float],
    sessions: int,
    rollouts: int,
    seed: int,
) -> list[dict[str, Any]]:
    """The workload's rows (one per distance of `DISTANCES`) run on the packages of `tree`."""
    spec = {
        "distances": DISTANCES,
        "drag": drag,
        "wind": wind,
        "sessions": sessions,
        "rollouts": rollouts,
        "seed": seed,
    }
    run = subprocess.run(
        [sys.executable, "-c", WORKLOAD, json.dumps(spec)],
        cwd=tree,  # `-c` puts the working folder first on the path
        env=env_for(tree),
        capture_output=True,
        text=True,
        check=True,
    )
    rows: list[dict[str, Any]] = json.loads(run.stdout)
    return rows


def _cell(row: dict[str, Any], sessions: int, budget: int) -> str:
    to_hit = np.array(row["rollouts_to_hit"])
    q1, median, q3 = np.percentile(to_hit, [25, 50, 75])
    hits = int(np.sum(to_hit <= budget))
    return f"{median:g} [{q1:g}, {q3:g}], {hits}/{sessions}"


def range_table(
    label: str,
    before: tuple[str, list[dict[str, Any]]],
    after: list[dict[str, Any]],
    *,
    sessions: int,
    budget: int,
) -> tuple[list[str], list[str]]:
    """(markdown table, goal lines) of one air: per distance, the first shot's miss (the
    nominal model's aim, the same in both trees), rollouts to the ring in both trees and this
    tree's second shot."""
    name, rows_before = before
    table = [
        f"| {label}: target (m) | first shot ‖r‖ (cm) | {name}: rollouts to hit, median "
        "[q1, q3], sessions hit | this tree | this tree: second shot ‖r‖ (cm), median [max] "
        "| time (s): before, this tree |",
        "|---|---|---|---|---|---|",
    ]
    goals = []
    for old, new in zip(rows_before, after, strict=True):
        distance = new["distance_m"]
        second = np.array(new["second_cm"])
        table.append(
            f"| {distance:g} | {np.median(new['first_cm']):.1f} | {_cell(old, sessions, budget)} "
            f"| {_cell(new, sessions, budget)} | {np.median(second):.1f} [{second.max():.1f}] "
            f"| {old['wall_s']:.1f}, {new['wall_s']:.1f} |"
        )
        to_hit = np.array(new["rollouts_to_hit"])
        median, hits = float(np.median(to_hit)), int(np.sum(to_hit <= budget))
        met = median <= 2 and hits == sessions
        goals.append(
            f"archer-prior goal (median <= 2, {sessions}/{sessions} hit) at {distance:g} m, "
            f"{label}: {'met' if met else 'NOT met'} (median {median:g}, {hits}/{sessions})"
        )
    return table, goals
