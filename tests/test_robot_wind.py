"""`setWind` on `ROBOT/archery/rpc:i` over a real router: the wind of the following shots moves
their true impact downwind, `status` reports it, and bad values are refused."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest

from archery.protocol.errors import RpcError
from tests.test_robot_service import Client, Joints, aim_joints, robot, shoot  # noqa: F401

WIND = [0.0, 10.0, 0.0]  # m/s along +y: r[0] of the impact is along +y


def test_set_wind_moves_the_impact_downwind(
    robot: Callable[..., Client],  # noqa: F811
    aim_joints: Joints,  # noqa: F811
) -> None:
    client = robot()
    assert client.archery("status")["world"]["wind"] == [0.0, 0.0, 0.0]
    calm = np.asarray(shoot(client, aim_joints, 3))
    assert client.archery("setWind", {"wind": WIND}) == {"wind": WIND}
    assert client.archery("status")["world"]["wind"] == WIND
    windy = np.asarray(
        shoot(client, aim_joints, 3)
    )  # same seed: the same launch, only the wind differs
    shift = windy - calm
    assert shift[0] > 0.03 and abs(shift[1]) < shift[0]  # downwind, mostly sideways
    assert client.archery("setWind", {"wind": [0, 0, 0]}) == {"wind": [0.0, 0.0, 0.0]}
    np.testing.assert_array_equal(
        np.asarray(shoot(client, aim_joints, 3)), calm
    )  # back to the calm impact


@pytest.mark.parametrize(
    "wind",
    [[0.0, 51.0, 0.0], [-50.5, 0.0, 0.0], [1.0, 2.0], [1.0, 2.0, 3.0, 4.0], ["x", 0.0, 0.0]],
)
def test_bad_winds_are_bad_requests(robot: Callable[..., Client], wind: list) -> None:  # noqa: F811
    client = robot()
    with pytest.raises(RpcError) as info:
        client.archery("setWind", {"wind": wind})
    assert info.value.code == "bad_request"
    assert client.archery("status")["world"]["wind"] == [0.0, 0.0, 0.0]
