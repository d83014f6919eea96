"""`archery compare` on the analytic world: the project's learners, pycma and nevergrad through
`archery/Aim-v0`, Fig. 6 and the table; its bad input."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import pytest

from archery.apps.compare.compare import main
from archery.apps.experiment.censored import count_stats
from archery.apps.experiment.config import ExperimentConfig
from archery.apps.experiment.experiment import run_algorithm
from archery.mesh.router import free_tcp_endpoint
from archery.sim.ballistic import Scenario


def test_compare_runs_every_method_through_the_environment(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "cmp"
    args = ["--sessions", "3", "--rollouts", "20", "--seed", "4", "--noise", "0.005"]
    assert main([*args, "--out", str(out), "--no-progress"]) == 0
    printed = capsys.readouterr().out
    summary = json.loads((out / "summary.json").read_text())
    assert list(summary["methods"]) == ["archer", "power", "pycma", "ngopt"]
    for name in summary["methods"]:
        assert name in printed
    assert (out / "fig6.png").read_bytes().startswith(b"\x89PNG")
    with (out / "curves.csv").open() as handle:
        rows = list(csv.DictReader(handle))
    assert len(rows) == 4 * 3 * 20
    # the project's learners through the environment: the experiment's sessions exactly
    config = ExperimentConfig(
        algorithms=("archer", "power"),
        sessions=3,
        rollouts=20,
        seed=4,
        scenario=Scenario(noise=0.005),
    )
    for name in config.algorithms:
        run = run_algorithm(config, name)
        assert summary["methods"][name]["rollouts_to_hit"] == count_stats(run.rollouts_to_hit(), 20)
        thetas = [
            [float(r["theta_x"]), float(r["theta_y"]), float(r["theta_z"])]
            for r in rows
            if r["method"] == name
        ]
        assert thetas == run.thetas.reshape(-1, 3).tolist()
    # the same seed, the same comparison (pycma and NGOpt seeded from it too)
    again = tmp_path / "again"
    assert main([*args, "--out", str(again), "--no-progress"]) == 0
    assert (again / "curves.csv").read_text() == (out / "curves.csv").read_text()


@pytest.mark.parametrize(
    ("argv", "said"),
    [
        (["--methods", "archer,bogus"], "--methods"),
        (["--sessions", "0"], "--sessions"),
        (["--drag", "-1"], "drag"),
        (["--wind", "0,3,0"], "wind"),
        (["--world", "mesh", "--drag", "0.1"], "--world ballistic"),
    ],
)
def test_bad_input_is_one_line_and_status_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], argv: list[str], said: str
) -> None:
    assert main([*argv, "--out", str(tmp_path / "x"), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("archery compare: error:") and said in err and err.count("\n") == 1


def test_no_robot_is_the_waiting_line_then_status_1(
    tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    endpoint = free_tcp_endpoint()
    argv = ["--world", "mesh", "--connect", endpoint, "--wait", "1", "--out", str(tmp_path)]
    assert main(argv) == 1
    err = capfd.readouterr().err
    assert f"waiting up to 1 s for the router at {endpoint}" in err
    assert f"archery compare: archery/AimRobot-v0: no robot 'icubSim' ready at {endpoint}" in err
