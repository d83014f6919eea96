"""Tests of `archery experiment` (apps.experiment.experiment) on small budgets."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from archery.apps.cli import main as archery
from archery.apps.experiment.config import (
    CURVE_COLUMNS,
    AlgorithmRun,
    ExperimentConfig,
    ExperimentError,
)
from archery.apps.experiment.experiment import main, run_algorithm, summarise
from archery.sim.ballistic import Scenario

SMALL = ["--sessions", "3", "--rollouts", "8", "--seed", "1", "--no-progress"]


def test_the_command_writes_valid_files(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    out = tmp_path / "run"
    status = archery(["experiment", *SMALL, "--out", str(out), "--drag", "0.02", "--noise", "0.01"])
    assert status == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["scenario"]["world"] == "ballistic"
    assert summary["scenario"]["drag"] == 0.02 and summary["scenario"]["noise"] == 0.01
    assert set(summary["algorithms"]) == {"archer", "power", "cma", "hill", "random"}
    for stats in summary["algorithms"].values():
        to_hit = stats["rollouts_to_hit"]
        assert set(to_hit) >= {"median", "mean", "q1", "q3"}
        assert 1 <= to_hit["q1"] <= to_hit["median"] <= to_hit["q3"] <= 9
        assert 0.0 <= stats["hit_rate"] <= 1.0
        assert stats["hits"] == round(3 * stats["hit_rate"])
        assert stats["final_distance"]["mean"] >= 0 and stats["final_distance"]["std"] >= 0
    with (out / "curves.csv").open() as handle:
        rows = list(csv.DictReader(handle))
    assert tuple(rows[0]) == CURVE_COLUMNS
    assert len(rows) == 5 * 3 * 8
    for row in rows:
        r_true = np.array([float(row["r_true_x"]), float(row["r_true_y"])])
        assert float(row["distance"]) == pytest.approx(np.linalg.norm(r_true), abs=1e-15)
    for figure in ("fig5.png", "fig6.png"):
        assert (out / figure).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "archer" in capsys.readouterr().out


def test_summary_matches_the_curves(tmp_path: Path) -> None:
    assert main([*SMALL, "--algo", "archer,random", "--out", str(tmp_path), "--no-figures"]) == 0
    summary = json.loads((tmp_path / "summary.json").read_text())
    with (tmp_path / "curves.csv").open() as handle:
        rows = list(csv.DictReader(handle))
    for name in ("archer", "random"):
        distances = np.array(
            [float(r["distance"]) for r in rows if r["algorithm"] == name]
        ).reshape(3, 8)
        hits = distances < 0.05
        to_hit = np.where(hits.any(axis=1), hits.argmax(axis=1) + 1, 9)
        stats = summary["algorithms"][name]
        assert stats["rollouts_to_hit"]["median"] == float(np.median(to_hit))
        assert stats["hit_rate"] == float(np.mean(to_hit <= 8))
        assert stats["final_distance"]["mean"] == pytest.approx(distances[:, -1].mean())


def test_a_session_that_never_hits_counts_as_budget_plus_one() -> None:
    r_true = np.zeros((2, 4, 2))
    r_true[0] = 1.0  # never within 5 cm
    r_true[1, :2] = 1.0  # hits at rollout 3
    run = AlgorithmRun("archer", np.zeros((2, 4, 3)), r_true, r_true, 0.0)
    assert run.rollouts_to_hit().tolist() == [5, 3]
    config = ExperimentConfig(algorithms=("archer",), sessions=2, rollouts=4)
    stats = summarise(config, {"archer": run})["algorithms"]["archer"]
    assert stats["hit_rate"] == 0.5
    assert stats["rollouts_to_hit"]["median"] == 4.0
    to_hit = stats["rollouts_to_hit"]
    assert (to_hit["median_censored"], to_hit["q1_censored"], to_hit["q3_censored"]) == (
        False,
        False,
        True,
    )
    assert to_hit["mean_censored"] and to_hit["censored_sessions"] == 1
    assert to_hit["censored_at"] == 5


def test_a_median_on_a_session_that_never_hit_is_printed_as_above_the_budget(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    # Uniform random search at 5 m with 8 rollouts: no session hits.
    argv = [*SMALL, "--algo", "archer,random", "--distance", "5", "--no-figures"]
    assert main([*argv, "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    summary = json.loads((tmp_path / "summary.json").read_text())["algorithms"]
    assert summary["random"]["hits"] == 0 and summary["random"]["rollouts_to_hit"]["median"] == 9
    assert summary["random"]["rollouts_to_hit"]["median_censored"]
    assert not summary["archer"]["rollouts_to_hit"]["median_censored"]
    row = next(line for line in out.splitlines() if "random" in line)
    assert "> 8 [> 8, > 8]" in row and "≥ 9.0" in row and "0/3 (0 %)" in row
    assert "9 [" not in row


def test_power_scale_changes_power_only(tmp_path: Path) -> None:
    common = {"sessions": 3, "rollouts": 8, "seed": 2}
    plain = ExperimentConfig(algorithms=("archer", "power", "power-metre"), **common)
    scaled = ExperimentConfig(
        algorithms=("archer", "power", "power-metre"), power_scale=0.01, **common
    )
    assert np.array_equal(
        run_algorithm(plain, "archer").thetas, run_algorithm(scaled, "archer").thetas
    )
    assert not np.array_equal(
        run_algorithm(plain, "power").thetas, run_algorithm(scaled, "power").thetas
    )
    # power-metre is PoWER with s = 1 m: --power-scale 1 makes power the same learner.
    metre = ExperimentConfig(algorithms=("power",), power_scale=1.0, **common)
    assert np.array_equal(
        run_algorithm(plain, "power-metre").thetas, run_algorithm(metre, "power").thetas
    )
    assert metre.learner("power", 0).return_scale == 1.0
    assert scaled.to_dict()["power_scale_m"] == 0.01 and plain.to_dict()["power_scale_m"] is None


@pytest.mark.parametrize("band", ["median", "mean"])
def test_fig6_band_is_selectable(band: str, tmp_path: Path) -> None:
    argv = [*SMALL, "--algo", "archer,hill", "--fig6", band, "--out", str(tmp_path)]
    assert main(argv) == 0
    assert (tmp_path / "fig6.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_same_seed_same_numbers_bit_for_bit_and_independent_of_the_algorithm_list() -> None:
    scenario = Scenario(drag=0.02, wind=(0.0, 1.0, 0.0), noise=0.01)
    both = ExperimentConfig(
        algorithms=("archer", "power"), sessions=3, rollouts=8, seed=4, scenario=scenario
    )
    alone = ExperimentConfig(
        algorithms=("power",), sessions=3, rollouts=8, seed=4, scenario=scenario
    )
    a, b = run_algorithm(both, "power"), run_algorithm(alone, "power")
    assert np.array_equal(a.thetas, b.thetas) and np.array_equal(a.r_observed, b.r_observed)
    other = run_algorithm(
        ExperimentConfig(algorithms=("power",), sessions=3, rollouts=8, seed=5, scenario=scenario),
        "power",
    )
    assert not np.array_equal(a.thetas, other.thetas)


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--algo", "archer,powr"], "unknown algorithm 'powr'; valid algorithms: archer"),
        (["--world", "mujoco"], "unknown world 'mujoco'; valid worlds: ballistic"),
        (["--rollouts", "3"], "rollouts 3 is below archer's exploration phase (3 rollouts)"),
        (["--rollouts", "6", "--algo", "cma"], "use rollouts >= 8"),
        (["--sessions", "0"], "sessions must be an integer >= 1, got 0"),
        (["--sessions", "many"], "--sessions needs an integer, got 'many'"),
        (
            ["--wind", "1,2"],
            "--wind must be a finite 3-vector (m/s): 3 comma-separated finite numbers, got '1,2'",
        ),
        (["--wind", "1,0,0"], "has no effect without air drag"),
        (["--drag", "-1"], "drag must be >= 0"),
        (["--noise", "nan"], "--noise needs a number, got 'nan'"),
        (["--distance", "0.2"], "distance 0.2 m puts the target behind"),
        (["--bow-stiffness", "0"], "bow_stiffness must be > 0"),
        (["--start", "0.5,0,0"], "start θ [0.5, 0.0, 0.0] m lies outside the θ box"),
        (["--power-scale", "0"], "--power-scale must be in [0.0001, 10] m, got 0.0"),
        (["--power-scale", "5cm"], "--power-scale needs a number, got '5cm'"),
        (["--power-scale", "inf"], "--power-scale needs a number, got 'inf'"),
    ],
)
def test_bad_input_is_a_clear_error(
    args: list[str], message: str, tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    status = main([*SMALL, "--out", str(tmp_path), *args])
    assert status == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "summary.json").exists()


def test_config_rejects_repeated_algorithms() -> None:
    with pytest.raises(ExperimentError, match="repeats"):
        ExperimentConfig(algorithms=("archer", "archer"))


def test_a_wind_change_is_run_counted_and_marked(tmp_path: Path) -> None:
    argv = ["--sessions", "3", "--rollouts", "12", "--no-progress", "--drag", "0.05"]
    argv += ["--wind", "0,3,0", "--wind-change", "6:0,-6,0", "--algo", "archer-prior,archer"]
    assert main([*argv, "--out", str(tmp_path)]) == 0
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["scenario"]["wind_change"] == {"at": 6, "wind": [0.0, -6.0, 0.0]}
    with (tmp_path / "curves.csv").open() as handle:
        rows = [r for r in csv.DictReader(handle) if r["algorithm"] == "archer-prior"]
    for s in range(3):
        distances = [float(r["distance"]) for r in rows if int(r["session"]) == s]
        hits = [k + 1 for k, d in enumerate(distances) if d < 0.05 and k + 1 >= 6]
        assert hits and hits[0] - 6 + 1 <= 2  # re-hit within two rollouts of the change
        assert distances[5] > 0.05  # the change moved the arrow off the ring
    prior = summary["algorithms"]["archer-prior"]
    assert prior["rollouts_to_rehit"]["median"] <= 2 and prior["rehits"] == 3
    # The same rollouts without the change: the arrows stay on the ring.
    config = ExperimentConfig(
        algorithms=("archer-prior",),
        sessions=2,
        rollouts=12,
        scenario=Scenario(drag=0.05, wind=(0.0, 3.0, 0.0)),
    )
    steady = run_algorithm(config, "archer-prior")
    assert np.all(steady.distances[:, 1:] < 0.05)
    assert (
        summarise(config, {"archer-prior": steady})["algorithms"]["archer-prior"][
            "rollouts_to_rehit"
        ]
        is None
    )


def test_rollouts_to_rehit_counts_from_the_change() -> None:
    far, near = 0.3, 0.01
    distances = np.array([[near, near, far, far, near], [near, far, far, far, far]])
    r_true = np.stack([distances, np.zeros_like(distances)], axis=-1)
    run = AlgorithmRun("x", np.zeros((2, 5, 3)), r_true, r_true, 0.0)
    assert run.rollouts_to_rehit(3).tolist() == [3, 4]  # hit at 5; none (budget − 3 + 2)
    assert run.rollouts_to_rehit(2).tolist() == [1, 5]  # rollout 2 itself hits
