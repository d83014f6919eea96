"""`archery up`, the command: its flags, the mesh they describe, the optional recorder, Foxglove
server and ROS 2 node, and the truthful last line and exit status once everything stopped.

While it starts, stdout says what it starts and stderr, as each wait begins, what it waits for
and its limit (`apps.waits`): the router to listen (`launcher.ROUTER_START` s), then the services
to be alive (`--timeout` s), e.g. `archery up: waiting up to 90 s for the services: robot,
camera, detector, controller, learner (Ctrl-C to stop)`.

The processes themselves are started, watched and stopped by `apps.up.launcher.Launcher` and
supervised by `apps.up.supervisor.Supervisor`; see `apps.up.launcher` for what `up` runs. The
YARP bridge (`--yarp`) is supervised too: a crash inside YARP's library is a restart, reported.
"""

from __future__ import annotations

import argparse
import shlex
import subprocess
import sys
import time
from pathlib import Path

from archery.apps.capacity import check_robots
from archery.apps.up.child import spawn
from archery.apps.up.launch_config import MeshConfig, default_mesh, load_mesh
from archery.apps.up.launcher import Launcher, LaunchError, Observer, StartInterrupted
from archery.apps.up.restart_policy import POLICIES, RestartPolicy, describe_status
from archery.apps.up.supervisor import GiveUp, Supervisor
from archery.apps.waits import announce
from archery.mesh.cliargs import (
    ArgumentParser,
    add_force_arg,
    check_output_file,
    check_writable_dir,
    count,
    nonnegative,
    seconds,
)
from archery.mesh.configflags import add_config_args, config_from_args
from archery.mesh.netflags import DEFAULT_ROUTER, DEFAULT_SECURE_ROUTER, NetConfig, add_network_args
from archery.mesh.signals import shutdown_on_signals
from archery.protocol.errors import ConfigError
from archery.protocol.exit_status import INTERRUPTED
from archery.protocol.keys import DEFAULT_ROBOT
from archery.services.robot.config import RobotConfig

__all__ = ["build_parser", "main", "mesh_from_args", "start_observer", "start_recorder"]

DESCRIPTION = "a router and all five services as supervised child processes of one command"


def build_parser() -> argparse.ArgumentParser:
    """The flags of `archery up`."""
    parser = ArgumentParser(prog="archery up", description=DESCRIPTION)
    add_network_args(parser)
    parser.set_defaults(robot=None)  # None: not given (the default mesh's, or --config's)
    parser.add_argument(
        "--config",
        metavar="FILE",
        help="the mesh to start, a TOML launch description (see mesh.toml); replaces "
        "--listen/--connect/--robot/--seed/--rtf/--shot/--runs/--no-router",
    )
    parser.add_argument(
        "--robots",
        type=count,
        metavar="N",
        help="a fleet of N robot stacks (robot, controller, camera, detector) under the prefixes "
        "ROBOT1 … ROBOTN and one learner that runs sessions on all of them (default 1: one "
        "robot under ROBOT itself)",
    )
    parser.add_argument(
        "--allow-overload",
        action="store_true",
        help="start more robot stacks than this machine holds (its maximum comes from the "
        "available memory and the cores: `apps.capacity`)",
    )
    parser.add_argument("--logs", default="runs/logs", help="directory of the children's logs")
    parser.add_argument("--runs", help="the learner's session directory (default runs)")
    parser.add_argument("--seed", type=count, help="the robot's shot-noise seed (default 0)")
    parser.add_argument(
        "--rtf",
        type=nonnegative,
        help="the robot's real-time factor (default 0: as fast as possible)",
    )
    parser.add_argument(
        "--shot",
        choices=("posture", "whole"),
        help="the robot's shot (default posture: the arrow is placed on the string; whole: "
        "every rollout grasps, nocks and draws it, the demonstration's movement as DMPs; needs "
        "the imitate extra)",
    )
    parser.add_argument(
        "--body",
        choices=("mujoco", "yarp"),
        help="the robot's body (default mujoco: the simulated iCub; yarp: a YARP robot's "
        "control boards, --remote, as `archery robot --body yarp`)",
    )
    parser.add_argument(
        "--remote",
        metavar="NAME",
        help="with --body yarp, the YARP robot's name, e.g. /icubSim (its boards NAME/PART)",
    )
    parser.add_argument(
        "--archery-rpc",
        metavar="PORT",
        help="with --body yarp, the robot's own archery RPC port (e.g. /icubSim/archery/rpc:i): "
        "its status, reset, nock, release and grasp answers (none: refused)",
    )
    for flag, metavar, what in _SHOT_FLAGS:
        parser.add_argument(flag, metavar=metavar, help=f"with --body yarp, {what}")
    parser.add_argument(
        "--no-router",
        action="store_true",
        help="start no router: the services connect to the --connect endpoint",
    )
    parser.add_argument(
        "--restart",
        choices=POLICIES,
        help="restart policy of every child (default on-failure: a non-zero exit status or a "
        "signal; exit status 2, a bad configuration, always stops everything)",
    )
    parser.add_argument(
        "--restart-budget",
        type=count,
        metavar="N",
        help="restarts allowed per child within 60 s; one more stops everything (default 5)",
    )
    parser.add_argument(
        "--timeout", type=seconds, default=90.0, help="wait this long for all services (s)"
    )
    parser.add_argument(
        "--record",
        metavar="FILE.mcap",
        help="record the whole run (every stream of the robot) into this MCAP file",
    )
    add_force_arg(parser, "an existing --record file")
    parser.add_argument(
        "--foxglove",
        metavar="PORT",
        type=int,
        nargs="?",
        const=8765,
        help="serve the first robot live to the Foxglove app on 127.0.0.1:PORT (default 8765; "
        "read-only, see `archery foxglove`)",
    )
    parser.add_argument(
        "--ros2",
        metavar="DOMAIN",
        type=int,
        nargs="?",
        const=0,
        help="put the first robot on the ROS 2 graph of DOMAIN (default 0) through the mesh's "
        "router (read-only, see `archery ros2`)",
    )
    parser.add_argument(
        "--yarp",
        metavar="HOST:PORT",
        nargs="?",
        const="",
        help="serve the first robot as a YARP robot (read-only, see `archery yarp`), registered "
        "with the YARP name server HOST:PORT (default: the configured one, else its own)",
    )
    return parser


def start_recorder(launcher: Launcher, out: str, timeout: float = 30.0) -> subprocess.Popen[bytes]:
    """An `archery record` child writing every stream of the first robot to `out` (checked,
    and replaced if it exists: `archery up --force`), its log `LOGS/recorder.log`, started once
    it subscribes.

    Raises:
        LaunchError: it exited or did not subscribe within `timeout` s.
    """
    argv = ["record", "--out", out, "--force"]
    return start_observer(launcher, "recorder", argv, b"archery record: recording", timeout)


def start_observer(
    launcher: Launcher,
    name: str,
    argv: list[str],
    ready: bytes,
    timeout: float = 30.0,
    *,
    restart: RestartPolicy | None = None,
) -> subprocess.Popen[bytes]:
    """An `archery ARGV…` child that follows the first robot (the recorder, the Foxglove
    server), its log `LOGS/NAME.log` rotated and bounded like the others', returned once its
    log holds `ready`; with `restart`, a child the launcher supervises under that policy.

    Raises:
        LaunchError: it exited or did not get ready within `timeout` s.
    """
    connect = ["--connect", launcher.endpoint, "--robot", launcher.net.robot]
    full = [sys.executable, "-m", "archery.apps.cli", *argv, *connect, *launcher.secure]
    output = launcher.output(name)
    if restart is not None:
        child = launcher.observe(name, Observer(tuple(full), ready, restart))
    else:
        output.close()
        for path in output.paths:  # this run's words only
            path.unlink(missing_ok=True)
        child = spawn(name, full, output, launcher.env)
    assert child.proc is not None
    deadline = time.monotonic() + timeout
    while ready not in _read(output.path):
        if child.returncode is not None or time.monotonic() > deadline:
            child.proc.kill()
            child.proc.wait()
            tail = child.tail().splitlines()[-1:]
            raise LaunchError(f"the {name} did not start: {' '.join(tail) or 'no output'}")
        time.sleep(0.05)
    return child.proc


def _read(path: Path) -> bytes:
    """The bytes of a log file (b"" while it does not exist)."""
    try:
        return path.read_bytes()
    except FileNotFoundError:
        return b""


def mesh_from_args(args: argparse.Namespace) -> MeshConfig:
    """The mesh `up` starts: --config's, or the default built from the flags.

    Raises:
        ConfigError: a bad file, or --config together with a flag it replaces.
    """
    if args.config is not None:
        given = {
            "--listen": args.listen,
            "--connect": args.connect,
            "--robot": args.robot,
            "--seed": args.seed,
            "--rtf": args.rtf,
            "--shot": args.shot,
            "--runs": args.runs,
            "--no-router": args.no_router or None,
            "--robots": args.robots,
            "--body": args.body,
            "--remote": args.remote,
            "--archery-rpc": args.archery_rpc,
            **{flag: _shot_flag(args, flag) for flag, _, _ in _SHOT_FLAGS},
        }
        clash = [flag for flag, value in given.items() if value is not None]
        if clash:
            raise ConfigError(f"{clash[0]} and --config: set it in {args.config} instead")
        mesh = load_mesh(Path(args.config))
    else:
        default = DEFAULT_SECURE_ROUTER if args.secure else DEFAULT_ROUTER
        chosen = args.connect if args.no_router else args.listen
        runs = args.runs or "runs"
        check_writable_dir(Path(runs), "--runs", create=True)
        mesh = default_mesh(
            (chosen or [default])[0],
            NetConfig(robot=args.robot or DEFAULT_ROBOT).robot,
            seed=args.seed or 0,
            rtf=args.rtf or 0.0,
            shot=args.shot or "posture",
            runs=runs,
            start_router=not args.no_router,
            robots=1 if args.robots is None else args.robots,
            body=_body(args),
        )
    return mesh.with_policy(args.restart, args.restart_budget)


def _body(args: argparse.Namespace) -> tuple[str, ...]:
    """The robot's body flags (`--body yarp --remote NAME [--archery-rpc PORT]`; () for the
    simulated iCub), checked as the robot checks them.

    Raises:
        ConfigError: --remote or --archery-rpc without --body yarp, --body yarp without
            --remote, a flag of the simulated robot's (--seed, --rtf, --shot) with it, or a
            name that is not a YARP name.
    """
    shot = {flag: _shot_flag(args, flag) for flag, _, _ in _SHOT_FLAGS}
    if args.body != "yarp":
        given = {"--remote": args.remote, "--archery-rpc": args.archery_rpc, **shot}
        for flag, value in given.items():
            if value is not None:
                raise ConfigError(f"{flag} goes with --body yarp")
        return ()
    if args.remote is None:
        raise ConfigError("--body yarp needs --remote NAME, the YARP robot's name, e.g. /icubSim")
    for flag, value in (("--seed", args.seed), ("--rtf", args.rtf), ("--shot", args.shot)):
        if value is not None:
            raise ConfigError(f"{flag} is the simulated robot's: a YARP body has none")
    body: tuple[str, ...] = ("--body", "yarp", "--remote", args.remote)
    if args.archery_rpc is not None:
        body += ("--archery-rpc", args.archery_rpc)
    for flag, value in shot.items():
        if value is not None:
            body += (flag, value)
    robot_parser = argparse.ArgumentParser(prog="archery robot", exit_on_error=False)
    add_config_args(robot_parser, RobotConfig)
    try:  # checked as the robot checks them, before anything starts
        parsed = robot_parser.parse_args(list(body))
        config_from_args(RobotConfig, parsed, net=NetConfig())
    except (argparse.ArgumentError, SystemExit) as exc:
        raise ConfigError(f"the robot's flags {' '.join(body)}: {exc}") from None
    return body


#: the YARP body's shot flags `archery up` passes on to the robot (`archery robot --help`)
_SHOT_FLAGS = (
    ("--landing", "events|camera", "who tells the landing (as `archery robot`)"),
    ("--release-joint", "AXIS", "the finger axis the release opens (as `archery robot`)"),
    ("--release-open", "DEG", "the angle the release finger opens to (as `archery robot`)"),
    ("--hand-postures", "FILE", "the hand postures of grasp, nock, reset (as `archery robot`)"),
)


def _shot_flag(args: argparse.Namespace, flag: str) -> str | None:
    value: str | None = getattr(args, flag.lstrip("-").replace("-", "_"))
    return value


def _final(launcher: Launcher, supervisor: Supervisor, outcome: GiveUp | None) -> int:
    """Stop everything; print the truthful last line; the exit status."""
    if outcome is not None:
        tail = outcome.child.tail().replace("\n", "\n  | ")
        print(f"archery up: the end of {outcome.child.log}:\n  | {tail}", file=sys.stderr)
    running = {n for n, c in launcher.children.items() if c.returncode is None}
    print("archery up: stopping …", flush=True)
    codes = launcher.stop_all()
    unclean = {n: c for n, c in codes.items() if n in running and c != 0}
    if unclean:
        listed = ", ".join(f"{n} ({describe_status(c)})" for n, c in unclean.items() if c)
        print(f"archery up: did not stop cleanly: {listed}", file=sys.stderr)
    if outcome is not None:
        print(f"archery up: stopped everything: {outcome.line()}", file=sys.stderr)
        return 1
    if unclean:
        return 1
    notes = []
    if supervisor.restarts:
        counts = ", ".join(f"{n} {len(t)}" for n, t in supervisor.restarts.items() if t)
        notes.append(f"restarts: {counts}" if counts else "")
    if supervisor.left:
        notes.append(f"left down before: {', '.join(supervisor.left)}")
    notes = [n for n in notes if n]
    print(f"archery up: all stopped cleanly{' (' + '; '.join(notes) + ')' if notes else ''}")
    return 0


def main(argv: list[str] | None = None) -> int:
    """Run `archery up` until Ctrl-C/SIGTERM (exit 0) or until a child's restart policy gives
    up (its budget is spent, or it exited with status 2: exit 1). Bad flags or a bad
    --config file: exit 2."""
    args = build_parser().parse_args(argv)
    try:
        mesh = mesh_from_args(args)
        check_robots(len(mesh.robots), args.allow_overload)
        check_writable_dir(Path(args.logs), "--logs", create=True)
        if args.record is not None:
            check_output_file(args.record, "--record", (".mcap",), force=args.force)
        if args.foxglove is not None and not 0 <= args.foxglove <= 65535:
            raise ConfigError(f"--foxglove {args.foxglove}: give a port number from 0 to 65535")
        if args.ros2 is not None and not 0 <= args.ros2 <= 232:
            raise ConfigError(f"--ros2 {args.ros2}: give a ROS 2 domain id from 0 to 232")
        if mesh.router.start:  # the router's listen endpoint, checked before anything starts
            NetConfig(
                connect=(),
                listen=(mesh.router.endpoint,),
                mode="router",
                secure=args.secure,
                insecure_network=args.insecure_network,
            )
        launcher = Launcher(
            logs=Path(args.logs),
            secure=args.secure,
            mesh=mesh,
            insecure_network=args.insecure_network,
        )
        stop = shutdown_on_signals()
        where = f"a router on {launcher.endpoint}" if launcher.with_router else "no router"
        print(f"archery up: starting {where} and {', '.join(launcher.specs)} …", flush=True)
        took = launcher.up(args.timeout, stop=stop, on_wait=announce("up"))
        observers: list[tuple[str, subprocess.Popen[bytes]]] = []
        try:
            if args.record is not None:
                observers.append(("the recorder", start_recorder(launcher, args.record)))
                print(f"archery up: recording to {args.record}", flush=True)
            if args.foxglove is not None:
                argv = ["foxglove", "--port", str(args.foxglove)]
                ready = b"archery foxglove: serving"
                observers.append(
                    ("the Foxglove server", start_observer(launcher, "foxglove", argv, ready))
                )
                where = f"ws://127.0.0.1:{args.foxglove}"
                print(f"archery up: serving Foxglove on {where}", flush=True)
            if args.ros2 is not None:
                argv = ["ros2", "--domain", str(args.ros2)]
                ready = b"archery ros2: on the ROS 2 graph"
                observers.append(("the ROS 2 node", start_observer(launcher, "ros2", argv, ready)))
                print(f"archery up: on the ROS 2 graph (domain {args.ros2})", flush=True)
            if args.yarp is not None:
                argv = ["yarp", *(["--yarp-server", args.yarp] if args.yarp else [])]
                ready = b"archery yarp: on YARP"
                given = (("mode", args.restart), ("budget", args.restart_budget))
                policy = RestartPolicy(**{k: v for k, v in given if v is not None})
                start_observer(launcher, "yarp", argv, ready, restart=policy)
                said = _read(launcher.output("yarp").path).decode(errors="replace")
                line = next(x for x in said.splitlines() if x.startswith("archery yarp: on YARP"))
                print(f"archery up: {line.removeprefix('archery yarp: ')}", flush=True)
        except LaunchError:
            for _, observer in observers:
                observer.terminate()
                observer.wait(60)
            launcher.stop_all()
            raise
    except StartInterrupted as exc:
        print(f"archery up: {exc}", file=sys.stderr)
        return INTERRUPTED
    except (ConfigError, LaunchError) as exc:
        print(f"archery up: {exc}", file=sys.stderr)
        return 2 if isinstance(exc, ConfigError) else 1
    robots = ", ".join(repr(r.prefix) for r in mesh.robots)
    learn = f"archery learn {shlex.join(launcher.secure)}{' ' if launcher.secure else ''}"
    learn += f"--connect {launcher.endpoint}"
    if len(mesh.robots) > 1:
        learn += f" --robot {mesh.robots[0].prefix}` (any robot) or `archery experiment "
        learn += f"--world mesh --connect {launcher.endpoint}"
    print(
        f"archery up: all alive in {took:.1f} s (robot {robots}, logs in {launcher.logs}/). "
        f"Run `{learn}` in another shell; Ctrl-C stops everything.",
        flush=True,
    )

    def report(line: str) -> None:
        print(f"archery up: {line}", file=sys.stderr, flush=True)

    launcher.on_ready = lambda name, line: report(f"{name} is back: {line.split(': ', 1)[-1]}")
    supervisor = Supervisor(launcher, report=report)
    outcome = supervisor.run(stop)
    for name, observer in observers:
        observer.terminate()
        if observer.wait(60) != 0:
            print(f"archery up: {name} ended with status {observer.returncode}", file=sys.stderr)
    return _final(launcher, supervisor, outcome)
