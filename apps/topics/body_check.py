"""`archery selfcheck --body yarp`: the check a lab runs on a YARP robot before any motion.

It opens each part's control board (`services/robot/yarp_parts.py`), prints the axes found and
mapped onto the contract's joints, the limits used (degrees) and where they came from, and the
encoders now; it commands nothing. Exit 0 when all is well, else 2 with one line naming what
is wrong (a name server that does not answer, a part or an axis missing, an encoder refused),
the last of stderr (YARP's own log lines come before it).
"""

from __future__ import annotations

import argparse
import ipaddress
import math
import socket
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

from archery.protocol.errors import ConfigError

if TYPE_CHECKING:
    from archery.apps.yarp.network import NameServer
    from archery.services.robot.yarp_parts import YarpBody

__all__ = ["BodyPlan", "add_body_args", "check_body_flags", "run_body_check"]


def add_body_args(parser: argparse.ArgumentParser) -> None:
    """The flags of the body check (`--body yarp`)."""
    parser.add_argument(
        "--body",
        choices=("mesh", "yarp"),
        default="mesh",
        help="what to check: the mesh end to end (default), or a YARP robot's body before any "
        "motion (reads its control boards, moves nothing)",
    )
    parser.add_argument(
        "--remote", default="/icub", help="the YARP robot's name (--body yarp; default /icub)"
    )
    parser.add_argument(
        "--yarp-server",
        metavar="HOST:PORT",
        help="the robot's YARP name server (--body yarp; default: the one `yarp conf` names)",
    )
    parser.add_argument(
        "--yarp-ip",
        help="the address this machine's YARP ports listen on (--body yarp; default: the one "
        "it reaches the name server by)",
    )


@dataclass(frozen=True)
class BodyPlan:
    """What the flags of `--body yarp` ask for, checked."""

    remote: str
    server: NameServer
    ip: str


def check_body_flags(args: argparse.Namespace) -> BodyPlan:
    """The body check's flags, checked before any work.

    Raises:
        ConfigError: a flag of the mesh's check given with `--body yarp`, a `--remote` that is
            not a YARP name, a bad `--yarp-server` or `--yarp-ip`, or no name server named.
    """
    from archery.apps.yarp.network import parse_server, user_server

    if args.echo or args.connect:
        raise ConfigError("--echo and --connect are the mesh's check: not with --body yarp")
    remote = args.remote
    if not (remote.startswith("/") and not remote.endswith("/") and remote.isprintable()) or any(
        c.isspace() for c in remote
    ):
        raise ConfigError(f"--remote {remote!r}: give the robot's YARP name, e.g. /icub")
    server = parse_server(args.yarp_server) if args.yarp_server else user_server()
    if server is None:
        raise ConfigError(
            "no YARP name server: give --yarp-server HOST:PORT, or name one with `yarp conf`"
        )
    if args.yarp_ip is not None:
        try:
            ipaddress.ip_address(args.yarp_ip)
        except ValueError:
            raise ConfigError(
                f"--yarp-ip {args.yarp_ip!r}: give an address, e.g. 127.0.0.1"
            ) from None
    return BodyPlan(remote, server, args.yarp_ip or _route_ip(server))


def _route_ip(server: NameServer) -> str:
    """This machine's address on the way to `server` (nothing is sent), 127.0.0.1 if none."""
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
            probe.connect((server.host, server.port))
            return str(probe.getsockname()[0])
    except OSError:
        return "127.0.0.1"


def _listens(server: NameServer, timeout: float) -> None:
    """Return once something accepts a connection at `server`.

    Raises:
        ConfigError: nothing does within `timeout` (s).
    """
    try:
        with socket.create_connection((server.host, server.port), timeout=timeout):
            return
    except OSError as exc:
        reason = exc.strerror or type(exc).__name__
        raise ConfigError(f"no YARP name server answers at {server}: {reason.lower()}") from None


def run_body_check(plan: BodyPlan, timeout: float) -> None:
    """Open the robot's parts, print what was found and the encoders now, close; moves nothing.

    Args:
        plan: the checked flags.
        timeout: s for the name server to answer, and for each part's first encoder reading.

    Raises:
        ArcheryError: what is wrong, in one line (`yarp_parts.BodyError` and YARP's set-up).
    """
    from archery.apps.yarp.network import NotANameServer, YarpNetwork, user_key
    from archery.services.robot.yarp_parts import open_parts

    _listens(plan.server, timeout)
    key = user_key()  # a secure robot's YARP (AuthHMAC) lets in only a YARP with its key
    network = YarpNetwork(plan.ip, plan.server, key)
    try:
        try:
            network.start(time.monotonic() + timeout)
        except NotANameServer as exc:
            if key is not None:
                raise
            raise ConfigError(
                f"{exc} (a YARP that authenticates its connections, AuthHMAC, answers only a "
                "YARP with its key: auth.conf in the working folder or YARP's configuration "
                "folder)"
            ) from None
        with open_parts(plan.remote, timeout=timeout) as body:
            now = body.encoders()
            _show(body, now, plan)
    finally:
        network.close()


def _show(body: YarpBody, now: dict[str, tuple[float, ...]], plan: BodyPlan) -> None:
    print(f"YARP body check of {body.remote} (name server {plan.server}): reads, moves nothing")
    for part, axes in body.parts.items():
        where = "the robot's within the project's" if axes.from_robot else "the project's"
        if not axes.from_robot:
            where += " (the robot's getLimits fails)"
        print(
            f"{part} {axes.board}: {len(axes.axes)} axes, {len(axes.joints)} mapped by name; "
            f"limits: {where}"
        )
        for joint, axis, lower, upper, value in zip(
            axes.joints, axes.index, axes.lower, axes.upper, now[part], strict=True
        ):
            print(
                f"  {joint:<18} axis {axis:>2}  limits [{math.degrees(lower):7.1f}, "
                f"{math.degrees(upper):7.1f}]°  now {math.degrees(value):7.1f}°"
            )
        if axes.unmapped:
            print(f"  not mapped: {', '.join(axes.unmapped)}")
    joints = sum(len(axes.joints) for axes in body.parts.values())
    print(f"ok: {len(body.parts)} parts, {joints} joints within their limits; nothing moved")
