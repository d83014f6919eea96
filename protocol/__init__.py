"""The contract of the mesh, and only it: key names (`keys`), message types (`messages`), the
RPC verbs of every service with their argument and reply types (`verbs`), the codec, the error
codes, the shared robot facts (`robotspec`, `parts`), θ's wire and box types (`theta`) and the
check of vectors (`vectors`).
No Zenoh, no argparse, no I/O: a reader learns every message and verb of the mesh here. The
runtime that carries them is `mesh`.
"""

from archery.protocol.codec import decode, encode
from archery.protocol.errors import (
    ArcheryError,
    BadRequest,
    ConfigError,
    DecodeError,
    KeyNameError,
    RpcError,
    RpcTimeout,
)
from archery.protocol.keys import Keys, port_of

__all__ = [
    "ArcheryError",
    "BadRequest",
    "ConfigError",
    "DecodeError",
    "KeyNameError",
    "Keys",
    "RpcError",
    "RpcTimeout",
    "decode",
    "encode",
    "port_of",
]
