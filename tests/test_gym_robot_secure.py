"""`archery/AimRobot-v0` in secure mode: a mutual-TLS router with its access control and one
MuJoCo iCub stack, each child with its own identity of a fresh deployment; the environment
presents the `operator` identity (or the one given). A few shots."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

from archery.apps.gym.aim_robot import AimRobotEnv, RobotUnavailable
from archery.apps.up.launcher import Launcher
from archery.mesh.credentials import init_deployment
from archery.mesh.router import free_tcp_endpoint
from archery.protocol.robotspec import THETA0

pytestmark = pytest.mark.slow

ROBOT = "archery.apps.gym:archery/AimRobot-v0"
PREFIX = "icubSim"


@pytest.fixture(scope="module")
def secure_mesh(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Launcher, Path]]:
    base = tmp_path_factory.mktemp("gym-secure")
    deployment = init_deployment(base / "deploy", robot=PREFIX)
    tls = free_tcp_endpoint().replace("tcp/", "tls/")
    launcher = Launcher(tls, PREFIX, base / "logs", secure=str(deployment))
    try:
        launcher.up(180, services=[n for n in launcher.specs if n != "learner"])
        yield launcher, deployment
    finally:
        launcher.stop_all()
        launcher.forget_identities()


def test_the_icub_shoots_over_a_secure_mesh(secure_mesh: tuple[Launcher, Path]) -> None:
    launcher, deployment = secure_mesh
    env = gym.make(ROBOT, endpoint=launcher.endpoint, secure=str(deployment)).unwrapped
    assert isinstance(env, AimRobotEnv)
    try:
        env.reset(seed=5)
        obs, reward, _, _, info = env.step(np.array(THETA0))
        assert info["status"] == "ok" and obs[:2].tolist() == info["r"].tolist() and reward < 0
    finally:
        env.close()


def test_an_identity_outside_the_deployment_is_refused(secure_mesh: tuple[Launcher, Path]) -> None:
    launcher, deployment = secure_mesh
    with pytest.raises((RobotUnavailable, ValueError), match="nobody"):
        gym.make(
            ROBOT, endpoint=launcher.endpoint, secure=str(deployment), identity="nobody", wait=2.0
        )
