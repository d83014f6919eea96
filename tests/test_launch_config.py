"""The launch description of `archery up` (--config mesh.toml): the model, its validation, the
shipped example, and that docker-compose.yml describes the same mesh as the default."""

from __future__ import annotations

import tomllib
from pathlib import Path

import pytest

from archery.apps.up.command import main
from archery.apps.up.launch_config import (
    SERVICES,
    MeshConfig,
    RobotSpec,
    default_mesh,
    load_mesh,
    parse_mesh,
)
from archery.apps.up.launcher import Launcher
from archery.apps.up.restart_policy import RestartPolicy
from archery.protocol.errors import ConfigError
from tests.composefile import read_compose

ROOT = Path(__file__).resolve().parents[1]
COMPOSE_RESTART = {"always": "always", "on-failure": "on-failure", "never": "no"}


def test_the_shipped_example_is_the_default() -> None:
    assert load_mesh(ROOT / "mesh.toml") == default_mesh()
    children = default_mesh().children()
    assert [c.id for c in children] == list(SERVICES)
    assert all(c.robot == "icubSim" and c.restart == RestartPolicy() for c in children)


def test_the_docs_show_the_example() -> None:
    page = (ROOT / "docs" / "mesh-up.md").read_text()
    example = (ROOT / "mesh.toml").read_text()
    shown = page.split("```toml\n", 1)[1].split("```", 1)[0]
    assert shown == example


def test_compose_describes_the_default_mesh() -> None:
    """Same services, the same arguments but for the endpoint (and the runs directory, which
    compose mounts from ./runs), and the same restart policies."""
    compose = read_compose(ROOT / "docker-compose.yml")["services"]
    mesh = default_mesh()
    plain = {n: s for n, s in compose.items() if "profiles" not in s and n != "demo"}
    assert set(plain) == {"router", *SERVICES}
    router = plain["router"]["command"]
    assert router[:3] == ["archery", "router", "--listen"] and len(router) == 5
    assert router[4] == "--insecure-network"  # the container network is the trust boundary
    assert plain["router"]["restart"] == COMPOSE_RESTART[mesh.router.restart.mode]
    volume = compose["learner"]["volumes"][0]
    host_runs, container_runs = volume.rsplit(":", 1)
    for child in mesh.children():
        command = plain[child.service]["command"]
        assert command[:4] == ["archery", child.service, "--connect", "tcp/router:7447"]
        args = [
            "runs" if a == container_runs and host_runs == "${ARCHERY_RUNS:-./runs}" else a
            for a in command[4:]
        ]
        if args[-2:] == ["--shot", "${ARCHERY_SHOT:-posture}"]:
            args = args[:-2]  # the shot's variable: the default, posture, when it is not set
        assert args == list(child.args), child.service
        assert plain[child.service]["restart"] == COMPOSE_RESTART[child.restart.mode]


def test_a_full_description(tmp_path: Path) -> None:
    path = tmp_path / "mesh.toml"
    path.write_text(
        """
[router]
endpoint = "tcp/127.0.0.1:7999"
start = false
restart = { mode = "always", backoff = 2 }

[restart]
budget = 3

[robots.left]
services = ["robot", "controller"]
args = { robot = ["--seed", "7"] }

[robots.right]
services = ["controller"]

[services.controller]
args = ["--log-level", "debug"]
restart = "never"
"""
    )
    mesh = load_mesh(path)
    assert mesh.router.endpoint == "tcp/127.0.0.1:7999" and not mesh.router.start
    assert mesh.router.restart == RestartPolicy(mode="always", budget=3, backoff=2.0)
    children = {c.id: c for c in mesh.children()}
    assert list(children) == ["robot@left", "controller@left", "controller@right"]
    assert children["robot@left"].args == ("--seed", "7")
    assert children["robot@left"].restart == RestartPolicy(budget=3)
    assert children["controller@right"].args == ("--log-level", "debug")
    assert children["controller@right"].restart == RestartPolicy(mode="never", budget=3)
    overridden = mesh.with_policy("always", 9)
    assert {c.restart.mode for c in overridden.children()} == {"always"}
    assert overridden.router.restart == RestartPolicy(mode="always", budget=9, backoff=2.0)
    launcher = Launcher(logs=tmp_path, mesh=mesh)
    assert not launcher.with_router and set(launcher.specs) == set(children)
    assert launcher.policy("controller@left").mode == "never"


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("[routr]\n", "routr: unknown key; known here: router, restart, robots, services"),
        ('[router]\nendpont = "x"\n', "router.endpont: unknown key"),
        ('[router]\nendpoint = "127.0.0.1:7447"\n', "router.endpoint: --connect '127.0.0.1:7447'"),
        ('[router]\nstart = "yes"\n', "router.start: expected true or false"),
        ('[restart]\nmode = "sometimes"\n', "restart: restart policy 'sometimes' is not one of"),
        ("[restart]\nbudget = -1\n", "restart: restart budget must be an integer"),
        ("[restart]\nretries = 3\n", "restart.retries: unknown key; known here: mode, budget"),
        ("[services.camra]\nargs = []\n", "services.camra: no service 'camra'; services: robot"),
        ('[services.robot]\nargs = "--seed 1"\n', "services.robot.args: expected a list"),
        ('[services.robot]\nrestart = "maybe"\n', "services.robot.restart: restart policy"),
        ("[services.robot]\nflags = []\n", "services.robot.flags: unknown key"),
        ('[robots.x]\nservices = ["arm"]\n', "robots.x.services: no service 'arm'"),
        ('[robots."a b"]\n', "robots.a b: --robot:"),
        ("[robots.x]\nargs = { eye = [] }\n", "robots.x.args: no service 'eye'"),
        ("robots = {}\n", "robots: the mesh needs at least one robot"),
        ("[router\n", "not valid TOML"),
    ],
)
def test_bad_descriptions_are_named(tmp_path: Path, text: str, message: str) -> None:
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(ConfigError) as error:
        load_mesh(path)
    assert str(error.value).startswith(f"--config {path}: ")
    assert message in str(error.value)
    assert "\n" not in str(error.value)


def test_the_model_checks_itself() -> None:
    with pytest.raises(ConfigError, match="services: no service 'eye'"):
        MeshConfig(services={"eye": default_mesh().services["robot"]})
    with pytest.raises(ConfigError, match=r"robots\.x: the robot is listed twice"):
        MeshConfig(robots=(RobotSpec("x"), RobotSpec("x")))
    empty = parse_mesh(tomllib.loads(""))  # every default: a router, five bare services
    assert empty.router == default_mesh().router
    assert [(c.id, c.robot, c.args) for c in empty.children()] == [
        (n, "icubSim", ()) for n in SERVICES
    ]


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--config", "{missing}"], "No such file"),
        (["--config", "{bad}"], "services.eye: no service 'eye'"),
        (["--config", "{good}", "--seed", "3"], "--seed and --config: set it in"),
        (["--config", "{good}", "--robot", "r"], "--robot and --config"),
        (["--config", "{good}", "--shot", "whole"], "--shot and --config"),
        (["--robots", "1000", "--runs", "{runs}"], "--robots 1000: this machine holds at most"),
    ],
)
def test_up_refuses_a_bad_config_with_one_line_and_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], argv: list[str], message: str
) -> None:
    files = {"missing": tmp_path / "none.toml", "bad": tmp_path / "bad.toml", "runs": tmp_path}
    files["bad"].write_text("[services.eye]\n")
    files["good"] = ROOT / "mesh.toml"
    argv = [a.format(**files) for a in argv] + ["--logs", str(tmp_path / "logs")]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("archery up: ") and message in err
    assert len(err.strip().splitlines()) == 1
    assert not (tmp_path / "logs").exists()  # nothing started


def test_the_whole_shot_is_the_robot_s_flag() -> None:
    robot = {c.service: c for c in default_mesh(shot="whole").children()}["robot"]
    assert robot.args[-2:] == ("--shot", "whole")
    assert "--shot" not in {c.service: c for c in default_mesh().children()}["robot"].args
