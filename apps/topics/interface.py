"""`archery interface KEY`: a port's message type, and for an `rpc:i` key each verb's argument
and reply schema (field, type, constraint, default), like `ros2 interface show`.

The schemas come from the live service serving KEY (its `describe` reply carries them), or,
when none is alive (or with --offline), from this installation's verb tables
(`protocol.verbs`), e.g. `archery interface icubSim/cartesianController/archery/rpc:i`.
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

import msgspec

from archery.mesh.acl import VIEWER
from archery.mesh.cliargs import ArgumentParser, seconds
from archery.mesh.netflags import NetConfig, add_network_args
from archery.protocol.codec import decode
from archery.protocol.errors import ArcheryError
from archery.protocol.exit_status import for_error
from archery.protocol.keys import port_of
from archery.protocol.messages import MESSAGE_TYPES, Describe
from archery.protocol.verbs import table_for_key
from archery.protocol.verbs.schema import fields_of, render_verb

__all__ = ["interface_lines", "interface_main", "live_interfaces", "message_lines"]


def message_lines(message: str, indent: str = "") -> list[str]:
    """The fields of a message type (by name), one line each: field, type, default."""
    message_type = MESSAGE_TYPES.get(message)
    if message_type is None:
        return [f"{indent}{message}"]
    name, rows = fields_of(msgspec.json.schema(message_type))
    width = max((len(r[0]) for r in rows), default=0)
    typew = max((len(r[1]) for r in rows), default=0)
    lines = [f"{indent}{name} (msgpack map tagged type={name!r})"]
    lines += [f"{indent}  {f.ljust(width)}  {t.ljust(typew)}  {p}" for f, t, p in rows]
    return lines


def interface_lines(interfaces: dict[str, Any], indent: str = "") -> list[str]:
    """Every verb of one rpc key (verb -> {doc, args, reply}), sorted by name."""
    lines: list[str] = []
    for verb in sorted(interfaces):
        lines += render_verb(verb, interfaces[verb], indent)
    return lines


def live_interfaces(node: Any, key: str, timeout: float) -> tuple[str, Describe] | None:
    """(service, its Describe) of the live service that serves `key`, or None."""
    for name in sorted(node.alive(timeout=timeout)):
        for reply in node.session.get(node.keys.describe(name), timeout=timeout):
            if reply.ok is None:
                continue
            info = decode(reply.ok.payload.to_bytes(), Describe)
            if any(port.key == key for port in info.ports):
                return name, info
    return None


def _show(key: str, args: argparse.Namespace) -> int:
    spec = port_of(key)
    live = None
    if not args.offline:
        try:
            from archery.mesh.node import Node

            with Node(None, NetConfig.from_args(args).with_identity(VIEWER)) as node:
                live = live_interfaces(node, key, args.timeout)
        except ArcheryError as exc:
            print(f"archery interface: no live mesh ({exc}); local tables", file=sys.stderr)
    if spec.kind != "rpc" or spec.message != "RpcRequest":
        if args.json:
            print(json.dumps(msgspec.json.schema(MESSAGE_TYPES[spec.message])))
        else:
            print(f"{key}  [{spec.kind}]")
            print("\n".join(message_lines(spec.message, "  ")))
        return 0
    if live is not None and live[1].interfaces.get(key):
        source, interfaces = f"live: service {live[0]}", live[1].interfaces[key]
    elif live is not None:
        verbs = ", ".join(live[1].verbs.get(key, [])) or "none"
        print(f"{key}  [rpc, live: service {live[0]}]: untyped verbs: {verbs}")
        return 0
    else:
        table = table_for_key(key)
        source, interfaces = f"local tables: {table.title}", table.schemas
    if args.json:
        print(json.dumps(interfaces))
        return 0
    print(f"{key}  [rpc, RpcRequest -> RpcReply; {source}]")
    print("\n".join(interface_lines(interfaces, "  ")))
    return 0


def interface_main(argv: list[str] | None = None) -> int:
    """`archery interface KEY [--offline] [--json]`: print the port's interface."""
    parser = ArgumentParser(
        prog="archery interface",
        description="a port's message type, and each rpc:i verb's argument and reply schema",
    )
    add_network_args(parser, default_mode="client")
    parser.add_argument("--timeout", type=seconds, default=2.0, help="seconds to wait (default 2)")
    parser.add_argument("key", help="a full key, e.g. icubSim/cartesianController/archery/rpc:i")
    parser.add_argument("--offline", action="store_true", help="use the local verb tables only")
    parser.add_argument("--json", action="store_true", help="print the JSON schemas")
    args = parser.parse_args(argv)
    try:
        port_of(args.key)
        NetConfig.from_args(args).with_identity(VIEWER)
    except ArcheryError as exc:  # bad input
        print(f"archery interface: {exc}", file=sys.stderr)
        return 2
    try:
        return _show(args.key, args)
    except ArcheryError as exc:
        print(f"archery interface: {exc}", file=sys.stderr)
        return for_error(exc.code)
