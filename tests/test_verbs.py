"""Typed RPC verbs: every verb's argument and reply types round-trip and enforce their
constraints (table-driven over every verb table), and the RPC server validates over a real router.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from typing import Any

import msgspec
import numpy as np
import pytest

from archery.mesh.netflags import NetConfig
from archery.mesh.node import Node
from archery.mesh.rpc_server import bad_args_message
from archery.protocol.codec import validation_text
from archery.protocol.errors import RpcError
from archery.protocol.messages import Image, RpcReply
from archery.protocol.theta import THETA_BOX
from archery.protocol.verbs import TABLES, NoArgs, Reply, Verb, VerbTable, table_for_key
from archery.protocol.verbs import controller as cv
from tests.conftest import archery
from tests.rpc import rpc_call

VERBS = [(table, verb) for table in TABLES for verb in table]
STRUCTS = sorted(
    {t for _, v in VERBS for t in (v.args, v.reply)}, key=lambda t: (t.__module__, t.__name__)
)


# -- samples generated from each type's JSON schema ------------------------------------------------
def _sample(schema: dict[str, Any], defs: dict[str, Any]) -> Any:
    if "$ref" in schema:
        body = defs[schema["$ref"].rsplit("/", 1)[-1]]
        if body.get("title") == "Image":
            return msgspec.to_builtins(
                Image.from_numpy(np.zeros((2, 3, 3), np.uint8)), builtin_types=(bytes,)
            )
        if body.get("title") == "ThetaBox":  # low < high: a schema cannot say it
            return msgspec.to_builtins(THETA_BOX)
        return {k: _sample(p, defs) for k, p in body.get("properties", {}).items()}
    if "anyOf" in schema:
        options = [s for s in schema["anyOf"] if s.get("type") != "null"]
        return _sample(options[0], defs) if options else None
    if "enum" in schema:
        return schema["enum"][0]
    kind = schema.get("type")
    if kind == "number":
        low = schema.get("minimum", schema.get("exclusiveMinimum", 0.0))
        high = schema.get("maximum", schema.get("exclusiveMaximum", low + 1.0))
        return (low + high) / 2
    if kind == "integer":
        return schema.get("minimum", 1)
    if kind == "string":
        return b"\x89PNG" if schema.get("contentEncoding") == "base64" else "x"
    if kind == "boolean":
        return True
    if kind == "array":
        return [_sample(schema.get("items", {}), defs)] * max(1, schema.get("minItems", 1))
    if kind == "object":
        values = schema.get("additionalProperties")
        return {"k": _sample(values, defs)} if isinstance(values, dict) else {"k": 1}
    return 1  # any


def sample(struct: type[msgspec.Struct]) -> dict[str, Any]:
    """A valid instance of `struct` as plain data, every field (optional ones too) set."""
    schema = msgspec.json.schema(struct)
    return _sample(schema, schema.get("$defs", {}))


def _top(struct: type[msgspec.Struct]) -> tuple[dict[str, Any], dict[str, Any], set[str]]:
    schema = msgspec.json.schema(struct)
    defs = schema.get("$defs", {})
    body = defs[schema["$ref"].rsplit("/", 1)[-1]]
    return body.get("properties", {}), defs, set(body.get("required", ()))


def _numbers(prop: dict[str, Any]) -> list[dict[str, Any]]:
    """The number schemas a property may hold directly (in an anyOf too)."""
    options = prop.get("anyOf", [prop])
    return [o for o in options if o.get("type") in ("number", "integer")]


# -- bad argument cases: (verb, args, the path the error must name, what else it must say) -----
def _cases() -> Iterator[Any]:
    seen: set[type] = set()
    for _, verb in VERBS:
        if verb.args in seen:
            continue
        seen.add(verb.args)
        base = sample(verb.args)
        tag = f"{verb.args.__name__}"
        yield pytest.param(
            verb, {**base, "bogus": 1}, "$", "unknown field `bogus`", id=f"{tag}-unknown"
        )
        props, _, required = _top(verb.args)
        for name, prop in props.items():
            if name in required:
                missing = {k: v for k, v in base.items() if k != name}
                yield pytest.param(
                    verb,
                    missing,
                    "$",
                    f"missing required field `{name}`",
                    id=f"{tag}-{name}-missing",
                )
            textual = prop.get("type") == "string" or "string" in str(prop) or "enum" in prop
            wrong = 5 if textual else "text"
            if prop.get("type") == "object" and "additionalProperties" not in prop:
                wrong = "text"
            yield pytest.param(
                verb, {**base, name: wrong}, f"$.{name}", "Expected", id=f"{tag}-{name}-type"
            )
            for number in _numbers(prop):
                yield pytest.param(
                    verb, {**base, name: True}, f"$.{name}", "got `bool`", id=f"{tag}-{name}-bool"
                )
                if number["type"] == "number":
                    for bad in (math.nan, math.inf, -math.inf):
                        yield pytest.param(
                            verb, {**base, name: bad}, f"$.{name}", "", id=f"{tag}-{name}-{bad}"
                        )
                for bound, delta in (
                    ("minimum", -1),
                    ("exclusiveMinimum", 0),
                    ("maximum", 1),
                    ("exclusiveMaximum", 0),
                ):
                    if bound in number:
                        value = number[bound] + delta
                        if number["type"] == "integer":
                            value = int(value)
                        yield pytest.param(
                            verb,
                            {**base, name: value},
                            f"$.{name}",
                            _num(number[bound]),
                            id=f"{tag}-{name}-{bound}",
                        )
            if prop.get("type") == "array" and prop.get("items", {}).get("type") == "number":
                elements = list(base[name])
                elements[0] = math.nan
                yield pytest.param(
                    verb,
                    {**base, name: elements},
                    f"$.{name}[0]",
                    "finite",
                    id=f"{tag}-{name}-nan-item",
                )
                if "maxItems" in prop:
                    longer = list(base[name]) * (prop["maxItems"] + 1)
                    yield pytest.param(
                        verb, {**base, name: longer}, f"$.{name}", "length", id=f"{tag}-{name}-long"
                    )


def _num(value: float) -> str:
    return f"{value:g}" if isinstance(value, float) else str(value)


@pytest.mark.parametrize(
    "struct", STRUCTS, ids=lambda t: f"{t.__module__.rsplit('.', 1)[-1]}.{t.__name__}"
)
def test_every_type_round_trips(struct: type[msgspec.Struct]) -> None:
    data = sample(struct)
    value = msgspec.convert(data, struct, strict=True)
    wire = msgspec.msgpack.encode(value)
    assert msgspec.msgpack.decode(wire, type=struct) == value
    assert msgspec.convert(msgspec.to_builtins(value, builtin_types=(bytes,)), struct) == value


@pytest.mark.parametrize(("table", "verb"), VERBS, ids=[f"{t.ports[0]}:{v.name}" for t, v in VERBS])
def test_every_verb_refuses_unknown_fields_and_has_docs(table: Any, verb: Verb[Any, Any]) -> None:
    assert verb.doc and table_for_key(f"icubSim/{table.ports[0]}") is table
    with pytest.raises(msgspec.ValidationError, match="unknown field `nope`"):
        verb.args_decoder.decode(msgspec.msgpack.encode({"nope": 1}))
    schema = verb.schema()
    assert schema["args"]["$defs"][verb.args.__name__]["additionalProperties"] is False


@pytest.mark.parametrize(("verb", "args", "path", "says"), list(_cases()))
def test_bad_arguments_name_the_field(
    verb: Verb[Any, Any], args: dict[str, Any], path: str, says: str
) -> None:
    with pytest.raises(msgspec.ValidationError) as info:
        verb.args_decoder.decode(msgspec.msgpack.encode(args))
    message = bad_args_message(verb, info.value)
    assert message.startswith(f"invalid argument of {verb.name} at `{path}")
    assert says in message
    if path != "$":  # the allowed values of the field follow
        field = path[2:].split("[")[0]
        assert f"; {field} must be " in message


def test_range_errors_state_the_whole_range() -> None:
    verb = cv.ARCHERY_VERBS["setTrajTime"]
    with pytest.raises(msgspec.ValidationError) as info:
        verb.args_decoder.decode(msgspec.msgpack.encode({"time": 61}))
    assert bad_args_message(verb, info.value) == (
        "invalid argument of setTrajTime at `$.time`: Expected `float` <= 60.0; "
        "time must be float in [0.05, 60] (s, sim time)"
    )


# -- the server, over a real router ----------------------------------------------------------------
class SoonReply(Reply, frozen=True):
    """What another implementation of getTrajTime might answer: not a TrajTimeReply."""

    time: str


OTHER = VerbTable(
    "another controller",
    ("cartesianController/left_arm/rpc:i",),
    (
        Verb("getTrajTime", NoArgs, SoonReply, "the time, in words"),
        Verb("echo", cv.SetTrajTimeArgs, cv.TrajTimeReply, "its argument"),
    ),
)


@pytest.fixture
def served(net: NetConfig) -> Iterator[tuple[Node, str, str]]:
    """The archery controller's verbs (trivial handlers) and, on another key, a table whose
    getTrajTime replies another type; a client node."""
    traj = {"time": 1.0}

    def set_time(args: cv.SetTrajTimeArgs) -> cv.TrajTimeReply:
        traj["time"] = args.time
        return cv.TrajTimeReply(time=args.time)

    def unused(args: Any) -> Any:
        raise RpcError("not served here", code="unsupported")

    with Node("verbs", net) as server, Node(None, net) as client:
        key = server.keys.cartesian_rpc("archery")
        other_key = server.keys.cartesian_rpc("left_arm")
        handlers = {
            "setTrajTime": set_time,
            "getTrajTime": lambda a: cv.TrajTimeReply(time=traj["time"]),
            "posture": unused,
            "status": lambda a: "not a reply",
        }
        server.serve(key, cv.ARCHERY_VERBS.bind_names(handlers))
        other = {
            "getTrajTime": lambda a: SoonReply(time="soon"),
            "echo": lambda a: cv.TrajTimeReply(time=a.time),
        }
        server.serve(other_key, OTHER.bind_names(other))
        server.ready()
        client.wait_alive(["verbs"], 10)  # its token follows both ports to the router
        yield client, key, other_key


def _raw(args_bytes: bytes, verb: str = "setTrajTime") -> bytes:
    head = msgspec.msgpack.encode({"type": "RpcRequest", "verb": verb})
    return b"\x83" + head[1:] + msgspec.msgpack.encode("args") + args_bytes


def test_server_answers_bad_request_naming_verb_field_and_range(served: Any) -> None:
    client, key, _ = served
    reply = client.call_typed(key, cv.ARCHERY_VERBS["setTrajTime"], cv.SetTrajTimeArgs(time=0.5))
    assert reply == cv.TrajTimeReply(time=0.5)
    assert rpc_call(client, key, "getTrajTime") == {"time": 0.5}
    for args, says in (
        (
            {"time": 0.0},
            r"setTrajTime at `\$.time`: Expected `float` >= 0.05; "
            r"time must be float in \[0.05, 60\]",
        ),
        ({"time": True}, r"`\$.time`: Expected `float`, got `bool`"),
        ({"time": "1"}, r"`\$.time`: Expected `float`, got `str`"),
        ({}, "missing required field `time`"),
        ({"time": 1.0, "speed": 2}, "unknown field `speed`; arguments of setTrajTime: time"),
    ):
        with pytest.raises(RpcError, match=says) as info:
            rpc_call(client, key, "setTrajTime", args)
        assert info.value.code == "bad_request"
    for bad in (math.nan, math.inf):  # out of any range
        payload = _raw(b"\x81\xa4time" + msgspec.msgpack.encode(bad))
        reply = client.request(key, payload, verb="setTrajTime")
        assert not reply.ok and reply.code == "bad_request"
        assert "`$.time`" in reply.message and "time must be float in [0.05, 60]" in reply.message
        theta = msgspec.msgpack.encode({"theta": [0.1, bad, 0.0]})
        reply = client.request(key, _raw(theta, "posture"), verb="posture")
        assert not reply.ok and reply.code == "bad_request"
        assert "`$.theta[1]`: Expected a finite number" in reply.message
    assert rpc_call(client, key, "getTrajTime") == {"time": 0.5}  # nothing reached the handler


def test_server_refuses_deep_nesting_and_untagged_requests(served: Any) -> None:
    client, key, other_key = served
    deep = b"\x81\xa1a" * 100_000 + b"\x80"  # past every Python's recursion limit (3.13: ~10,000)
    for k, verb in ((key, "setTrajTime"), (other_key, "echo")):
        reply = client.request(k, _raw(deep, verb), verb=verb, timeout=5)
        assert not reply.ok and reply.code == "bad_message" and "deep" in reply.message
    untagged = msgspec.msgpack.encode({"verb": "getTrajTime", "args": {}})
    reply = client.request(key, untagged, verb="getTrajTime", timeout=5)
    assert not reply.ok and reply.code == "bad_message"
    assert "no `type` field" in reply.message and "RpcRequest" in reply.message
    reply = client.request(
        key, msgspec.msgpack.encode({"type": "RpcReply", "ok": True}), verb="getTrajTime"
    )
    assert not reply.ok and reply.code == "bad_message"
    assert rpc_call(client, key, "getTrajTime", timeout=5) == {"time": 1.0}  # still serving


def test_replies_are_typed_at_both_ends(served: Any) -> None:
    client, key, other_key = served
    with pytest.raises(RpcError, match="handler returned str, not ArcheryStatusReply") as info:
        rpc_call(client, key, "status")
    assert info.value.code == "internal"
    with pytest.raises(RpcError, match=r"not a TrajTimeReply.*\$.result.time") as info:
        client.call_typed(other_key, cv.ARCHERY_VERBS["getTrajTime"])
    assert info.value.code == "bad_reply"
    with pytest.raises(RpcError, match="not served here") as info:
        client.call_typed(key, cv.ARCHERY_VERBS["posture"], cv.PostureArgs(theta=[0.1, 0.0, 0.0]))
    assert info.value.code == "unsupported"
    with pytest.raises(TypeError, match="takes SetTrajTimeArgs"):
        client.call_typed(key, cv.ARCHERY_VERBS["setTrajTime"], NoArgs())


def test_describe_carries_each_verbs_schema(served: Any) -> None:
    client, key, _ = served
    out = archery("interface", key, "--connect", client.net.connect[0], "--robot", client.net.robot)
    assert out.returncode == 0, out.stderr
    assert "live: service verbs" in out.stdout
    assert "time  float in [0.05, 60] (s, sim time)  required" in out.stdout
    assert "theta    list[finite float] length 3" in out.stdout
    out = archery(
        "ports", "--verbose", "--connect", client.net.connect[0], "--robot", client.net.robot
    )
    assert out.returncode == 0, out.stderr
    assert "reply: PostureReply" in out.stdout and "reply: SoonReply" in out.stdout


def test_interface_offline_from_the_local_tables() -> None:
    out = archery("interface", "icubSim/cartesianController/archery/rpc:i", "--offline")
    assert out.returncode == 0, out.stderr
    assert "local tables" in out.stdout and "args: PostureArgs" in out.stdout
    assert "timeout  float in [0.1, 3600] (wall s) | null" in out.stdout
    out = archery("interface", "icubSim/left_arm/state:o", "--offline")
    assert out.returncode == 0 and "JointState" in out.stdout and "position" in out.stdout
    out = archery("interface", "icubSim/nowhere/rpc:i", "--offline")
    assert out.returncode == 2 and "unknown key" in out.stderr


def test_every_served_reply_is_an_rpc_reply_struct() -> None:
    reply = RpcReply(ok=True, result=cv.TrajTimeReply(time=1.0))
    decoded = cv.ARCHERY_VERBS["getTrajTime"].reply_decoder.decode(msgspec.msgpack.encode(reply))
    assert decoded.result == cv.TrajTimeReply(time=1.0)


def test_theta_is_checked_where_it_is_decoded_not_where_it_is_built() -> None:
    """θ enters a process where a message holding it is decoded: there NaN and inf are refused
    in words; the sender's build checks nothing (it is not where θ enters), while the other
    floats of the same message are still checked on both sides."""
    args = cv.PostureArgs(theta=[0.17, math.nan, -0.03])
    with pytest.raises(msgspec.ValidationError) as info:
        cv.POSTURE.args_decoder.decode(msgspec.msgpack.encode(args))
    assert validation_text(info.value) == "Expected a finite number - at `$.theta[1]`"
    assert "at `$.theta[1]`: Expected a finite number" in bad_args_message(cv.POSTURE, info.value)
    with pytest.raises(ValueError, match=r"\$.timeout is nan"):
        cv.PostureArgs(theta=[0.17, 0.03, -0.03], timeout=math.nan)
    for bad in (math.inf, -math.inf):
        payload = msgspec.msgpack.encode({"theta": [bad, 0.03, -0.03]})
        with pytest.raises(msgspec.ValidationError) as info:
            cv.POSTURE.args_decoder.decode(payload)
        assert validation_text(info.value).startswith("Expected a finite number")
