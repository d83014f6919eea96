"""Key names: built from YARP port names, validated, and mapped back to their port."""

from __future__ import annotations

import contextlib

import pytest
from hypothesis import given
from hypothesis import strategies as st

from archery.protocol.errors import KeyNameError
from archery.protocol.keys import PORTS, Keys, port_of, validate_robot
from archery.protocol.parts import PARTS


def test_keys_follow_yarp_names() -> None:
    keys = Keys()
    assert keys.state("left_arm") == "icubSim/left_arm/state:o"
    assert keys.command("torso") == "icubSim/torso/command:i"
    assert keys.cartesian_rpc("left_arm") == "icubSim/cartesianController/left_arm/rpc:i"
    assert keys.cam_frames() == "icubSim/cam/target:o"
    assert Keys("icub2").archery_rpc() == "icub2/archery/rpc:i"


def test_every_built_key_maps_back_to_its_port() -> None:
    keys = Keys("r1")
    built = [keys.state(p) for p in PARTS] + [keys.command(p) for p in PARTS]
    built += [keys.part_rpc(p) for p in PARTS] + [keys.cartesian_rpc("archery")]
    built += [
        keys.archery_rpc(),
        keys.world_state(),
        keys.world_events(),
        keys.cam_frames(),
        keys.cam_rpc(),
        keys.detector_hits(),
        keys.detector_rpc(),
        keys.learner_rollouts(),
        keys.learner_rpc(),
        keys.alive("robot"),
        keys.describe("camera"),
    ]
    for key in built:
        spec = port_of(key)
        assert spec in PORTS
    assert port_of(keys.state("torso")).message == "JointState"
    assert port_of(keys.world_events()).kind == "events"


@pytest.mark.parametrize(
    "key",
    ["icubSim/left_leg/state:o", "icubSim/left_arm/state", "/icubSim/torso/state:o", "torso/x:o"],
)
def test_unknown_keys_are_rejected_with_the_valid_patterns(key: str) -> None:
    with pytest.raises(KeyNameError, match="valid keys"):
        port_of(key)


def test_bad_parts_and_robots_name_the_valid_options() -> None:
    with pytest.raises(KeyNameError, match="valid parts: torso, left_arm, right_arm"):
        Keys().state("left_leg")
    with pytest.raises(KeyNameError, match="valid: left_arm, right_arm, archery"):
        Keys().cartesian_rpc("head")
    for bad in ["", "1robot", "a/b", "a*", "x" * 65, "with space"]:
        with pytest.raises(KeyNameError, match="invalid robot name"):
            validate_robot(bad)


@given(st.text(max_size=80))
def test_port_of_never_crashes(key: str) -> None:
    with contextlib.suppress(KeyNameError):
        port_of(key)
