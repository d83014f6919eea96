"""The Gymnasium environments raise one documented exception type per kind of bad input, with a
bounded message: a bad or unknown `make` keyword or `reset` option is a ValueError naming it;
an action that is not 3 finite numbers is `BadAction` (Gymnasium's `InvalidAction`, also a
ValueError); a finite action outside the box is clipped."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.error import InvalidAction

import archery.apps.gym  # noqa: F401 (registers the ids)
from archery.apps.gym.aim_robot import AimRobotEnv
from archery.apps.gym.keywords import MESSAGE_LIMIT
from archery.apps.gym.registration import AIM_ID
from archery.apps.gym.spaces import BadAction

MILLION = [0.1] * 10**6

AIM_KEYWORDS: dict[str, tuple[dict[str, Any], str]] = {
    "unknown": ({"nosuch": 1}, "takes no keyword 'nosuch'; its keywords: distance"),
    "wind not a vector": ({"wind": 5}, "wind must be a finite 3-vector"),
    "start not a vector": ({"start": 5}, "start must be a finite 3-vector"),
    "bounds not a pair": ({"bounds": 5}, "bounds must be (low, high)"),
    "until_hit not a bool": ({"until_hit": "maybe"}, "until_hit must be True or False"),
    "distance not a number": ({"distance": "x"}, "distance must be a number (m)"),
    "distance of a million": ({"distance": MILLION}, "distance must be a number (m)"),
    "wind_change of a million": ({"wind_change": "x" * 10**6}, "--wind-change needs"),
    "distance out of range": ({"distance": -1.0}, "distance -1.0 m"),
}


@pytest.mark.parametrize(("keywords", "says"), AIM_KEYWORDS.values(), ids=AIM_KEYWORDS)
def test_a_bad_keyword_of_aim_is_a_value_error_naming_it(
    keywords: dict[str, Any], says: str
) -> None:
    with pytest.raises(ValueError) as caught:
        gym.make(AIM_ID, **keywords)
    assert says in str(caught.value) and len(str(caught.value)) <= MESSAGE_LIMIT


ROBOT_KEYWORDS: dict[str, tuple[dict[str, Any], str]] = {
    "unknown": ({"nosuch": 1}, "takes no keyword 'nosuch'; its keywords: endpoint"),
    "robot not a name": ({"robot": 5}, "robot must name one robot prefix or several"),
    "until_hit not a bool": ({"until_hit": "x"}, "until_hit must be True or False"),
    "wait not a number": ({"wait": "x"}, "wait must be a number (s)"),
    "hit_radius of a million": ({"hit_radius": MILLION}, "hit_radius must be a number (m)"),
    "endpoint of a million": ({"endpoint": "x" * 10**6}, "--connect 'xxx"),
}


@pytest.mark.parametrize(("keywords", "says"), ROBOT_KEYWORDS.values(), ids=ROBOT_KEYWORDS)
def test_a_bad_keyword_of_aim_robot_is_a_value_error_before_the_mesh(
    keywords: dict[str, Any], says: str
) -> None:
    with pytest.raises(ValueError) as caught:
        AimRobotEnv(**keywords)  # refused before any router is looked for
    assert says in str(caught.value) and len(str(caught.value)) <= MESSAGE_LIMIT


@pytest.mark.parametrize(
    ("options", "says"),
    [
        ({"session": -1}, "options['session'] must be an integer >= 0"),
        ({"nosuch": 1}, "reset takes no option 'nosuch'; its options: session"),
        (5, "reset options must be a dict or None, got 5"),
    ],
    ids=["session", "unknown", "not a dict"],
)
def test_a_bad_reset_option_is_a_value_error(options: Any, says: str) -> None:
    env = gym.make(AIM_ID)
    with pytest.raises(ValueError, match=says.replace("[", r"\[").replace("(", r"\(")):
        env.reset(options=options)


@pytest.mark.parametrize(
    ("action", "says"),
    [
        (MILLION, "got 1000000: [0.1, 0.1"),
        (np.zeros(10**6), "got 1000000: array("),
        ("abc", "got 'abc'"),
        ({"a": 1}, "got {'a': 1}"),
        (None, "got 1: None"),
        ([np.nan, 0.0, 0.0], "holds nan at index 0"),
        ([1e400, 0.0, 0.0], "holds inf at index 0"),
    ],
    ids=["million list", "million array", "text", "dict", "None", "NaN", "inf"],
)
def test_a_bad_action_is_gymnasiums_invalid_action_with_a_bounded_message(
    action: object, says: str
) -> None:
    env = gym.make(AIM_ID)
    env.reset(seed=0)
    with pytest.raises(BadAction) as caught:
        env.step(action)
    assert isinstance(caught.value, InvalidAction) and isinstance(caught.value, ValueError)
    assert says in str(caught.value) and len(str(caught.value)) <= MESSAGE_LIMIT
    assert env.unwrapped._shots == 0  # nothing was shot


def test_a_finite_action_outside_the_box_is_clipped() -> None:
    env = gym.make(AIM_ID)
    env.reset(seed=0)
    info = env.step(np.array([5.0, 0.0, 0.0]))[4]
    assert info["clipped"] and info["theta"][0] == env.action_space.high[0]
