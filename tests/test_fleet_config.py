"""The fleet's settings without robots: the prefixes and children of `archery up --robots N`,
the learner's `--fleet`, which robot stacks count as alive, and the experiment's bad input
(one line, exit status 2)."""

from __future__ import annotations

from pathlib import Path

import pytest

from archery.apps.experiment.config import ExperimentConfig, ExperimentError
from archery.apps.experiment.experiment_mesh import journal_path, mesh_experiment_config
from archery.apps.experiment.fleet import robot_stacks
from archery.apps.experiment.mesh_out import PLAN_NAME, SessionItem, prepare_out, session_config
from archery.apps.up.launch_config import default_mesh, fleet_prefixes
from archery.mesh.netflags import NetConfig
from archery.protocol.errors import ConfigError
from archery.services.learner.config import LearnerServiceConfig
from tests.conftest import archery


def test_fleet_prefixes_keep_one_robot_as_it_was() -> None:
    assert fleet_prefixes("icubSim", 1) == ("icubSim",)
    assert fleet_prefixes("icubSim", 3) == ("icubSim1", "icubSim2", "icubSim3")
    with pytest.raises(ConfigError, match="--robots must be an integer >= 1, got 0"):
        fleet_prefixes("icubSim", 0)


def test_a_fleet_mesh_has_n_stacks_and_one_learner_serving_all() -> None:
    assert default_mesh(robots=1) == default_mesh()
    children = {c.id: c for c in default_mesh(seed=4, robots=3).children()}
    stack = ("robot", "controller", "camera", "detector")
    expected = [f"{s}@icubSim{i}" for i in (1, 2, 3) for s in stack]
    assert sorted(children) == sorted([*expected, "learner@icubSim1"])
    learner = children["learner@icubSim1"]
    assert learner.args[-2:] == ("--fleet", "icubSim2,icubSim3")
    seeds = [children[f"robot@icubSim{i}"].args for i in (1, 2, 3)]
    assert [a[a.index("--seed") + 1] for a in seeds] == ["4", "5", "6"]


def test_up_refuses_zero_robots_and_a_config_with_robots(tmp_path: Path) -> None:
    result = archery("up", "--robots", "0", "--runs", str(tmp_path), "--logs", str(tmp_path))
    assert result.returncode == 2
    assert result.stderr.strip().splitlines() == [
        "archery up: --robots must be an integer >= 1, got 0"
    ]
    clash = archery("up", "--robots", "2", "--config", "mesh.toml")
    assert clash.returncode == 2
    assert clash.stderr.strip() == "archery up: --robots and --config: set it in mesh.toml instead"


def test_learner_fleet_flag_is_checked() -> None:
    config = LearnerServiceConfig(net=NetConfig(robot="a"), runs=Path("runs"), fleet=("b", "c"))
    assert config.robots() == ("a", "b", "c")
    with pytest.raises(ConfigError, match="--fleet 'b c'"):
        LearnerServiceConfig(net=NetConfig(robot="a"), runs=Path("runs"), fleet=("b c",))
    with pytest.raises(ConfigError, match="a robot is listed twice"):
        LearnerServiceConfig(net=NetConfig(robot="a"), runs=Path("runs"), fleet=("a",))


def test_a_robot_stack_is_alive_only_with_all_four_services() -> None:
    keys = {f"r1/alive/{s}" for s in ("robot", "camera", "detector", "controller")}
    keys |= {"r2/alive/robot", "r2/alive/camera", "r1/alive/robot/0a1b", "r3/alive/learner"}
    assert robot_stacks(keys) == ["r1"]


def test_sessions_share_the_ballistic_seeds_and_resume_checks_the_plan(tmp_path: Path) -> None:
    config = mesh_experiment_config(
        ExperimentConfig(algorithms=("archer", "power"), sessions=2, rollouts=8, world="mesh")
    )
    a, b = (session_config(config, SessionItem(n, 1)) for n in ("archer", "power"))
    assert a.seed == b.seed != session_config(config, SessionItem("archer", 0)).seed
    assert (a.rollouts, a.until_hit) == (8, False)
    assert journal_path(tmp_path, SessionItem("cma", 3)).parts[-3:] == (
        "sessions",
        "cma-s03",
        "journal.jsonl",
    )
    prepare_out(tmp_path, config, resume=False)
    assert (tmp_path / PLAN_NAME).exists()
    prepare_out(tmp_path, config, resume=True)
    with pytest.raises(ExperimentError, match="holds an experiment already; continue it with"):
        prepare_out(tmp_path, config, resume=False)
    other = mesh_experiment_config(
        ExperimentConfig(algorithms=("archer",), sessions=2, rollouts=8, world="mesh")
    )
    ran = r"ran algorithms \['archer', 'power'\], not \['archer'\]"
    with pytest.raises(ExperimentError, match=ran):
        prepare_out(tmp_path, other, resume=True)


@pytest.mark.parametrize(
    ("args", "line"),
    [
        (
            ("--world", "mesh", "--drag", "0.1"),
            "--drag sets the ballistic world; with --world mesh the scene is the robot's "
            "(`archery robot --help`)",
        ),
        (("--resume", "."), "--resume and --robots are for --world mesh"),
        (("--world", "mesh", "--robots", ","), "--robots needs distinct robot prefixes, got ','"),
        (("--world", "mesh", "--robot-wait", "0"), "--robot-wait needs seconds in [0.5, 3600]"),
        (
            (
                "--world",
                "moon",
            ),
            "unknown world 'moon'; valid worlds: ballistic, mesh",
        ),
    ],
)
def test_experiment_bad_input_is_one_line(args: tuple[str, ...], line: str, tmp_path: Path) -> None:
    result = archery("experiment", "--out", str(tmp_path / "x"), *args)
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"archery experiment: error: {line}"), lines


def test_resume_of_a_folder_without_an_experiment(tmp_path: Path) -> None:
    result = archery("experiment", "--world", "mesh", "--resume", str(tmp_path))
    assert result.returncode == 2
    assert result.stderr.strip() == (
        f"archery experiment: error: --resume {str(tmp_path)!r}: no readable {PLAN_NAME} of an "
        f"`archery experiment --world mesh` there"
    )
