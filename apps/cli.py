"""The `archery` console script: one verb per service or tool, dispatched lazily."""

from __future__ import annotations

import contextlib
import importlib
import importlib.metadata
import logging
import os
import sys

from archery.apps.waits import interrupted_line
from archery.mesh.cliargs import ArgumentParser
from archery.mesh.logs import DEFAULT_SPEC, add_log_args, configure
from archery.protocol.errors import ConfigError
from archery.protocol.exit_status import BAD_INPUT, INTERRUPTED, OK

__all__ = ["VERBS", "main"]

# verb -> ("module:function", one-line help). Each function takes argv (list[str]) and returns
# the process exit status. Modules are imported only when their verb runs, so a tool never pays
# for MuJoCo or Pinocchio it does not use.
VERBS: dict[str, tuple[str, str]] = {
    "router": ("archery.mesh.router:main", "run a Zenoh router (the mesh's embedded default)"),
    "ports": (
        "archery.apps.topics.tools:ports_main",
        "list live services and their ports (yarp name list)",
    ),
    "alive": (
        "archery.apps.topics.tools:alive_main",
        "exit 0 when the router answers and the named services are alive (health checks)",
    ),
    "read": (
        "archery.apps.topics.tools:read_main",
        "print decoded messages from a key as JSON lines",
    ),
    "write": (
        "archery.apps.topics.tools:write_main",
        "publish one message, given as JSON, on a key",
    ),
    "rpc": ("archery.apps.topics.tools:rpc_main", "call an rpc:i verb and print the reply"),
    "interface": (
        "archery.apps.topics.interface:interface_main",
        "a port's message type; each rpc:i verb's argument and reply schema",
    ),
    "record": (
        "archery.apps.topics.observe:record_main",
        "record the robot's streams (or KEY_PATTERNs) into an MCAP file",
    ),
    "replay": (
        "archery.apps.topics.observe:replay_main",
        "publish an MCAP recording again, in time",
    ),
    "hz": (
        "archery.apps.topics.observe:hz_main",
        "message rate and bandwidth of the matching keys",
    ),
    "view": ("archery.apps.topics.tools:view_main", "save the next image on an image port as PNG"),
    "selfcheck": (
        "archery.apps.topics.selfcheck:main",
        "start a router and two nodes, check the mesh",
    ),
    "robot": (
        "archery.services.robot.service:main",
        "the simulated iCub: joint ports, bow, arrow, target",
    ),
    "camera": (
        "archery.services.camera.service:main",
        "camera frames of the target (rendered/device/folder)",
    ),
    "detector": (
        "archery.services.detector.service:main",
        "GMM colour detector: target centre, arrow tip",
    ),
    "calibrate": ("archery.apps.detect:calibrate_main", "fit the colour model from pixels"),
    "detect": ("archery.apps.detect:detect_main", "detect target and arrow in an image"),
    "controller": (
        "archery.services.controller.service:main",
        "Pinocchio IK: archery posture for θ",
    ),
    "learner": (
        "archery.services.learner.service:main",
        "learning sessions over the mesh (ARCHER, PoWER, baselines), journaled",
    ),
    "learn": (
        "archery.apps.learn.learn:main",
        "run one learning session against running services",
    ),
    "up": (
        "archery.apps.up.command:main",
        "start a router and all five services; stop them on Ctrl-C",
    ),
    "drill": (
        "archery.apps.drills.runner:main",
        "fault drills on a real mesh (kills, freezes, router outages, floods); their table",
    ),
    "experiment": (
        "archery.apps.experiment.experiment:main",
        "run the paper's simulation experiment (the ballistic world, or the robots of a fleet)",
    ),
    "compare": (
        "archery.apps.compare.compare:main",
        "ARCHER and PoWER against pycma and nevergrad through the Gymnasium environment",
    ),
    "report": (
        "archery.apps.report:main",
        "draw report.png beside session journals (a session's or an experiment's folder)",
    ),
    "film": (
        "archery.apps.film.film:main",
        "a video of a session's hit (or --rollout N), simulated again from its journal",
    ),
    "info": (
        "archery.apps.topics.info:main",
        "an MCAP recording's duration, channels, counts, rates, schemas and size",
    ),
    "foxglove": (
        "archery.apps.foxglove.command:main",
        "a live Foxglove WebSocket server: the robot in 3D, the camera, the learning curve",
    ),
    "ros2": (
        "archery.apps.ros2.command:main",
        "the robot on the ROS 2 graph through rmw_zenoh's wire format (joint states, TF, camera)",
    ),
    "yarp": (
        "archery.apps.yarp.command:main",
        "the robot as a YARP robot: control boards for remote_controlboard, camera, verbs",
    ),
    "export": (
        "archery.apps.ros2.export:main",
        "a recording as a ROS 2 bag (--ros2 OUT: MCAP, CDR) of the topics `archery ros2` sends",
    ),
    "dashboard": (
        "archery.apps.dashboard.server:main",
        "a live view in the browser: frame, target face, distances, liveliness, rates",
    ),
    "demo": ("archery.apps.demo:main", "start the mesh, learn until the 5 cm ring is hit, show it"),
    "demonstrate": (
        "archery.apps.demonstrate:main",
        "record a demonstration of the whole shot while the arms are driven, or check one",
    ),
    "imitate": (
        "archery.apps.imitate:main",
        "the whole shot from a demonstration's DMPs alone, drawn for θ, on a running robot",
    ),
    "keys": ("archery.apps.keys:main", "keys init DIR: CA, identities and ACL for --secure"),
}


def _usage() -> str:
    width = max(len(v) for v in VERBS)
    lines = [
        "usage: archery VERB [options]   (archery help VERB, or archery VERB --help, for a "
        "verb's options)",
        "       archery --version",
        "",
    ]
    lines += [f"  {verb.ljust(width)}  {help_}" for verb, (_, help_) in VERBS.items()]
    return "\n".join(lines)


def _version() -> str:
    try:
        return importlib.metadata.version("archery")
    except importlib.metadata.PackageNotFoundError:
        return "unknown (not installed)"


def _unknown(verb: str) -> int:
    print(f"archery: unknown verb {verb!r}; valid verbs: {', '.join(VERBS)}", file=sys.stderr)
    return 2


# The demo's own Zenoh sessions log nothing unless asked: while the services stop, Zenoh
# sometimes reports internal "Undefined face context" errors that mean nothing to a user;
# failures still surface as exceptions, and the services keep their logs.
_DEFAULT_SPECS = {"demo": f"{DEFAULT_SPEC},zenoh=off"}


def _configure_logging(verb: str, rest: list[str]) -> None:
    """Apply the verb's `--log-level` before it runs: every log line on stderr.

    Raises:
        ConfigError: a malformed spec.
    """
    parser = ArgumentParser(prog=f"archery {verb}", add_help=False, allow_abbrev=False)
    add_log_args(parser)
    parser.set_defaults(log_level=_DEFAULT_SPECS.get(verb, DEFAULT_SPEC))
    known, _ = parser.parse_known_args(rest)
    configure(known.log_level)


def _run(verb: str, rest: list[str]) -> int:
    module_name, func_name = VERBS[verb][0].split(":")
    func = getattr(importlib.import_module(module_name), func_name)
    return int(func(rest) or 0)


def _reader_gone() -> int:
    """The reader of stdout went away (see the Python docs' "Note on SIGPIPE"): send the rest
    of the output nowhere so that the final flush does not fail too, and end quietly (1)."""
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, sys.stdout.fileno())
    return 1


def main(argv: list[str] | None = None) -> int:
    """Run `archery VERB ...`; returns the verb's exit status.

    A closed stdout (`archery read KEY | head -1`) ends the verb quietly, as Unix tools do;
    Ctrl-C outside a verb's own handling (e.g. in a wait) ends it with status 130, one line
    on stderr and no traceback.
    """
    args = list(sys.argv[1:] if argv is None else argv)
    if not args:
        print("archery: give a verb (`archery --help` lists them)", file=sys.stderr)
        return BAD_INPUT
    if args[0] in ("-h", "--help", "-V", "--version") and len(args) > 1:
        print(f"archery: {args[0]} takes no arguments, got {' '.join(args[1:])!r}", file=sys.stderr)
        return BAD_INPUT
    if args[0] in ("-h", "--help"):
        print(_usage())
        return OK
    if args[0] in ("-V", "--version"):
        print(f"archery {_version()}")
        return OK
    verb, rest = args[0], args[1:]
    if verb == "help":
        if not rest:
            print(_usage())
            return 0
        if rest[0] not in VERBS:
            return _unknown(rest[0])
        verb, rest = rest[0], ["--help"]
    if verb not in VERBS:
        return _unknown(verb)
    try:
        _configure_logging(verb, rest)
    except ConfigError as exc:
        print(f"archery {verb}: {exc}", file=sys.stderr)
        return 2
    try:
        status = _run(verb, rest)
        sys.stdout.flush()
        return status
    except BrokenPipeError:
        return _reader_gone()
    except KeyboardInterrupt:
        print(interrupted_line(verb), file=sys.stderr, flush=True)
        return INTERRUPTED


def entry() -> None:
    """The `archery` command (and `python -m archery.apps.cli`): `main`, then leave with its status
    without the interpreter's teardown.

    Zenoh's threads may still hand the interpreter a callback or drop a reference while it
    tears itself down; on Python 3.11 such a thread then exits by unwinding through native
    frames that catch the unwind, and the process aborts (SIGABRT, "FATAL: exception not
    rethrown") after a clean stop. Every verb closes and flushes what it writes before it
    returns, so the process ends here: logging shut down, stdout and stderr flushed, `os._exit`.
    """
    try:
        status = main()
    except BrokenPipeError:  # `archery --help | head -1`
        status = _reader_gone()
    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(OSError, ValueError):  # a closed or broken pipe
            stream.flush()
    os._exit(status)


if __name__ == "__main__":
    entry()
