"""A benchmark's own RPC verb: `echo` returns the θ it is given, served from a verb table like
every verb of the mesh (what the RPC benchmarks time)."""

from __future__ import annotations

from protocol.verbs import Args, Reply, ServedVerbs, Verb, VerbTable

__all__ = ["ECHO", "ECHO_ARGS", "ThetaArgs", "ThetaReply", "echo_verbs"]


class ThetaArgs(Args, frozen=True):
    theta: list[float]


class ThetaReply(Reply, frozen=True):
    theta: list[float]


ECHO = Verb("echo", ThetaArgs, ThetaReply, "returns θ")
ECHO_ARGS = ThetaArgs(theta=[0.17, 0.03, -0.03])
_TABLE = VerbTable("benchmark echo", ("bench/rpc:i",), (ECHO,))


def echo_verbs() -> ServedVerbs:
    """The echo table, bound: what a benchmark's server node serves."""
    return _TABLE.bind({"echo": lambda a: ThetaReply(theta=a.theta)})
