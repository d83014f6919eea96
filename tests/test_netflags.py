"""The common network flags and session opening errors."""

from __future__ import annotations

import argparse
import time

import pytest

from archery.mesh.netflags import DEFAULT_ROUTER, NetConfig, add_network_args, open_session
from archery.mesh.router import free_tcp_endpoint
from archery.protocol.errors import ConfigError


def _parse(*argv: str) -> NetConfig:
    parser = argparse.ArgumentParser()
    add_network_args(parser)
    return NetConfig.from_args(parser.parse_args(list(argv)))


def test_defaults_connect_to_the_local_router() -> None:
    net = _parse()
    assert net == NetConfig(connect=(DEFAULT_ROUTER,), listen=(), mode="client", robot="icubSim")


def test_flags_are_repeatable() -> None:
    net = _parse(
        "--connect",
        "tcp/10.0.0.1:7447",
        "--connect",
        "tcp/router:7447",
        "--listen",
        "tcp/0.0.0.0:0",
        "--mode",
        "client",
        "--robot",
        "icub2",
        "--insecure-network",
    )
    assert net.connect == ("tcp/10.0.0.1:7447", "tcp/router:7447")
    assert net.listen == ("tcp/0.0.0.0:0",) and net.mode == "client" and net.robot == "icub2"


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"connect": ("127.0.0.1:7447",)}, "not a Zenoh endpoint"),
        ({"listen": ("http://x",)}, "not a Zenoh endpoint"),
        ({"mode": "server"}, "not one of peer, client, router"),
        ({"robot": "bad/robot"}, "--robot: invalid robot name"),
        ({"mode": "client", "connect": ()}, "needs at least one --connect"),
    ],
)
def test_invalid_settings_name_the_flag(kwargs: dict, match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        NetConfig(**kwargs)


def test_client_without_router_fails_at_once_with_advice() -> None:
    net = NetConfig(connect=(free_tcp_endpoint(),), mode="client")
    start = time.monotonic()
    with pytest.raises(ConfigError, match="Is a router running there"):
        open_session(net)
    assert time.monotonic() - start < 5


@pytest.mark.parametrize(
    ("listen", "allowed"),
    [
        ("tcp/127.0.0.1:7447", True),
        ("tcp/127.0.0.2:7447", True),
        ("tcp/[::1]:7447", True),
        ("tcp/localhost:7447", True),
        ("unixsock-stream//tmp/archery.sock", True),
        ("tcp/0.0.0.0:7447", False),
        ("tcp/[::]:7447", False),
        ("tcp/192.0.2.7:7447", False),
        ("tcp/robothost:7447", False),
    ],
)
def test_plain_mode_listens_beyond_loopback_only_when_told(listen: str, allowed: bool) -> None:
    """Plain mode trusts every peer: listening where other machines reach it needs
    --insecure-network (or --secure, which has its own tls/ rule)."""
    if allowed:
        assert NetConfig(listen=(listen,)).listen == (listen,)
    else:
        with pytest.raises(ConfigError, match=r"plain mode trusts every peer.*--insecure-network"):
            NetConfig(listen=(listen,))
    assert NetConfig(listen=(listen,), insecure_network=True).listen == (listen,)
