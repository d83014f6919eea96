"""`archery/AimRobot-v0` on a real mesh: a router and two MuJoCo iCub stacks (robot, controller,
camera, detector; `archery up --robots 2`'s `icubSim1`, `icubSim2`) on a free loopback port,
at rtf 0. A few shots per test."""

from __future__ import annotations

import json
import signal
import time
import warnings
from collections.abc import Iterator
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from archery.apps.compare.compare import main as compare_main
from archery.apps.gym.aim_robot import AimRobotEnv, RobotUnavailable, ServiceLostError
from archery.apps.up.launch_config import default_mesh
from archery.apps.up.launcher import Launcher
from archery.mesh.router import free_tcp_endpoint
from archery.protocol.robotspec import THETA0
from archery.protocol.theta import THETA_BOX

pytestmark = pytest.mark.slow

ROBOT = "archery.apps.gym:archery/AimRobot-v0"
ROBOTS = ("icubSim1", "icubSim2")


@pytest.fixture(scope="module")
def mesh(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Launcher]:
    launcher = Launcher(
        logs=tmp_path_factory.mktemp("gym-mesh"),
        mesh=default_mesh(free_tcp_endpoint(), robots=2, rtf=0.0),
    )
    try:
        launcher.up(180, services=[n for n in launcher.specs if not n.startswith("learner")])
        yield launcher
    finally:
        launcher.stop_all()


def _env(mesh: Launcher, **keywords: object) -> AimRobotEnv:
    env = gym.make(ROBOT, endpoint=mesh.endpoint, robot=ROBOTS[0], **keywords).unwrapped
    assert isinstance(env, AimRobotEnv)
    return env


def test_gymnasiums_checker_passes_on_the_icub(mesh: Launcher) -> None:
    env = _env(mesh, budget=3)
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            check_env(env)
        remarks = {str(w.message) for w in caught}
        assert all("symmetric and normalized" in m or "infinity" in m for m in remarks), remarks
    finally:
        env.close()


def test_the_detectors_r_is_the_observation_and_the_truth_only_in_info(mesh: Launcher) -> None:
    env = _env(mesh)
    try:
        assert env.action_space.low.tolist() == THETA_BOX.low
        assert env.action_space.high.tolist() == THETA_BOX.high
        obs, info = env.reset(seed=4)
        assert obs[2:].tolist() == list(THETA0) and info["shots"] == 0
        obs, reward, _, _, info = env.step(np.array(THETA0))
        assert info["status"] == "ok" and obs[:2].tolist() == info["r"].tolist()
        assert reward == -info["distance"] == -float(np.hypot(*info["r"]))
        assert info["r_true"] is not None and info["r_true"].tolist() != info["r"].tolist()
        assert np.abs(info["r_true"] - info["r"]).max() < 0.01  # the detector within 1 cm
        assert np.abs(info["theta_measured"] - THETA0).max() < 1e-3
        assert 0.0 < info["confidence"] <= 1.0 and not info["clipped"]
        # reset(seed) reseeds the robot's shot noise: the same shot again
        env.reset(seed=4)
        again = env.step(np.array(THETA0))[4]
        assert again["r_true"].tolist() == info["r_true"].tolist()
    finally:
        env.close()


def test_bad_actions_never_reach_the_robot(mesh: Launcher) -> None:
    env = _env(mesh)
    try:
        env.reset(seed=1)
        shots = env.rig.setup()["shot"]
        with pytest.raises(ValueError, match="nan at index 2"):
            env.step(np.array([0.17, 0.0, np.nan]))
        assert env.rig.setup()["shot"] == shots  # nothing moved, nothing released
        _, _, _, _, info = env.step(np.array([0.5, 0.0, -0.026]))
        assert info["clipped"] and info["theta"][0] == THETA_BOX.high[0]
        assert abs(info["theta_measured"][0] - THETA_BOX.high[0]) < 1e-3
    finally:
        env.close()


def test_no_mesh_is_the_waiting_line_then_a_clear_error(capfd: pytest.CaptureFixture[str]) -> None:
    endpoint = free_tcp_endpoint()
    started = time.monotonic()
    with pytest.raises(RobotUnavailable, match=f"no robot 'icubSim' ready at {endpoint}"):
        gym.make(ROBOT, endpoint=endpoint, wait=1.0)
    assert time.monotonic() - started < 15
    err = capfd.readouterr().err
    line = f"archery/AimRobot-v0: waiting up to 1 s for the router at {endpoint} (Ctrl-C to stop)"
    assert line in err


def test_a_robot_not_on_the_mesh_is_the_waiting_line_then_a_clear_error(
    mesh: Launcher, capfd: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(RobotUnavailable, match=r"no robot 'nobody' ready .* not alive after 1 s"):
        gym.make(ROBOT, endpoint=mesh.endpoint, robot="nobody", wait=1.0)
    err = capfd.readouterr().err
    assert "archery/AimRobot-v0: waiting up to 1 s for the services: " in err
    with pytest.raises(ValueError, match="tls/"):  # a secure deployment needs a TLS endpoint
        gym.make(ROBOT, endpoint=mesh.endpoint, secure="/nowhere")


def test_a_service_lost_in_a_step_is_named_and_the_next_reset_works(mesh: Launcher) -> None:
    env = _env(mesh, rpc_timeout=3.0, wait=30.0)
    detector = mesh.children[f"detector@{ROBOTS[0]}"].proc
    assert detector is not None
    try:
        env.reset(seed=2)
        detector.send_signal(signal.SIGSTOP)  # frozen: alive for Zenoh, silent for the rig
        try:
            with pytest.raises(ServiceLostError, match="detector") as lost:
                env.step(np.array(THETA0))
            assert lost.value.service == "detector"
        finally:
            detector.send_signal(signal.SIGCONT)
        env.reset(seed=2)
        assert env.step(np.array(THETA0))[4]["status"] == "ok"
    finally:
        env.close()


def test_make_vec_gives_each_process_its_own_robot_of_the_fleet(mesh: Launcher) -> None:
    envs = gym.make_vec(
        ROBOT,
        num_envs=2,
        vectorization_mode="async",
        endpoint=mesh.endpoint,
        robot=list(ROBOTS),
        vector_kwargs={"context": "spawn"},
    )
    try:
        envs.reset(seed=[1, 2])
        _, rewards, _, _, infos = envs.step(np.array([THETA0, THETA0]))
    finally:
        envs.close()
    assert sorted(infos["robot"].tolist()) == list(ROBOTS)
    assert np.all(rewards < 0)


def test_a_process_forked_after_zenoh_ran_says_so_instead_of_hanging(
    mesh: Launcher, capfd: pytest.CaptureFixture[str]
) -> None:
    # the worker raises at once and exits; the parent sees its pipe closed
    with pytest.raises((ConnectionError, EOFError)):
        envs = gym.make_vec(
            ROBOT,
            num_envs=2,
            vectorization_mode="async",
            vector_kwargs={"context": "fork"},
            endpoint=mesh.endpoint,
            robot=list(ROBOTS),
        )
        try:
            envs.reset(seed=[1, 2])
        finally:
            envs.close(terminate=True)
    assert "Zenoh does not survive fork" in capfd.readouterr().err


def test_compare_on_the_icub_with_a_short_budget(
    mesh: Launcher, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = ["--world", "mesh", "--connect", mesh.endpoint, "--robot", ROBOTS[1]]
    argv += ["--sessions", "1", "--rollouts", "3", "--methods", "archer,ngopt"]
    assert compare_main([*argv, "--out", str(tmp_path), "--no-progress"]) == 0
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["run"]["env"] == "archery/AimRobot-v0"
    assert list(summary["methods"]) == ["archer", "ngopt"]
    assert (tmp_path / "fig6.png").is_file() and "archer" in capsys.readouterr().out
