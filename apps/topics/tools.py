"""Introspection tools, the `yarp` CLI of this mesh: ports, read, write, rpc, view."""

from __future__ import annotations

import argparse
import json
import queue
import sys
import time
from collections.abc import Callable
from typing import Any

import msgspec
import zenoh

from archery.apps.waits import announce, interrupted_line
from archery.mesh.acl import VIEWER
from archery.mesh.cliargs import (
    IMAGE_EXTENSIONS,
    ArgumentParser,
    add_force_arg,
    check_output_file,
    count,
    loads_finite,
    seconds,
    seconds_or_zero,
)
from archery.mesh.instances import describe_all
from archery.mesh.netflags import NetConfig, add_network_args
from archery.mesh.node import Node, open_node
from archery.mesh.patterns import check_pattern, is_wildcard, stream_type
from archery.mesh.rpc_server import bad_args_message
from archery.mesh.tokens import TokenSet
from archery.protocol.codec import decode, from_jsonable, to_jsonable
from archery.protocol.errors import (
    ArcheryError,
    BadRequest,
    ConfigError,
    DecodeError,
    KeyNameError,
    RpcError,
)
from archery.protocol.exit_status import BAD_INPUT, INTERRUPTED, for_error
from archery.protocol.keys import ALIVE_EVERY_ROBOT, DEFAULT_ROBOT, Keys, port_of
from archery.protocol.messages import MESSAGE_TYPES, Describe, Image, Message, PortInfo
from archery.protocol.robotspec import CALL_TIMEOUT
from archery.protocol.verbs import Verb, table_for_key
from archery.protocol.verbs.robot import COUNTERS

__all__ = ["alive_main", "ports_main", "read_main", "rpc_main", "view_main", "write_main"]


def _parser(prog: str, description: str) -> argparse.ArgumentParser:
    parser = ArgumentParser(prog=f"archery {prog}", description=description)
    add_network_args(parser, default_mode="client")
    parser.add_argument(
        "--timeout",
        type=seconds,
        default=CALL_TIMEOUT,
        help=f"seconds to wait (default {CALL_TIMEOUT:g})",
    )
    return parser


def _run(prog: str, check: Callable[[], Any], body: Callable[[Any], int]) -> int:
    """Check the input (`check()`; its errors: exit status 2), then run `body(checked)` (its
    errors: `protocol.exit_status.for_error`, e.g. nothing reachable: 1, a remote service
    refusing the request: 2; Ctrl-C: 130). Each error is one line on stderr."""
    try:
        checked = check()
    except ArcheryError as exc:
        print(f"archery {prog}: {exc}", file=sys.stderr)
        return 2
    try:
        return body(checked)
    except ArcheryError as exc:
        print(f"archery {prog}: {exc}", file=sys.stderr)
        return for_error(exc.code)
    except KeyboardInterrupt:
        print(interrupted_line(prog), file=sys.stderr, flush=True)
        return INTERRUPTED


def _stream_type(key: str) -> type[Message]:
    spec = port_of(key)
    if spec.kind in ("rpc", "liveliness"):
        raise KeyNameError(f"{key} is an {spec.kind} port, not a stream; use `archery rpc`")
    return MESSAGE_TYPES[spec.message]


def alive_main(argv: list[str] | None = None) -> int:
    """`archery alive [NAME…] [--wait N]`: a health check. Exit 0 when the router answers and
    every named service of the robot holds its liveliness token now (or, with `--wait`, within
    N s); 1 (one line on stderr) when not. With `--wait`, a wait that begins (no router listens
    yet, or a named service is not alive yet) says so at once on stderr with its limit
    (`apps.waits`)."""
    parser = _parser("alive", "exit 0 when the router answers and the named services are alive")
    parser.add_argument("names", nargs="*", metavar="NAME", help="services that must be alive")
    parser.add_argument(
        "--wait",
        type=seconds_or_zero,
        default=0.0,
        metavar="N",
        help="wait up to N s for them to come alive (by liveliness; default 0: alive now)",
    )
    args = parser.parse_args(argv)

    def body(net: NetConfig) -> int:
        on_wait = announce("alive")
        with open_node(net, args.wait, on_wait=on_wait) as node:
            if args.wait:  # the tokens seen by the subscription decide (no second query)
                missing = sorted(node.missing_after(args.names, args.wait, on_wait))
            else:
                missing = sorted(set(args.names) - node.alive(timeout=args.timeout))
            if missing:
                print(
                    f"archery alive: not alive on robot {node.keys.robot!r}: {', '.join(missing)}",
                    file=sys.stderr,
                )
                return 1
        return 0

    return _run("alive", lambda: NetConfig.from_args(args).with_identity(VIEWER), body)


def ports_main(argv: list[str] | None = None) -> int:
    """`archery ports`: live services and their ports (like `yarp name list`): of every robot
    on the router, grouped by robot prefix (a fleet: `ROBOT1`, `ROBOT2`, …), or of `--robot`.
    With `--wait N`, a wait that begins (no router listens yet, or no service is alive yet)
    says so at once on stderr with its limit (`apps.waits`)."""
    parser = _parser("ports", "list live services and their ports")
    parser.set_defaults(robot=None)  # None: every robot alive on the router
    parser.add_argument("--json", action="store_true", help="one JSON object per service")
    parser.add_argument(
        "--wait",
        type=seconds_or_zero,
        default=0.0,
        metavar="N",
        help="wait up to N s for a service to come alive (default 0: list who is alive now)",
    )
    parser.add_argument(
        "--verbose", action="store_true", help="message fields and each rpc verb's schemas"
    )
    args = parser.parse_args(argv)
    every = args.robot is None

    def check() -> NetConfig:
        robot = DEFAULT_ROBOT if every else args.robot
        namespace = argparse.Namespace(**(vars(args) | {"robot": robot}))
        return NetConfig.from_args(namespace).with_identity(VIEWER)

    def body(net: NetConfig) -> int:
        on_wait = announce("ports")
        with open_node(net, args.wait, on_wait=on_wait) as node:
            seen: set[str] = set()  # names whose tokens the wait saw arrive
            if args.wait:
                pattern = ALIVE_EVERY_ROBOT if every else node.keys.alive_all()
                waits = not _any_alive(node, every, args.timeout)  # asked before subscribing
                with TokenSet(node.session, pattern) as alive:
                    if waits and not alive.present():
                        where = "any robot" if every else f"robot {args.robot!r}"
                        on_wait(f"a service of {where} to come alive", args.wait)
                    alive.wait_for(bool, args.wait)
                    seen = alive.present()
            robots = node.alive_robots(timeout=args.timeout)
            if seen and not every:  # a query just after a token arrived may not list it yet
                robots[args.robot] = robots.get(args.robot, set()) | seen
            elif seen and not robots:
                robots = node.alive_robots(timeout=args.timeout)
            if every and not robots:  # in secure mode the ACL lets one see one's robot only
                own = node.alive(timeout=args.timeout)
                robots = {node.keys.robot: own} if own else {}
            if not every:
                robots = {args.robot: robots[args.robot]} if args.robot in robots else {}
            if not robots:
                where = "any robot" if every else f"robot {args.robot!r}"
                others = sorted(node.alive_robots(timeout=args.timeout)) if not every else []
                hint = f"; alive on it: robot {', '.join(others)} (--robot NAME)" if others else ""
                print(
                    f"archery ports: no service alive on {where} (router "
                    f"{', '.join(net.connect)}){hint}",
                    file=sys.stderr,
                )
                return 0
            for robot, names in sorted(robots.items()):
                if len(robots) > 1 and not args.json:
                    print(f"== robot {robot}: {len(names)} services")
                keys = Keys(robot)
                for name in sorted(names):
                    _print_service(node, keys, name, args)
        return 0

    return _run("ports", check, body)


def _any_alive(node: Node, every: bool, timeout: float) -> bool:
    """Whether a service is alive now (of any robot with `every`, else of the node's robot), by
    one query (a liveliness subscription's history streams in one token at a time; a query
    made just after subscribing may miss them: ask before)."""
    limit = max(0.01, min(1.0, timeout))
    return bool(node.alive_robots(timeout=limit) if every else node.alive(timeout=limit))


def _print_service(node: Node, keys: Keys, name: str, args: argparse.Namespace) -> None:
    """The ports of one live service (each instance's, if several answer) as `ports` shows."""
    described = describe_all(node.session, keys, name, timeout=args.timeout)
    if not described:
        print(f"{name}: alive, but no describe reply")
        return
    many = f"  [{len(described)} instances!]" if len(described) > 1 else ""
    for zid, info in sorted(described.items()):
        if args.json:
            print(json.dumps(to_jsonable(info) | {"instance": zid, "robot": keys.robot}))
            continue
        print(f"{name}  (pid {info.pid} on {info.host}, instance {zid}){many}")
        for port in info.ports:
            verbs = info.verbs.get(port.key)
            extra = f"  verbs: {', '.join(verbs)}" if verbs else ""
            print(f"  {port.kind:<6} {port.key}  [{port.message}]{extra}")
            if args.verbose:
                print("\n".join(_verbose_lines(info, port)))


def _verbose_lines(info: Describe, port: PortInfo) -> list[str]:
    from archery.apps.topics.interface import interface_lines, message_lines

    if port.kind != "rpc":
        return message_lines(port.message, "      ")
    if port.key in info.interfaces:
        return interface_lines(info.interfaces[port.key], "      ")
    return ["      (untyped verbs)"] if port.message == "RpcRequest" else []


def _field(value: Any, path: str) -> Any:
    """The part of a JSON-like message at a dotted `path` (`r_m.0`, `names.1`); None where a
    step meets a null (an optional field not set, e.g. `r_m` of a detection without an arrow).

    Raises:
        KeyNameError: a step names no key of an object, or an index outside a list.
    """
    where = "the message"
    for step in path.split("."):
        if value is None:
            return None
        if isinstance(value, dict):
            if step not in value:
                raise KeyNameError(
                    f"--field {path!r}: {where} has no {step!r}; it has {', '.join(value)}"
                )
            value = value[step]
        elif isinstance(value, list):
            if not (step.lstrip("-").isdigit() and -len(value) <= int(step) < len(value)):
                raise KeyNameError(
                    f"--field {path!r}: {where} has {len(value)} entries, no entry {step!r}"
                )
            value = value[int(step)]
        else:
            raise KeyNameError(f"--field {path!r}: {where} is {value!r}, it has no {step!r}")
        where = step
    return value


def _check_field(message_type: type[Message] | None, path: str) -> None:
    """Raise KeyNameError when `path`'s first step is no field of `message_type`."""
    head = path.split(".", 1)[0]
    if message_type is not None and head not in ("type", *message_type.__struct_fields__):
        raise KeyNameError(
            f"--field {path!r}: {message_type.__name__} has no field {head!r}; its fields: "
            f"{', '.join(message_type.__struct_fields__)}"
        )


def read_main(argv: list[str] | None = None) -> int:
    """`archery read KEY [--count N] [--field PATH]`: decoded messages as JSON lines (like `yarp
    read`); a KEY with wildcards (`icubSim/*/state:o`) prints {"key", "value"} objects."""
    parser = _parser("read", "print decoded messages from a stream key as JSON lines")
    parser.add_argument("key", help="a stream key, or a pattern such as ROBOT/*/state:o")
    parser.add_argument(
        "--count",
        type=count,
        default=0,
        help="stop after N messages, each waited for at most --timeout s (0: read until Ctrl-C)",
    )
    parser.add_argument(
        "--field", metavar="PATH", help="print only this field, e.g. r_m.0 or position.2"
    )
    args = parser.parse_args(argv)
    wildcard = is_wildcard(args.key)

    def check() -> tuple[NetConfig, type[Message] | None]:
        net = NetConfig.from_args(args).with_identity(VIEWER)
        if wildcard:
            check_pattern(args.key)
            message_type = None
        else:
            message_type = _stream_type(args.key)
        if args.field is not None:
            _check_field(message_type, args.field)
        return net, message_type

    def body(checked: tuple[NetConfig, type[Message] | None]) -> int:
        net, message_type = checked
        received: queue.SimpleQueue[tuple[str, Message]] = queue.SimpleQueue()
        malformed = [0]

        def on_sample(sample: zenoh.Sample) -> None:
            key = str(sample.key_expr)
            wanted = message_type or stream_type(key)
            if wanted is None:
                return
            try:
                received.put((key, decode(sample.payload.to_bytes(), wanted)))
            except DecodeError:
                malformed[0] += 1

        with Node(None, net) as node:
            sub = node.session.declare_subscriber(args.key, on_sample)
            printed = 0
            try:
                while args.count == 0 or printed < args.count:
                    try:
                        key, message = received.get(timeout=args.timeout if args.count else None)
                    except queue.Empty:
                        print(
                            f"archery read: no message on {args.key} within {args.timeout:g} s "
                            f"({printed} of {args.count} read, {malformed[0]} malformed dropped)",
                            file=sys.stderr,
                        )
                        return 1
                    value: Any = to_jsonable(message)
                    if args.field is not None:
                        try:
                            value = _field(value, args.field)
                        except KeyNameError as exc:  # the user's path, judged on a message
                            print(f"archery read: {exc}", file=sys.stderr)
                            return BAD_INPUT
                    print(
                        json.dumps({"key": key, "value": value} if wildcard else value), flush=True
                    )
                    printed += 1
            finally:
                sub.undeclare()
        return 0

    return _run("read", check, body)


def _command_total(counters: dict[str, Any]) -> int:
    return sum(int(counters.get(k, 0)) for k in ("accepted", "rejected", "undecodable"))


def _counters(node: Node, rpc_key: str, timeout: float) -> dict[str, Any]:
    """The command counters of the part whose `rpc:i` is `rpc_key`, as plain data."""
    reply = node.call_typed(rpc_key, COUNTERS, timeout=timeout)
    counters: dict[str, Any] = msgspec.to_builtins(reply)
    return counters


def _verdict(node: Node, rpc_key: str, before: dict[str, Any], timeout: float) -> str | None:
    """Wait until the owner's counters count the command; the refusal message, or None.

    Raises:
        RpcError: the counters did not move within `timeout` s, or another command arrived in
            the meantime and the counters cannot tell which was refused.
    """
    deadline = time.monotonic() + timeout
    while True:
        after = _counters(node, rpc_key, timeout)
        arrived = _command_total(after) - _command_total(before)
        if arrived >= 1:
            break
        if time.monotonic() >= deadline:
            raise RpcError(
                f"the command was delivered but {rpc_key} did not count it within {timeout:g} s"
            )
        time.sleep(0.01)
    refused = int(after.get("rejected", 0)) - int(before.get("rejected", 0))
    undecodable = int(after.get("undecodable", 0)) - int(before.get("undecodable", 0))
    if refused + undecodable == 0:
        return None
    if arrived == 1:
        return str(after.get("last_rejection") or "the command could not be decoded")
    raise RpcError(
        f"{arrived} commands arrived on {rpc_key} at once and {refused + undecodable} were "
        f"refused (the last: {after.get('last_rejection', '')!r}); cannot tell about this one"
    )


def write_main(argv: list[str] | None = None) -> int:
    """`archery write KEY JSON`: publish one message of the key's type (like `yarp write`)."""
    parser = _parser(
        "write",
        "Publish one message, given as a JSON object, on a key. On a joint command port "
        "(ROBOT/PART/command:i) the tool then asks the part's rpc:i `counters` verb whether the "
        "robot accepted the command: it exits 1 with the robot's reason when it was refused "
        "(and says so when the owner has no counters verb, or another command arrived at the "
        "same moment). Exit status: 0 delivered (and accepted), 1 nobody subscribes, refused "
        "or no verdict, 2 bad input (unknown key, invalid JSON or message).",
    )
    parser.add_argument("key")
    parser.add_argument("json", help="the message fields as a JSON object")
    args = parser.parse_args(argv)

    def check() -> tuple[NetConfig, type[Message], Message]:
        net = NetConfig.from_args(args)
        message_type = _stream_type(args.key)
        data = loads_finite(args.json, "the message")
        return net, message_type, from_jsonable(data, message_type)

    def body(checked: tuple[NetConfig, type[Message], Message]) -> int:
        net, message_type, message = checked
        spec = port_of(args.key)
        lossless = spec.kind == "events"
        rpc_key = args.key.removesuffix("command:i") + "rpc:i" if spec.kind == "sub" else None
        with Node(None, net) as node:
            pub = node.publisher(args.key, message_type, lossless=lossless)
            if not pub.wait_matched(args.timeout):
                print(f"archery write: nobody subscribes to {args.key}", file=sys.stderr)
                return 1
            before, note = None, "its counters verb gave no counts"
            if rpc_key is not None:
                try:
                    before = _counters(node, rpc_key, args.timeout)
                except RpcError as exc:
                    note = f"{rpc_key} has no command counters ({exc.code})"
            sent = pub.put(message)
            print(json.dumps(to_jsonable(sent)), flush=True)
            if rpc_key is None:
                return 0
            if not isinstance(before, dict):
                print(
                    f"archery write: delivered; whether it was accepted is unknown: {note}",
                    file=sys.stderr,
                )
                return 0
            refusal = _verdict(node, rpc_key, before, args.timeout)
            if refusal is not None:
                print(f"archery write: refused by {rpc_key}: {refusal}", file=sys.stderr)
                return 1
        return 0

    return _run("write", check, body)


def rpc_main(argv: list[str] | None = None) -> int:
    """`archery rpc KEY VERB [JSON]`: call and print the reply; status 1 on error or timeout."""
    parser = _parser("rpc", "call an rpc:i verb and print the result as JSON")
    parser.add_argument("key")
    parser.add_argument("verb")
    parser.add_argument("args", nargs="?", default="{}", help="arguments as a JSON object")
    args = parser.parse_args(argv)

    def check() -> tuple[NetConfig, Verb[Any, Any] | None, Any]:
        net = NetConfig.from_args(args)
        spec = port_of(args.key)
        if spec.kind != "rpc" or spec.message != "RpcRequest":
            raise KeyNameError(f"{args.key} is a {spec.kind} port, not an rpc:i port")
        call_args = loads_finite(args.args, "the arguments")
        if not isinstance(call_args, dict):
            raise DecodeError(f"the arguments must be a JSON object, got {args.args!r}")
        verb = _typed_verb(args.key, args.verb)
        try:  # checked here, before any network work
            call_args = msgspec.convert(call_args, verb.args, strict=True)
        except msgspec.ValidationError as exc:
            raise BadRequest(bad_args_message(verb, exc)) from None
        return net, verb, call_args

    def body(checked: tuple[NetConfig, Verb[Any, Any], Any]) -> int:
        net, verb, call_args = checked
        with Node(None, net) as node:
            reply = node.call_typed(args.key, verb, call_args, timeout=args.timeout)
            result = msgspec.to_builtins(reply, builtin_types=(bytes,))
        print(json.dumps(to_jsonable(result)), flush=True)
        return 0

    return _run("rpc", check, body)


def _typed_verb(key: str, name: str) -> Verb[Any, Any]:
    """The verb `name` of the verb table for `key`.

    Raises:
        KeyNameError: no verb table serves `key`.
        BadRequest: the table has no verb `name` (the message lists its verbs).
    """
    table = table_for_key(key)
    if name not in table.names():
        raise BadRequest(f"{key} has no verb {name!r}; verbs: {', '.join(table.names())}")
    return table[name]


def view_main(argv: list[str] | None = None) -> int:
    """`archery view KEY --out FILE.png`: save the next image on an image port (like yarpview)."""
    parser = _parser("view", "save the next image published on an image port")
    parser.add_argument("key")
    parser.add_argument("--out", required=True, help="image file to write (.png, .jpg, …)")
    add_force_arg(parser)
    args = parser.parse_args(argv)

    def check() -> NetConfig:
        net = NetConfig.from_args(args).with_identity(VIEWER)
        if _stream_type(args.key) is not Image:
            raise KeyNameError(f"{args.key} does not carry images")
        check_output_file(args.out, "--out", IMAGE_EXTENSIONS, force=args.force)
        return net

    def body(net: NetConfig) -> int:
        import cv2

        with Node(None, net) as node:
            sub = node.subscribe(args.key, Image)
            start = time.monotonic()
            image = sub.wait_newer(args.timeout)
            pixels = image.to_numpy()
        bgr = pixels[:, :, ::-1] if pixels.ndim == 3 else pixels
        if not cv2.imwrite(args.out, bgr):
            raise ConfigError(f"could not write {args.out!r}")
        waited = time.monotonic() - start
        print(
            f"{args.out}: {image.width}x{image.height} {image.encoding}, frame {image.frame}, "
            f"waited {waited:.2f} s",
            flush=True,
        )
        return 0

    return _run("view", check, body)
