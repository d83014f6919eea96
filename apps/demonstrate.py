"""`archery demonstrate`: record a demonstration of the whole shot, or check one.

`--out DEMO.json` follows a running robot while an operator drives its arms (the parts'
`command:i` ports: `--teach`'s scripted teacher, `archery write`) and writes both arms' joint
trajectory (the robot's joint states at every period of its `--state-rate` in simulated s, read
from its history whatever its rtf) with the shot's events once the arrow has landed
(`protocol.demonstration`). `--check FILE` validates a file as `imitate` and the controller
read it (`services.controller.demonstration_file`: bounded size, form, samples, the grasp, nock
and release, each joint's speed and acceleration, every angle within the joint limits). A bad
file or flag: one line naming what is wrong, exit status 2.
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from archery.apps.waits import announce, interrupted_line
from archery.mesh.cliargs import ArgumentParser, add_force_arg, check_output_file, seconds
from archery.mesh.netflags import NetConfig, add_network_args
from archery.mesh.node import Node, open_node
from archery.mesh.robot_client import RobotClient
from archery.protocol.demonstration import (
    FORMAT,
    MIN_DT,
    BadDemonstration,
    DemoEvent,
    Demonstration,
    Sample,
    check_limits,
    encode_demonstration,
    parse_demonstration,
)
from archery.protocol.errors import ArcheryError, ConfigError, RpcTimeout
from archery.protocol.exit_status import BAD_INPUT, FAILURE, INTERRUPTED, OK, for_error
from archery.protocol.messages import WorldEvent
from archery.protocol.parts import ARM_PARTS, PARTS
from archery.protocol.robotspec import NOMINAL_THETA, ROBOT, STRING_ARM
from archery.protocol.vectors import parse_vector
from archery.protocol.verbs.robot import GET_POSITIONS
from archery.services.controller.demonstration_file import read_demonstration

if TYPE_CHECKING:
    from archery.apps.teacher import Teacher

__all__ = ["Recorder", "joint_limits", "main"]

PROG = "demonstrate"
_SHOT_ENDS = ("landed", "missed")
_EVENTS = ("grasped", "nocked", "released", *_SHOT_ENDS)


class Recorder:
    """Both arms' joint trajectory and the shot's events of one robot, from now until the shot
    ends: the events as they come (`world/events:o`), the arms' positions at every point of
    the robot's joint-state grid (`--state-rate` per simulated second) read from its history
    once the shot has ended (`getHistory`): at rtf 0 the `state:o` streams go out at most
    `--state-rate` times per wall second, and a movement 50 times faster than the wall clock
    would leave most of its samples unpublished.

    Args:
        node: a node on the robot's mesh (its world events followed here, the robot read
            through its client, `mesh.robot_client`).
        shot: the robot's shot ("posture" or "whole"), written into the demonstration.
        made: how the demonstration is made (free text), written into it.
    """

    def __init__(self, node: Node, shot: str, made: str = "") -> None:
        self._robot = RobotClient(node)
        self._lock = threading.Lock()
        self._events: list[tuple[float, str]] = []
        self._start = float("inf")  # s (simulated): the recording's start
        self._end = float("inf")  # s (simulated): the shot's end
        self._started = threading.Event()
        self._ended = threading.Event()  # the shot's end event (or a reset) arrived
        self._reset = False
        self._shot, self._made = shot, made
        self._events_sub = node.subscribe(
            node.keys.world_events(), WorldEvent, mode="fifo", callback=self._event
        )

    def _event(self, msg: WorldEvent) -> None:
        if msg.sim_time is None or not self._started.is_set() or self._ended.is_set():
            return
        with self._lock:
            if msg.kind == "reset":  # simulated time starts again: the recording is void
                self._reset = True
            elif msg.kind not in _EVENTS or msg.sim_time < self._start:
                return
            else:
                self._events.append((msg.sim_time, msg.kind))
                if msg.kind in _SHOT_ENDS:
                    self._end = msg.sim_time
        if self._reset or msg.kind in _SHOT_ENDS:
            self._ended.set()

    def wait_started(self, timeout: float) -> bool:
        """Start the recording at the robot's simulated time now (its string arm's encoders);
        True once it is known (the operator may start), False if the robot did not answer
        within `timeout` s."""
        try:
            now = self._robot.part_call(STRING_ARM, GET_POSITIONS, timeout=timeout)
        except RpcTimeout:
            return False
        with self._lock:
            self._start = now.sim_time
        self._started.set()
        return True

    def wait_ended(self, timeout: float) -> bool:
        """True once the arrow has landed (or missed), or the robot was reset, within `timeout`
        wall s: the robot's history then holds the arms' states up to the landing (it keeps
        them before it tells the landing)."""
        return self._ended.wait(timeout)

    def demonstration(self, timeout: float = 30.0) -> Demonstration:
        """What was recorded: both arms at every joint-state grid point from the start up to
        the first after the landing (at least `protocol.demonstration.MIN_DT` apart), read from
        the robot within `timeout` s.

        Raises:
            BadDemonstration: the robot was reset meanwhile, or too short to be a
                demonstration.
        """
        with self._lock:
            start, end, reset = self._start, self._end, self._reset
            events = list(self._events)
        if reset:
            raise BadDemonstration("the robot was reset while recording: record it again")
        by_time: dict[float, dict[str, list[float]]] = {}
        for part in ARM_PARTS:
            history = self._robot.history(part, start, timeout)
            for t, position in zip(history.times, history.positions, strict=True):
                by_time.setdefault(t, {})[part] = position
        both = sorted(t for t, parts in by_time.items() if len(parts) == len(ARM_PARTS))
        after = [t for t in both if t >= end]
        times = [t for t in both if t < end] + after[:1]
        if not times:
            raise BadDemonstration("no state of both arms was recorded")
        times = _spaced(times)
        first = times[0]
        demo = Demonstration(
            format=FORMAT,
            joints={part: list(PARTS[part]) for part in ARM_PARTS},
            samples=[
                Sample(
                    t=t - first, left_arm=by_time[t]["left_arm"], right_arm=by_time[t]["right_arm"]
                )
                for t in times
            ],
            events=[DemoEvent(t=t - first, kind=kind) for t, kind in events],  # type: ignore[arg-type]  # kinds filtered by _EVENTS
            shot=self._shot,  # type: ignore[arg-type]  # the robot's status names one of the two
            made=self._made,
        )
        return parse_demonstration(encode_demonstration(demo))

    def close(self) -> None:
        """Stop following the robot."""
        self._events_sub.close()
        self._robot.close()


def _spaced(times: list[float]) -> list[float]:
    """`times` (s, sorted) thinned so that two kept ones are at least `MIN_DT` apart (a state
    stream faster than a learner plays)."""
    kept = [times[0]]
    for t in times[1:]:
        if t - kept[-1] >= MIN_DT:
            kept.append(t)
    return kept


def joint_limits(shot: str) -> Mapping[str, tuple[Sequence[float], Sequence[float]]]:
    """The arms' joint limits (rad) of the simulated robot for `shot`: the URDF's, which its
    joints never pass (commands stop a margin inside them, `SceneConfig.limit_margin`)."""
    from archery.sim.model_build import build_scene
    from archery.sim.scene import ScenePhysics
    from archery.sim.scene_config import SceneConfig

    physics = ScenePhysics(build_scene(SceneConfig(meshes=False, shot=shot)))
    limits = {}
    for part in ARM_PARTS:
        lower, upper = physics.joint_limits(part)
        limits[part] = (lower.tolist(), upper.tolist())
    return limits


def _summary(demo: Demonstration) -> str:
    return json.dumps(
        {
            "samples": len(demo.samples),
            "duration_s": round(demo.samples[-1].t, 4),
            "events": [e.kind for e in demo.events],
            "shot": demo.shot,
        }
    )


def _check(path: Path) -> int:
    try:
        demo = read_demonstration(path, flag="")
        check_limits(demo, joint_limits(demo.shot))
    except ConfigError as exc:  # the reader names the file
        print(f"archery {PROG}: {exc.message}", file=sys.stderr)
        return BAD_INPUT
    except BadDemonstration as exc:
        print(f"archery {PROG}: {path}: {exc.message}", file=sys.stderr)
        return BAD_INPUT
    print(_summary(demo), flush=True)
    return OK


def _teacher(node: Node, timeout: float) -> Teacher:
    """The scripted whole shot's teacher (`apps.teacher`), its robot at its starting posture.

    Raises:
        ConfigError: not a whole-shot robot. NotAtStart: not at its starting posture.
    """
    from archery.apps.teacher import Teacher

    teacher = Teacher(node, timeout)
    try:
        teacher.check_start()
    except BaseException:
        teacher.close()
        raise
    return teacher


def _record(args: argparse.Namespace) -> int:
    try:
        out = check_output_file(args.out, "--out", (".json",), force=args.force)
    except ConfigError as exc:
        print(f"archery {PROG}: {exc.message}", file=sys.stderr)
        return BAD_INPUT
    try:
        theta = parse_vector("--theta", args.theta, ConfigError, unit="m")
    except ConfigError as exc:
        print(f"archery {PROG}: {exc.message}", file=sys.stderr)
        return BAD_INPUT
    net = NetConfig.from_args(args)
    on_wait = announce(PROG)
    with open_node(net, args.wait, on_wait=on_wait) as node:
        node.wait_alive([ROBOT], args.wait, on_wait=on_wait)
        status = RobotClient(node, timeout=args.wait).status()
        teacher = _teacher(node, args.wait) if args.teach else None  # nothing recorded yet
        recorder = Recorder(node, status.scene.shot, args.made)
        try:
            if not recorder.wait_started(args.wait):
                print(
                    f"archery {PROG}: the robot told no simulated time within {args.wait:g} s",
                    file=sys.stderr,
                )
                return FAILURE
            print(f"archery {PROG}: recording until the arrow lands", file=sys.stderr, flush=True)
            if teacher is not None:
                teacher.teach(theta)
            if not recorder.wait_ended(args.timeout):
                print(
                    f"archery {PROG}: no shot ended within {args.timeout:g} s; nothing written",
                    file=sys.stderr,
                )
                return FAILURE
            demo = recorder.demonstration()
        except BadDemonstration as exc:
            print(
                f"archery {PROG}: the recording is no demonstration: {exc.message}", file=sys.stderr
            )
            return FAILURE
        finally:
            recorder.close()
            if teacher is not None:
                teacher.close()
    out.write_bytes(encode_demonstration(demo))
    print(_summary(demo), flush=True)
    return OK


def main(argv: list[str] | None = None) -> int:
    """Record (`--out`) or check (`--check`) a demonstration; exit status 0, 1 (no shot ended,
    the robot is not there or, with --teach, not at its starting posture), 2 (bad flags or
    file) or 130 (Ctrl-C)."""
    parser = ArgumentParser(
        prog=f"archery {PROG}",
        description="record a demonstration of the whole shot while an operator drives the "
        "arms (--out), or check a demonstration file (--check)",
    )
    add_network_args(parser, default_mode="client")
    what = parser.add_mutually_exclusive_group(required=True)
    what.add_argument("--out", type=Path, metavar="DEMO.json", help="record into this file")
    what.add_argument("--check", type=Path, metavar="FILE", help="check this file")
    add_force_arg(parser, "an existing --out file")
    parser.add_argument(
        "--timeout", type=seconds, default=600.0, help="wall s to wait for the shot to end"
    )
    parser.add_argument(
        "--wait", type=seconds, default=30.0, help="wall s to wait for the robot and its states"
    )
    parser.add_argument("--made", default="", help="how it is made, written into the file")
    parser.add_argument(
        "--teach",
        action="store_true",
        help="with --out: drive the arms through the scripted whole shot while recording",
    )
    parser.add_argument(
        "--theta",
        default=",".join(f"{v:g}" for v in NOMINAL_THETA),
        metavar="X,Y,Z",
        help="with --teach: draw the string hand to bow hand + θ (m)",
    )
    args = parser.parse_args(argv)
    if args.check is not None:
        return _check(args.check)
    try:
        return _record(args)
    except KeyboardInterrupt:
        print(interrupted_line(PROG), file=sys.stderr)
        return INTERRUPTED
    except ArcheryError as exc:
        print(f"archery {PROG}: {exc.message}", file=sys.stderr)
        return for_error(exc.code)
