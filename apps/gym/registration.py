"""The environment ids of the archery task and their registration with Gymnasium.

`archery/Aim-v0` (`apps.gym.aim.AimEnv`, the analytic world) and `archery/AimRobot-v0`
(`apps.gym.aim_robot.AimRobotEnv`, the MuJoCo iCub over a running mesh). Importing `apps.gym`
registers them, so `gymnasium.make("archery.apps.gym:archery/Aim-v0")` needs no import first; the
package also declares `register_envs` under Gymnasium's plugin entry-point group
(`gymnasium.envs`, pyproject.toml). Registering twice is harmless.
"""

from __future__ import annotations

import gymnasium as gym

__all__ = ["AIM_ID", "AIM_ROBOT_ID", "register_envs"]

AIM_ID = "archery/Aim-v0"
AIM_ROBOT_ID = "archery/AimRobot-v0"


def register_envs() -> None:
    """Register both ids (their budgets are the environments' own `budget` keyword, so no
    `TimeLimit` wrapper is added)."""
    if AIM_ID not in gym.registry:
        gym.register(id=AIM_ID, entry_point="archery.apps.gym.aim:AimEnv")
    if AIM_ROBOT_ID not in gym.registry:
        gym.register(id=AIM_ROBOT_ID, entry_point="archery.apps.gym.aim_robot:AimRobotEnv")
