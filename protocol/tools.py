"""Introspection tools, the `yarp` CLI of this mesh: ports, read, write, rpc, view."""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable
from typing import Any

from protocol.codec import from_jsonable, to_jsonable
from protocol.errors import ArcheryError, DecodeError, KeyNameError, RpcTimeout
from protocol.instances import describe_all
from protocol.keys import port_of
from protocol.messages import MESSAGE_TYPES, Image, Message
from protocol.netflags import NetConfig, add_network_args
from protocol.node import Node

__all__ = ["ports_main", "read_main", "rpc_main", "view_main", "write_main"]


def _parser(prog: str, description: str) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog=f"archery {prog}", description=description)
    add_network_args(parser, default_mode="client")
    parser.add_argument("--timeout", type=float, default=5.0, help="seconds to wait (default 5)")
    return parser


def _run(prog: str, body: Callable[[], int]) -> int:
    """Run a tool body, turning the project's errors into a message and exit status 1."""
    try:
        return body()
    except ArcheryError as exc:
        print(f"archery {prog}: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 0


def _stream_type(key: str) -> type[Message]:
    spec = port_of(key)
    if spec.kind in ("rpc", "liveliness"):
        raise KeyNameError(f"{key} is an {spec.kind} port, not a stream; use `archery rpc`")
    return MESSAGE_TYPES[spec.message]


def ports_main(argv: list[str] | None = None) -> int:
    """`archery ports`: live services of the robot and their ports (like `yarp name list`)."""
    parser = _parser("ports", "list live services and their ports")
    parser.add_argument("--json", action="store_true", help="one JSON object per service")
    args = parser.parse_args(argv)

    def body() -> int:
        with Node(None, NetConfig.from_args(args)) as node:
            names = sorted(node.alive(timeout=args.timeout))
            if not names:
                print(f"no live services for robot {node.keys.robot!r}", file=sys.stderr)
                return 1
            for name in names:
                described = describe_all(node.session, node.keys, name, timeout=args.timeout)
                if not described:
                    print(f"{name}: alive, but no describe reply")
                    continue
                many = f"  [{len(described)} instances!]" if len(described) > 1 else ""
                for zid, info in sorted(described.items()):
                    if args.json:
                        print(json.dumps(to_jsonable(info) | {"instance": zid}))
                        continue
                    print(f"{name}  (pid {info.pid} on {info.host}, instance {zid}){many}")
                    for port in info.ports:
                        verbs = info.verbs.get(port.key)
                        extra = f"  verbs: {', '.join(verbs)}" if verbs else ""
                        print(f"  {port.kind:<6} {port.key}  [{port.message}]{extra}")
        return 0

    return _run("ports", body)


def read_main(argv: list[str] | None = None) -> int:
    """`archery read KEY [--count N]`: decoded messages as JSON lines (like `yarp read`)."""
    parser = _parser("read", "print decoded messages from a stream key as JSON lines")
    parser.add_argument("key")
    parser.add_argument("--count", type=int, default=0, help="stop after N messages (0: never)")
    args = parser.parse_args(argv)

    def body() -> int:
        message_type = _stream_type(args.key)
        with Node(None, NetConfig.from_args(args)) as node:
            sub = node.subscribe(args.key, message_type, mode="fifo")
            printed = 0
            while args.count <= 0 or printed < args.count:
                try:
                    message = sub.get(timeout=args.timeout if args.count else None)
                except RpcTimeout:
                    print(
                        f"archery read: no message on {args.key} within {args.timeout:g} s "
                        f"({printed} of {args.count} read, {sub.dropped} malformed dropped)",
                        file=sys.stderr,
                    )
                    return 1
                print(json.dumps(to_jsonable(message)), flush=True)
                printed += 1
        return 0

    return _run("read", body)


def write_main(argv: list[str] | None = None) -> int:
    """`archery write KEY JSON`: publish one message of the key's type (like `yarp write`)."""
    parser = _parser("write", "publish one message, given as a JSON object, on a key")
    parser.add_argument("key")
    parser.add_argument("json", help="the message fields as a JSON object")
    args = parser.parse_args(argv)

    def body() -> int:
        message_type = _stream_type(args.key)
        try:
            data = json.loads(args.json)
        except json.JSONDecodeError as exc:
            raise DecodeError(f"the message is not valid JSON: {exc}") from None
        message = from_jsonable(data, message_type)
        lossless = port_of(args.key).kind == "events"
        with Node(None, NetConfig.from_args(args)) as node:
            pub = node.publisher(args.key, message_type, lossless=lossless)
            if not pub.wait_matched(args.timeout):
                print(f"archery write: nobody subscribes to {args.key}", file=sys.stderr)
                return 1
            sent = pub.put(message)
            print(json.dumps(to_jsonable(sent)))
        return 0

    return _run("write", body)


def rpc_main(argv: list[str] | None = None) -> int:
    """`archery rpc KEY VERB [JSON]`: call and print the reply; status 1 on error or timeout."""
    parser = _parser("rpc", "call an rpc:i verb and print the result as JSON")
    parser.add_argument("key")
    parser.add_argument("verb")
    parser.add_argument("args", nargs="?", default="{}", help="arguments as a JSON object")
    args = parser.parse_args(argv)

    def body() -> int:
        spec = port_of(args.key)
        if spec.kind != "rpc" or spec.message != "RpcRequest":
            raise KeyNameError(f"{args.key} is a {spec.kind} port, not an rpc:i port")
        try:
            call_args: Any = json.loads(args.args)
        except json.JSONDecodeError as exc:
            raise DecodeError(f"the arguments are not valid JSON: {exc}") from None
        if not isinstance(call_args, dict):
            raise DecodeError(f"the arguments must be a JSON object, got {args.args!r}")
        with Node(None, NetConfig.from_args(args)) as node:
            result = node.call(args.key, args.verb, call_args, timeout=args.timeout)
        print(json.dumps(result))
        return 0

    return _run("rpc", body)


def view_main(argv: list[str] | None = None) -> int:
    """`archery view KEY --out FILE.png`: save the next image on an image port (like yarpview)."""
    parser = _parser("view", "save the next image published on an image port")
    parser.add_argument("key")
    parser.add_argument("--out", required=True, help="PNG file to write")
    args = parser.parse_args(argv)

    def body() -> int:
        import cv2

        if _stream_type(args.key) is not Image:
            raise KeyNameError(f"{args.key} does not carry images")
        with Node(None, NetConfig.from_args(args)) as node:
            sub = node.subscribe(args.key, Image)
            start = time.monotonic()
            image = sub.wait_newer(args.timeout)
            pixels = image.to_numpy()
        bgr = pixels[:, :, ::-1] if pixels.ndim == 3 else pixels
        if not cv2.imwrite(args.out, bgr):
            raise KeyNameError(f"could not write {args.out!r}: use a .png path in a folder")
        waited = time.monotonic() - start
        print(
            f"{args.out}: {image.width}x{image.height} {image.encoding}, frame {image.frame}, "
            f"waited {waited:.2f} s"
        )
        return 0

    return _run("view", body)
