"""`archery demonstrate`: record a demonstration of the whole shot, or check one.

`--out DEMO.json` follows a running robot while an operator drives its arms (the parts'
`command:i` ports: `--teach`'s scripted teacher, `archery write`) and its verbs, and writes
both arms' joint trajectory (the `state:o` streams, in simulated s) with the shot's events
once the arrow has landed (`protocol.demonstration`). `--check FILE` validates a file with the
reader `imitate` and the controller use (`services.controller.demonstration_file`: a regular
file of bounded size, its form, samples, duration and events what a learner can play), and
every angle within the simulated robot's joint limits. A bad file or flag: one line
naming what is wrong, exit status 2.
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
import time
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from archery.apps.waits import announce, interrupted_line
from archery.mesh.cliargs import ArgumentParser, add_force_arg, check_output_file, seconds
from archery.mesh.netflags import NetConfig, add_network_args
from archery.mesh.node import Node, open_node
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
from archery.protocol.errors import ArcheryError, ConfigError
from archery.protocol.exit_status import BAD_INPUT, FAILURE, INTERRUPTED, OK, for_error
from archery.protocol.messages import JointState, WorldEvent
from archery.protocol.parts import ARM_PARTS, PARTS
from archery.protocol.robotspec import NOMINAL_THETA, ROBOT
from archery.protocol.vectors import parse_vector
from archery.protocol.verbs.robot import ARCHERY_STATUS
from archery.services.controller.demonstration_file import read_demonstration

__all__ = ["Recorder", "joint_limits", "main"]

PROG = "demonstrate"
_SHOT_ENDS = ("landed", "missed")
_EVENTS = ("grasped", "nocked", "released", *_SHOT_ENDS)


class Recorder:
    """Both arms' states and the shot's events of one robot, from now until the shot ends.

    Args:
        node: a node on the robot's mesh.
        shot: the robot's shot ("posture" or "whole"), written into the demonstration.
        made: how the demonstration is made (free text), written into it.
    """

    def __init__(self, node: Node, shot: str, made: str = "") -> None:
        self._lock = threading.Lock()
        self._by_time: dict[float, dict[str, list[float]]] = {}
        self._events: list[tuple[float, str]] = []
        self._first = threading.Event()
        self._ended = threading.Event()  # the shot's end event arrived: no more events
        self._complete = threading.Event()  # and both arms' states reached its time
        self._end = float("inf")  # s (simulated): the shot's end
        self._shot, self._made = shot, made
        keys = node.keys
        self._states = [
            node.subscribe(keys.state(part), JointState, mode="fifo", callback=self._state)
            for part in ARM_PARTS
        ]
        self._events_sub = node.subscribe(
            keys.world_events(), WorldEvent, mode="fifo", callback=self._event
        )

    def _state(self, msg: JointState) -> None:
        if msg.part not in ARM_PARTS or msg.sim_time is None or self._complete.is_set():
            return
        with self._lock:
            parts = self._by_time.setdefault(msg.sim_time, {})
            parts[msg.part] = list(msg.position)
            reached = msg.sim_time >= self._end and len(parts) == len(ARM_PARTS)
        self._first.set()
        if reached:
            self._complete.set()

    def _event(self, msg: WorldEvent) -> None:
        if msg.kind not in _EVENTS or msg.sim_time is None or not self._first.is_set():
            return
        if self._ended.is_set():
            return
        reached = False
        with self._lock:
            self._events.append((msg.sim_time, msg.kind))
            if msg.kind in _SHOT_ENDS:
                self._end = msg.sim_time
                reached = any(
                    t >= self._end and len(parts) == len(ARM_PARTS)
                    for t, parts in self._by_time.items()
                )
        if msg.kind in _SHOT_ENDS:
            self._ended.set()
            if reached:
                self._complete.set()

    def wait_started(self, timeout: float) -> bool:
        """True once the first state arrived (the operator may start), within `timeout` s."""
        return self._first.wait(timeout)

    def wait_ended(self, timeout: float) -> bool:
        """True once the arrow has landed (or missed), within `timeout` wall s, and then both
        arms' states have reached the landing's time (the state streams and the events are
        separate streams: the last states may follow the event), within what is left of it."""
        deadline = time.monotonic() + timeout
        if not self._ended.wait(timeout):
            return False
        self._complete.wait(max(0.0, deadline - time.monotonic()))
        return True

    def demonstration(self) -> Demonstration:
        """What was recorded: the times at which both arms' states arrived, up to the first
        after the landing (at least `protocol.demonstration.MIN_DT` apart).

        Raises:
            BadDemonstration: too short to be a demonstration.
        """
        with self._lock:
            both = sorted(t for t, parts in self._by_time.items() if len(parts) == len(ARM_PARTS))
            after = [t for t in both if t >= self._end]
            times = [t for t in both if t < self._end] + after[:1]
            events = list(self._events)
            by_time = {t: self._by_time[t] for t in times}
        if not times:
            raise BadDemonstration("no state of both arms was recorded")
        times = _spaced(times)
        start = times[0]
        demo = Demonstration(
            format=FORMAT,
            joints={part: list(PARTS[part]) for part in ARM_PARTS},
            samples=[
                Sample(
                    t=t - start, left_arm=by_time[t]["left_arm"], right_arm=by_time[t]["right_arm"]
                )
                for t in times
            ],
            events=[DemoEvent(t=t - start, kind=kind) for t, kind in events],  # type: ignore[arg-type]  # kinds filtered by _EVENTS
            shot=self._shot,  # type: ignore[arg-type]  # the robot's status names one of the two
            made=self._made,
        )
        return parse_demonstration(encode_demonstration(demo))

    def close(self) -> None:
        """Stop following the robot."""
        for sub in self._states:
            sub.close()
        self._events_sub.close()


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


def _teach(node: Node, theta: np.ndarray, timeout: float) -> None:
    """Drive the robot through the scripted whole shot (`apps.teacher`)."""
    from archery.apps.teacher import Teacher

    teacher = Teacher(node, timeout)
    try:
        teacher.teach(theta)
    finally:
        teacher.close()


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
        status = node.call_typed(node.keys.archery_rpc(), ARCHERY_STATUS)
        recorder = Recorder(node, status.scene.shot, args.made)
        try:
            if not recorder.wait_started(args.wait):
                print(f"archery {PROG}: no joint state within {args.wait:g} s", file=sys.stderr)
                return FAILURE
            print(f"archery {PROG}: recording until the arrow lands", file=sys.stderr, flush=True)
            if args.teach:
                _teach(node, theta, args.wait)
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
    out.write_bytes(encode_demonstration(demo))
    print(_summary(demo), flush=True)
    return OK


def main(argv: list[str] | None = None) -> int:
    """Record (`--out`) or check (`--check`) a demonstration; exit status 0, 1 (no shot ended,
    the robot is not there), 2 (bad flags or file) or 130 (Ctrl-C)."""
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
