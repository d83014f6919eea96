"""A camera service on a thread and a node that publishes the world states it renders: the set-up
of the camera's tests."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

from archery.mesh.node import Node
from archery.mesh.publisher import Publisher
from archery.protocol.messages import WorldState
from archery.services.camera.config import CameraConfig
from archery.services.camera.service import run
from tests.conftest import serving


@contextmanager
def camera_with_world(
    config: CameraConfig, first: WorldState
) -> Iterator[tuple[Node, Publisher[WorldState]]]:
    """The camera of `config` serving, a node on its network that sees it alive, and that node's
    world-state publisher, matched by the camera and with `first` published."""
    with serving(run, config), Node(None, config.net) as node:
        node.wait_alive(["camera"], timeout=30)
        world = node.publisher(node.keys.world_state(), WorldState)
        assert world.wait_matched(5)
        world.put(first)
        yield node, world
