"""The mesh library: key names, message types, codec, node base and CLI tools.

It is the only code the services share.
"""

from protocol.codec import decode, encode
from protocol.errors import (
    ArcheryError,
    BadRequest,
    ConfigError,
    DecodeError,
    KeyNameError,
    RpcError,
    RpcTimeout,
)
from protocol.keys import Keys, port_of
from protocol.netflags import NetConfig, add_network_args
from protocol.node import Node, shutdown_on_signals

__all__ = [
    "ArcheryError",
    "BadRequest",
    "ConfigError",
    "DecodeError",
    "KeyNameError",
    "Keys",
    "NetConfig",
    "Node",
    "RpcError",
    "RpcTimeout",
    "add_network_args",
    "decode",
    "encode",
    "port_of",
    "shutdown_on_signals",
]
