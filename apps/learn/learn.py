"""`archery learn`: run one learning session against running services and print its result.

It asks the learner service to `start` (or `--resume`) a session, or to start one from another
session's learned model (`--from SESSION`: its id under the learner's runs directory, or its
journal; see `services.learner.transfer`), or follows a running one (`--attach SESSION`,
`apps.learn.attach`), shows each rollout as it is published on `learner/rollout:o` and what a
waiting session waits for, and ends by printing one JSON line on stdout. `main` says what it
prints, what it waits for and its exit statuses; following through faults is
`apps.learn.follow`'s.
"""

from __future__ import annotations

import argparse
import inspect
import math
import sys
from pathlib import Path
from typing import Any

from archery.apps.film.film import film_hit, film_ready, hit_video
from archery.apps.learn import attach
from archery.apps.learn.client import learner_call, start_args
from archery.apps.learn.follow import SessionLost, follow, result_line
from archery.apps.learn.operator_prompt import OperatorPrompt
from archery.apps.waits import announce
from archery.mesh.cliargs import ArgumentParser, loads_finite, seconds
from archery.mesh.netflags import NetConfig, add_network_args
from archery.mesh.node import open_node
from archery.protocol.errors import ArcheryError, ConfigError, RpcError
from archery.protocol.exit_status import FAILURE, INTERRUPTED, for_error
from archery.protocol.journal_records import AbortedRecord, ProposedRecord
from archery.protocol.messages import Rollout
from archery.protocol.robotspec import SERVICES
from archery.protocol.vectors import parse_vector
from archery.services.learner.algorithms.base import LearnerError
from archery.services.learner.algorithms.registry import ALGORITHMS, check_transfer
from archery.services.learner.config import SessionConfig

__all__ = ["DEFAULTS", "build_parser", "main", "session_flags_given", "start_request"]

DEFAULTS: dict[str, Any] = {"algo": "archer", "rollouts": 30, "seed": 0}
# s: longer than `archery up` takes to restart a crashed learner or router (its back-off and the
# start of a process), short enough that a learner gone for good is told soon.
LOST_WAIT = 30.0
# (flag, argparse dest) of the flags that describe a new session
SESSION_FLAGS = (
    ("--algo", "algo"),
    ("--rollouts", "rollouts"),
    ("--seed", "seed"),
    ("--no-until-hit", "no_until_hit"),
    ("--theta0", "theta0"),
    ("--hit-radius", "hit_radius"),
    ("--option", "option"),
)


def option_names(algo: str) -> tuple[str, ...]:
    """The options the learner `algo` accepts (its constructor's settings)."""
    parameters = inspect.signature(ALGORITHMS[algo].cls.__init__).parameters
    fixed = ("self", "theta0", "rng", "bounds")
    return tuple(name for name in parameters if name not in fixed)


def _option(text: str, algo: str) -> tuple[str, Any]:
    name, sep, value = text.partition("=")
    if not sep or not name:
        raise ConfigError(f"--option must be NAME=VALUE (VALUE in JSON), got {text!r}")
    valid = option_names(algo)
    if name not in valid:
        raise ConfigError(
            f"--option {name!r}: {algo} has no such option; its options: {', '.join(valid)}"
        )
    try:
        return name, loads_finite(value, f"--option {name}:")
    except ConfigError as exc:
        raise ConfigError(f"{exc} (VALUE is JSON, e.g. 0.003 or [1,2,3])") from None


def _hit_radius(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of metres") from None
    if not (math.isfinite(value) and 0.001 <= value <= 0.25):
        raise argparse.ArgumentTypeError(f"{text!r} is not in [0.001, 0.25] m")
    return value


def build_parser() -> argparse.ArgumentParser:
    """The flags of `archery learn`."""
    parser = ArgumentParser(prog="archery learn", description=__doc__.split("\n")[0])
    add_network_args(parser)
    # The session's flags default to None (not given), so that --resume and --attach, which
    # take the session as it was journaled, can refuse them; `start_request` applies defaults.
    parser.add_argument(
        "--algo", help=f"one of {', '.join(ALGORITHMS)} (default {DEFAULTS['algo']})"
    )
    parser.add_argument(
        "--rollouts", type=int, help=f"budget of done rollouts (default {DEFAULTS['rollouts']})"
    )
    parser.add_argument(
        "--seed", type=int, help=f"seed of the learner and the shots (default {DEFAULTS['seed']})"
    )
    parser.add_argument(
        "--no-until-hit",
        action="store_true",
        help="use the whole budget instead of ending at the first hit",
    )
    parser.add_argument("--theta0", metavar="X,Y,Z", help="start θ (m)")
    parser.add_argument(
        "--hit-radius", type=_hit_radius, help="hit radius (m, in [0.001, 0.25], default 0.05)"
    )
    parser.add_argument(
        "--option", action="append", metavar="NAME=VALUE", help="learner option (repeatable)"
    )
    which = parser.add_mutually_exclusive_group()
    which.add_argument(
        "--resume",
        metavar="PATH",
        help="continue the session journaled at PATH, inside the learner's runs folder (a "
        "relative PATH that does not exist here is taken from that folder)",
    )
    which.add_argument(
        "--from",
        dest="from_",
        metavar="SESSION",
        help="start a new session from SESSION's learned model (its id or journal)",
    )
    which.add_argument(
        "--attach",
        metavar="SESSION",
        help="follow the running session SESSION (its id or journal) from where it is",
    )
    parser.add_argument(
        "--wait",
        type=seconds,
        default=60.0,
        help="wait this long for the router to listen and the five services to be alive (s)",
    )
    parser.add_argument(
        "--lost-wait",
        type=seconds,
        default=LOST_WAIT,
        help="while following, wait this long for a vanished learner or router to come back (s)",
    )
    parser.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    parser.add_argument(
        "--require-hit",
        action="store_true",
        help="exit status 1 when the session finishes without a hit (containers, scripts)",
    )
    parser.add_argument(
        "--no-film",
        action="store_true",
        help="do not film a hit into shot.mp4 beside the journal (see `archery film`)",
    )
    return parser


def session_flags_given(args: argparse.Namespace) -> list[str]:
    """The flags describing a new session that were given (those --resume/--attach refuse)."""
    values = ((flag, getattr(args, dest)) for flag, dest in SESSION_FLAGS)
    return [flag for flag, value in values if value is not None and value is not False]


def start_request(args: argparse.Namespace) -> dict[str, Any]:
    """The `start` request for parsed flags (the defaults of `DEFAULTS` for those not given).

    Raises:
        ConfigError: an unknown algorithm, or --resume with flags of a new session (the
            journaled session goes on as it was started; the message names them).
    """
    if args.resume:
        given = session_flags_given(args)
        if given:
            raise ConfigError(
                f"--resume continues the session as it was journaled; it cannot honour "
                f"{', '.join(given)} (leave them out, or start a new session)"
            )
        return {"resume": _resume_path(args.resume)}
    algo = DEFAULTS["algo"] if args.algo is None else args.algo
    if algo not in ALGORITHMS:
        raise ConfigError(
            f"--algo {algo!r} is not a learner; valid algorithms: {', '.join(ALGORITHMS)}"
        )
    scenario: dict[str, Any] = {}
    if args.theta0:
        scenario["theta0"] = parse_vector("--theta0", args.theta0, ConfigError).tolist()
    if args.hit_radius is not None:
        scenario["hit_radius"] = args.hit_radius
    request: dict[str, Any] = {
        "algo": algo,
        "rollouts": DEFAULTS["rollouts"] if args.rollouts is None else args.rollouts,
        "seed": DEFAULTS["seed"] if args.seed is None else args.seed,
        "until_hit": not args.no_until_hit,
        "options": dict(_option(text, algo) for text in args.option or []),
    }
    if scenario:
        request["scenario"] = scenario
    if args.from_:
        request["from_journal"] = _from_journal(args.from_, algo)
    return request


def _resume_path(target: str) -> str:
    """`--resume`'s journal as the learner is to read it: a path that exists here as an
    absolute path (on this machine the learner's runs folder holds it), any other as given (the
    learner, maybe elsewhere, takes a relative path from its runs folder)."""
    path = Path(target)
    return str(path.resolve()) if path.exists() else target


def _from_journal(target: str, algo: str) -> str:
    """`--from`'s session id, or its journal or directory as an absolute path (the learner may
    run elsewhere); a path that does not exist here is refused."""
    try:
        check_transfer(algo)
    except LearnerError as exc:
        raise ConfigError(str(exc)) from None
    path = Path(target)
    if path.exists():
        return str(path.resolve())
    if "/" in target or target.endswith(".jsonl"):
        raise ConfigError(f"--from {target!r}: no such journal or session directory")
    return target  # a session id, looked up in the learner's runs directory


def _progress(message: Rollout) -> None:
    record = message.record
    theta = ", ".join(f"{100 * v:.2f}" for v in record.theta)
    if isinstance(record, ProposedRecord):
        return
    if isinstance(record, AbortedRecord):
        print(f"  attempt {record.index}: θ ({theta}) cm aborted: {record.note()}", file=sys.stderr)
        return
    r = record.r_m
    distance = 100 * (r[0] ** 2 + r[1] ** 2) ** 0.5
    hit = "  HIT" if record.hit else ""
    print(
        f"  attempt {record.index}: θ ({theta}) cm → r ({100 * r[0]:+.1f}, {100 * r[1]:+.1f}) cm, "
        f"{distance:.1f} cm{hit}",
        file=sys.stderr,
        flush=True,
    )


def main(argv: list[str] | None = None) -> int:
    """Run `archery learn`; its exit status.

    The one JSON line on stdout (its counts read from the session's journal,
    `apps.learn.follow.result_line`): `{"session", "rollouts", "hit_at", "final_distance_m",
    "journal", "status", "aborted", "report", "hit_frame", "video"}`; then a hit is filmed
    into `shot.mp4` beside the journal when the journal is on this machine (`apps.film`; not
    with `--no-film`): "video" is that path, else null. Filming comes after the line: a
    failure there is one warning on stderr and leaves the exit status that of the session.

    Every wait says on stderr, the moment it begins, what it waits for and for how long at
    most (`apps.waits`; not with `--quiet`, which keeps every progress line off): the router
    while nothing listens at `--connect` (up to `--wait` s), the services not alive yet (up to
    `--wait` s), and the learner resuming a `--resume` session (up to `--wait` + 30 s), e.g.
    `archery learn: waiting up to 60 s for the services: robot, camera (Ctrl-C to stop)`.

    Following survives the faults `archery up` mends (`apps.learn.follow`): a learner or router
    that vanishes is waited for up to `--lost-wait` s; a learner restarted without the session
    is asked once to resume it from its journal, and the session is followed on to its end; a
    session whose journal ended meanwhile gets the journal's final line.

    Exit status 0 when the session finished (hit or budget; with `--require-hit`: 1 when it
    finished without a hit); 1 when it failed, could not be followed on (the message says how
    to go on: `--attach` while it may still run, `--resume` when it does not) or the learner is
    busy; 2 for bad input; 130 after Ctrl-C (the session is stopped after its current rollout
    and can be resumed).
    """
    args = build_parser().parse_args(argv)
    try:
        net = NetConfig.from_args(args)
        given = session_flags_given(args)
        if args.attach and given:
            raise ConfigError(
                f"--attach follows the session as it runs; it cannot honour {', '.join(given)}"
            )
        request = start_request(args)
        if "resume" not in request:  # the learner's own checks, then the verb's types
            SessionConfig.from_request(request)
        start = start_args(request)
        if not args.no_film and not args.attach:  # the hit is filmed here, after the session
            film_ready()
    except ArcheryError as exc:
        print(f"archery learn: {exc}", file=sys.stderr)
        return 2
    show = (lambda m: None) if args.quiet else _progress
    lines = (lambda s: None) if args.quiet else attach.WaitingLines(attach.stderr_line)
    note = None if args.quiet else attach.stderr_line
    on_wait = None if args.quiet else announce("learn")
    resume_timeout = args.wait + 30.0  # s: a resumed session's `start` waits for the services
    try:
        node = open_node(net, args.wait, on_wait=on_wait)
    except ArcheryError as exc:
        print(f"archery learn: {exc}", file=sys.stderr)
        return for_error(exc.code)
    with node:
        keys = sys.stdin if sys.stdin is not None and sys.stdin.isatty() else None
        prompt = OperatorPrompt(node, attach.stderr_line, keys)  # said even with --quiet

        def waiting(status: dict[str, Any]) -> None:
            lines(status)
            prompt(status)

        rollouts = node.subscribe(node.keys.learner_rollouts(), Rollout, mode="fifo")
        if args.attach:
            return attach.attach(
                node,
                rollouts,
                args.attach,
                show,
                quiet=args.quiet,
                gone_after=args.lost_wait,
                resume_timeout=resume_timeout,
                note=note,
            )
        try:
            node.wait_alive(SERVICES, timeout=args.wait, on_wait=on_wait)
            if "resume" in request and on_wait is not None:  # it reads and replays the journal
                on_wait(f"the learner to resume the session of {request['resume']}", resume_timeout)
            status = learner_call(node, "start", start, timeout=resume_timeout)
        except RpcError as exc:
            print(f"archery learn: {exc}", file=sys.stderr)
            return for_error(exc.code)
        session = status["session"]
        if not args.quiet:
            print(f"session {session}: journal {status['journal']}", file=sys.stderr)
        try:
            status = follow(
                node,
                session,
                rollouts,
                show,
                on_status=waiting,
                journal=status["journal"],
                resume=True,
                gone_after=args.lost_wait,
                resume_timeout=resume_timeout,
                note=note,
            )
        except SessionLost as exc:
            print(f"archery learn: {exc}", file=sys.stderr)
            status = attach.journal_counts(exc.status or status) | {"state": "lost"}
            print(result_line(status))
            return 1
        except RpcError as exc:  # the learner refused its status (e.g. access control)
            print(f"archery learn: {exc}", file=sys.stderr)
            return for_error(exc.code)
        except KeyboardInterrupt:
            print("archery learn: stopping the session after its current rollout", file=sys.stderr)
            try:
                learner_call(node, "stop", timeout=5.0)
                status = follow(node, session, rollouts, show)
            except (ArcheryError, KeyboardInterrupt):
                pass
            print(result_line(attach.journal_counts(status)))
            return INTERRUPTED
    counts = attach.journal_counts(status)
    video = None if args.no_film else hit_video(counts)
    counts["video"] = None if video is None else str(video)
    print(result_line(counts), flush=True)  # the result first: nothing after it can lose it
    if video is not None and film_hit(counts, quiet=args.quiet) and not args.quiet:
        print(f"archery learn: the hit filmed into {video}", file=sys.stderr)
    if status["state"] != "finished":
        print(
            f"archery learn: session {status['state']}: {status.get('cause', '')}", file=sys.stderr
        )
        return 1
    if args.require_hit and counts.get("hit_at") is None:
        print(f"archery learn: session {session} finished without a hit", file=sys.stderr)
        return FAILURE
    return 0
