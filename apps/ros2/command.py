"""`archery ros2`: its flags, their checks (a domain outside 0…232 is bad input, exit 2) and the
node started on the robot (`viewer_main`: the run until Ctrl-C or SIGTERM); at the end, one line
of what the node sent, dropped and refused."""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING

from archery.apps.viewer import View, add_wait_arg, viewer_main
from archery.mesh.cliargs import ArgumentParser
from archery.mesh.netflags import NetConfig, add_network_args
from archery.protocol.errors import ConfigError

if TYPE_CHECKING:
    from archery.apps.ros2.graph import Ros2Node

__all__ = ["READY", "build_parser", "main"]

READY = "archery ros2: on the ROS 2 graph"  # the line `archery up --ros2` waits for


def build_parser() -> ArgumentParser:
    """The flags of `archery ros2`."""
    parser = ArgumentParser(
        prog="archery ros2",
        description="the robot on the ROS 2 graph, on the mesh's own router (rmw_zenoh's wire "
        "format: RMW_IMPLEMENTATION=rmw_zenoh_cpp sees it): joint states, /tf, the robot "
        "description, the camera, rollouts and landings; with --operator the parts' commands "
        "and the reset, nock and release services",
    )
    add_network_args(parser, default_mode="client")
    parser.add_argument(
        "--domain", type=int, default=0, help="the ROS 2 domain id, 0 to 232 (default 0)"
    )
    parser.add_argument("--namespace", help="the node's namespace (default /ROBOT, e.g. /icubSim)")
    parser.add_argument(
        "--operator",
        action="store_true",
        help="take the parts' commands and trajectories (one waiting per part, at the robot's "
        "command rate; a trajectory is played at its points' times, what comes for its part "
        "meanwhile waits for its end) and serve reset, nock and release as "
        "std_srvs/srv/Trigger; without it the node declares no command subscription and "
        "answers each service call success: false",
    )
    add_wait_arg(parser)
    return parser


def _check(args: argparse.Namespace) -> tuple[NetConfig, str]:
    from archery.apps.ros2.wire import MAX_DOMAIN, check_name
    from archery.mesh.acl import ROS2, ROS2_OPERATOR

    if not 0 <= args.domain <= MAX_DOMAIN:
        raise ConfigError(f"--domain {args.domain}: give a ROS 2 domain id from 0 to {MAX_DOMAIN}")
    net = NetConfig.from_args(args).with_identity(ROS2_OPERATOR if args.operator else ROS2)
    try:
        namespace = check_name(args.namespace or f"/{net.robot}", "--namespace")
    except ValueError as exc:
        raise ConfigError(str(exc)) from None
    if net.secure and namespace != f"/{net.robot}":
        raise ConfigError(
            f"--namespace {namespace} with --secure: the access control grants the ROS 2 keys "
            f"of /{net.robot} only"
        )
    return net, namespace


def main(argv: list[str] | None = None) -> int:
    """`archery ros2`: keep the robot on the ROS 2 graph until Ctrl-C or SIGTERM."""
    return viewer_main(argv, prog="ros2", parser=build_parser(), check=_check, start=_start)


class _OnTheGraph:
    """The node on the graph, as `viewer_main` runs it."""

    def __init__(self, ros: Ros2Node, view: View, namespace: str) -> None:
        self.ros = ros
        self.view = view
        self.namespace = namespace

    def ready(self) -> str:
        from archery.apps.ros2.graph import NODE_NAME

        args, net = self.view.args, self.view.node.net
        mode = "operator" if args.operator else "read-only"
        return (
            f"{READY.removeprefix('archery ros2: ')} as {self.namespace.rstrip('/')}/{NODE_NAME} "
            f"(domain {args.domain}, {mode}) through "
            f"{net.connect[0] if net.connect else 'the default router'}"
        )

    def close(self) -> str:
        self.ros.close()
        counts = ", ".join(f"{k} {v}" for k, v in sorted(self.ros.counts.snapshot().items()))
        return f"stopped ({counts or 'nothing sent'})"


def _start(view: View, namespace: str) -> _OnTheGraph:
    from archery.apps.ros2.graph import Ros2Node
    from archery.sim.urdf import urdf_text

    assert view.status is not None and view.scene is not None and view.frames is not None
    args = view.args
    ros = Ros2Node(
        view.node,
        view.frames,
        urdf_text(),
        view.scene.camera_fovy,
        domain=args.domain,
        namespace=namespace,
        operator=args.operator,
        rtf=view.status.rtf,
    )
    return _OnTheGraph(ros, view, namespace)
