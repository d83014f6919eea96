"""`archery ros2`: its flags, their checks (a domain outside 0…232 is bad input, exit 2) and the
run until Ctrl-C or SIGTERM; at the end, one line of what the node sent, dropped and refused."""

from __future__ import annotations

import argparse
import sys

from apps.waits import announce
from mesh.cliargs import ArgumentParser, seconds
from mesh.netflags import NetConfig, add_network_args
from protocol.errors import ArcheryError, ConfigError
from protocol.exit_status import BAD_INPUT, FAILURE, OK

__all__ = ["READY", "build_parser", "main"]

DEFAULT_WAIT = 30.0  # s: for the router and the robot
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
    parser.add_argument(
        "--wait",
        type=seconds,
        default=DEFAULT_WAIT,
        help=f"wait this long for the router and the robot (s, default {DEFAULT_WAIT:g})",
    )
    return parser


def _check(args: argparse.Namespace) -> tuple[NetConfig, str]:
    from apps.ros2.wire import MAX_DOMAIN, check_name
    from mesh.acl import ROS2, ROS2_OPERATOR

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
    args = build_parser().parse_args(argv)
    try:
        net, namespace = _check(args)
    except ArcheryError as exc:
        print(f"archery ros2: {exc}", file=sys.stderr)
        return BAD_INPUT
    try:
        return _serve(args, net, namespace)
    except ArcheryError as exc:
        print(f"archery ros2: {exc}", file=sys.stderr)
        return FAILURE


def _serve(args: argparse.Namespace, net: NetConfig, namespace: str) -> int:
    from apps.ros2.graph import NODE_NAME, Ros2Node
    from apps.topics.robot_frames import RobotFrames, urdf_text
    from mesh.node import open_node
    from mesh.signals import shutdown_on_signals
    from protocol.verbs.robot import ARCHERY_STATUS
    from sim.scene_config import SceneConfig

    on_wait = announce("ros2")
    stop = shutdown_on_signals()
    with open_node(net, args.wait, on_wait=on_wait) as node:
        node.wait_alive(["robot"], timeout=args.wait, on_wait=on_wait)
        status = node.call_typed(node.keys.archery_rpc(), ARCHERY_STATUS)
        scene = SceneConfig.of(status.scene)
        frames = RobotFrames(node.keys.robot, scene)
        ros = Ros2Node(
            node,
            frames,
            urdf_text(),
            scene.camera_fovy,
            domain=args.domain,
            namespace=namespace,
            operator=args.operator,
            rtf=status.rtf,
        )
        try:
            mode = "operator" if args.operator else "read-only"
            print(
                f"{READY} as {namespace.rstrip('/')}/{NODE_NAME} (domain {args.domain}, {mode}) "
                f"through {net.connect[0] if net.connect else 'the default router'}",
                flush=True,
            )
            stop.wait()
        finally:
            ros.close()
            counts = ", ".join(f"{k} {v}" for k, v in sorted(ros.counts.snapshot().items()))
            print(f"archery ros2: stopped ({counts or 'nothing sent'})", file=sys.stderr)
    return OK
