"""A benchmark's own RPC verb: `echo` returns the θ it is given, served from a verb table like
every verb of the mesh (what the RPC benchmarks time)."""

from __future__ import annotations

from archery.mesh.acl import roles
from archery.protocol.keys import split_verb
from archery.protocol.verbs import Args, Reply, ServedVerbs, Verb, VerbTable

__all__ = [
    "ECHO",
    "ECHO_ARGS",
    "ThetaArgs",
    "ThetaReply",
    "echo_verbs",
    "granted_verbs",
    "named_echo",
]


class ThetaArgs(Args, frozen=True):
    theta: list[float]


class ThetaReply(Reply, frozen=True):
    theta: list[float]


ECHO = Verb("echo", ThetaArgs, ThetaReply, "returns θ")
ECHO_ARGS = ThetaArgs(theta=[0.17, 0.03, -0.03])
_TABLE = VerbTable("benchmark echo", ("bench/rpc:i",), (ECHO,))


def echo_verbs() -> ServedVerbs:
    """The echo table, bound: what a benchmark's server node serves."""
    return _TABLE.bind_names({"echo": lambda a: ThetaReply(theta=a.theta)})


def named_echo(name: str) -> tuple[Verb, ServedVerbs]:
    """The echo under the verb name `name` (e.g. one the secure router's ACL grants the caller:
    `granted_verbs`): the verb to call, and its table bound, what the server node serves."""
    verb = Verb(name, ThetaArgs, ThetaReply, "returns θ")
    table = VerbTable("benchmark echo", ("bench/rpc:i",), (verb,))
    return verb, table.bind_names({name: lambda a: ThetaReply(theta=a.theta)})


def granted_verbs(robot: str, caller: str, port: str) -> list[str]:
    """The verbs the secure router's ACL (`mesh.acl.roles` of robot prefix `robot`) lets the
    identity `caller` call on the `rpc:i` port `port` (its calls travel on `PORT/VERB`), in
    the order the ACL lists them.

    Raises:
        RuntimeError: it grants `caller` none there.
    """
    # a verb that names its caller is granted as VERB~CALLER: the client names it itself
    chunks = [c.rpartition("/")[2] for c in roles(robot)[caller].call if c.startswith(f"{port}/")]
    names = list(dict.fromkeys(split_verb(chunk)[0] for chunk in chunks))
    if not names:
        raise RuntimeError(f"the ACL grants {caller} no verb on {port}")
    return names
