"""`viewer_main`: the start-up every program that follows the mesh for others shares (the
dashboard, the Foxglove server, the ROS 2 node, any later bridge), beside the services'
`archery.mesh.service.service_main`: the flags checked (bad input: one line, exit status 2),
the node opened on the router, the robot awaited and its status, scene and frames read (for a
bridge that shows the robot), the bridge started, one line once it serves, the run until Ctrl-C
or SIGTERM, the bridge closed (its last line on stderr) and `archery.protocol.exit_status`'s
status. Each bridge's own module then holds only its flags and its mapping.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol, TypeVar

from archery.apps.waits import announce
from archery.mesh.cliargs import ArgumentParser, seconds
from archery.mesh.netflags import NetConfig
from archery.mesh.node import Node, open_node
from archery.mesh.robot_client import RobotClient
from archery.mesh.signals import shutdown_on_signals, wait_for_stop
from archery.protocol.errors import ArcheryError
from archery.protocol.exit_status import BAD_INPUT, OK, for_error
from archery.protocol.robotspec import CALL_TIMEOUT
from archery.protocol.verbs import robot as rv

if TYPE_CHECKING:
    from archery.apps.topics.robot_frames import RobotFrames
    from archery.sim.scene_config import SceneConfig

__all__ = ["DEFAULT_WAIT", "View", "Viewer", "add_wait_arg", "viewer_main"]

C = TypeVar("C")

DEFAULT_WAIT = 30.0  # s: for the router (and the robot)


@dataclass(frozen=True)
class View:
    """What a bridge starts from: its parsed flags, its node (its identity's) and, when it shows
    the robot, the robot's archery status, its scene and the robot's frames on it."""

    args: argparse.Namespace
    node: Node
    status: rv.ArcheryStatusReply | None = None
    scene: SceneConfig | None = None
    frames: RobotFrames | None = None


class Viewer(Protocol):
    """A started bridge."""

    def ready(self) -> str:
        """The line printed on stdout (after `archery PROG: `) once it serves."""
        ...

    def close(self) -> str | None:
        """Stop it; its last line for stderr, or None."""
        ...


def add_wait_arg(parser: argparse.ArgumentParser, *, robot: bool = True) -> None:
    """`--wait S`: how long `viewer_main` waits for the router (and, with `robot`, the robot)."""
    parser.add_argument(
        "--wait",
        type=seconds,
        default=DEFAULT_WAIT,
        help=f"wait this long for the router{' and the robot' if robot else ''} "
        f"(s, default {DEFAULT_WAIT:g})",
    )


def viewer_main(
    argv: list[str] | None,
    *,
    prog: str,
    parser: ArgumentParser,
    check: Callable[[argparse.Namespace], tuple[NetConfig, C]],
    start: Callable[[View, C], Viewer],
    robot: bool = True,
    early: Callable[[argparse.Namespace], int | None] | None = None,
) -> int:
    """Run a bridge from the command line.

    `parser` holds the bridge's flags, the network flags and `--wait` (`add_wait_arg`);
    `check(args)` returns the node's settings and what else the bridge prepared from its flags
    (raising `ArcheryError` for bad values); `start(view, prepared)` starts the bridge on the
    opened node. With `robot`, the robot's services are awaited first and `view` carries its
    status, scene and frames. `early(args)`, when given, runs first: a verb of the bridge's that
    needs no mesh (its exit status), or None to go on.

    Returns:
        0 after a stop by a signal, 2 for bad flags, else `for_error` of the error met.
    """
    args = parser.parse_args(argv)
    if early is not None and (status := early(args)) is not None:
        return status
    try:
        net, prepared = check(args)
    except ArcheryError as exc:
        print(f"archery {prog}: {exc}", file=sys.stderr)
        return BAD_INPUT
    on_wait = announce(prog)
    stop = shutdown_on_signals()
    try:
        with open_node(net, args.wait, on_wait=on_wait) as node:
            view = _view(args, node, on_wait) if robot else View(args, node)
            viewer = start(view, prepared)
            try:
                print(f"archery {prog}: {viewer.ready()}", flush=True)
                wait_for_stop(stop)
            finally:
                last = viewer.close()
                if last:
                    print(f"archery {prog}: {last}", file=sys.stderr)
    except ArcheryError as exc:
        print(f"archery {prog}: {exc}", file=sys.stderr)
        return for_error(exc.code)
    return OK


def _view(args: argparse.Namespace, node: Node, on_wait: Callable[[str, float], None]) -> View:
    """The robot awaited, its status read, its scene and frames built."""
    from archery.apps.topics.robot_frames import RobotFrames
    from archery.sim.scene_config import SceneConfig

    node.wait_alive(["robot"], timeout=args.wait, on_wait=on_wait)
    status = RobotClient(node, timeout=CALL_TIMEOUT).status()
    scene = SceneConfig.of(status.scene)
    return View(args, node, status, scene, RobotFrames(node.keys.robot, scene))
