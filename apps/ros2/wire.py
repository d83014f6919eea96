"""rmw_zenoh's wire format (its `docs/design.md`): the data keys, the liveliness tokens of the
graph, the QoS text of a token and the 33-byte attachment of every sample. Pure: no Zenoh.

Data key: `<domain>/<fully qualified name without its leading />/<DDS type>/<RIHS01 hash>`.
Token: `@ros2_lv/<domain>/<zid>/<node id>/<entity id>/<NN|MP|MS|SS|SC>/<enclave>/<namespace>/
<node name>`, then for an endpoint `/<name>/<DDS type>/<hash>/<QoS>`, each name with its `/`
written as `%` (an empty namespace or enclave: `%`). Attachment: sequence number (int64), source
timestamp (int64, ns since the epoch), the GID's length (one byte, 16), the GID (16 bytes)."""

from __future__ import annotations

import re
import struct
from dataclasses import dataclass
from enum import Enum

import xxhash

__all__ = [
    "ADMIN_SPACE",
    "ATTACHMENT_SIZE",
    "MAX_DOMAIN",
    "Attachment",
    "AttachmentError",
    "Endpoint",
    "Kind",
    "NodeId",
    "Qos",
    "check_name",
    "data_key",
    "gid_of",
    "mangle",
]

ADMIN_SPACE = "@ros2_lv"
MAX_DOMAIN = 232  # ROS 2's largest domain id
GID_SIZE = 16
ATTACHMENT_SIZE = 8 + 8 + 1 + GID_SIZE  # bytes
_ATTACHMENT = struct.Struct(f"<qqB{GID_SIZE}s")
_NAME = re.compile(r"^(/[A-Za-z_][A-Za-z0-9_]*)+$")


class Kind(Enum):
    """An entity's kind in its token."""

    NODE = "NN"
    PUBLISHER = "MP"
    SUBSCRIPTION = "MS"
    SERVICE = "SS"
    CLIENT = "SC"


def mangle(name: str) -> str:
    """A name as tokens write it: every `/` as `%`; an empty name (or `/`) as `%`."""
    return "%" if name in ("", "/") else name.replace("/", "%")


def check_name(name: str, what: str) -> str:
    """`name` if it is a fully qualified ROS 2 name (`/a/b_c`: each part a letter or `_`, then
    letters, digits, `_`).

    Raises:
        ValueError: naming `what` and the rule.
    """
    if not _NAME.match(name):
        raise ValueError(
            f"{what} {name!r} is not a ROS 2 name: '/' then parts of letters, digits and '_', "
            "each starting with a letter or '_' (e.g. /icubSim)"
        )
    return name


def data_key(domain: int, name: str, dds_type: str, hash_: str) -> str:
    """The key a topic's samples (or a service's queries) travel on, e.g.
    `0/icubSim/joint_states/sensor_msgs::msg::dds_::JointState_/RIHS01_…`."""
    return f"{domain}/{name.strip('/')}/{dds_type}/{hash_}"


@dataclass(frozen=True)
class Qos:
    """An endpoint's QoS, written into its token as rmw_zenoh does: a setting equal to rmw_zenoh's
    default (reliable, volatile, keep last) is left empty; the depth is always written."""

    depth: int = 10
    best_effort: bool = False
    transient_local: bool = False

    def text(self) -> str:
        """`<reliability>:<durability>:<history>,<depth>:<deadline>:<lifespan>:<liveliness>`,
        e.g. `::,10:,:,:,,`; `2` is best effort, `1` transient local (rmw's enums)."""
        reliability = "2" if self.best_effort else ""
        durability = "1" if self.transient_local else ""
        return f"{reliability}:{durability}:,{self.depth}:,:,:,,"


@dataclass(frozen=True)
class NodeId:
    """A node of the graph: its domain, session (Zenoh id, lowercase hex), id, namespace and
    name."""

    domain: int
    zid: str
    id: int
    namespace: str
    name: str
    enclave: str = ""

    def _head(self, entity: int, kind: Kind) -> str:
        return (
            f"{ADMIN_SPACE}/{self.domain}/{self.zid}/{self.id}/{entity}/{kind.value}/"
            f"{mangle(self.enclave)}/{mangle(self.namespace)}/{mangle(self.name)}"
        )

    def token(self) -> str:
        """The node's token (kind `NN`, its entity id its own id)."""
        return self._head(self.id, Kind.NODE)


@dataclass(frozen=True)
class Endpoint:
    """A publisher, subscription, service or client of a node: its entity id, fully qualified
    name, ROS 2 type (`pkg/msg/Name`, `pkg/srv/Name`), RIHS01 hash and QoS."""

    node: NodeId
    id: int
    kind: Kind
    name: str
    dds_type: str
    hash: str
    qos: Qos

    def token(self) -> str:
        """The endpoint's token."""
        head = self.node._head(self.id, self.kind)
        return f"{head}/{mangle(self.name)}/{self.dds_type}/{self.hash}/{self.qos.text()}"

    def key(self) -> str:
        """The key its data travels on."""
        return data_key(self.node.domain, self.name, self.dds_type, self.hash)

    def gid(self) -> bytes:
        """Its GID (16 bytes), derived from its token: unique on the graph, the same for the
        same entity."""
        return gid_of(self.token())


def gid_of(token: str) -> bytes:
    """The 16-byte GID rmw_zenoh gives the entity whose liveliness token is `token`: the
    XXH3-128 hash (seed 0) of the token's text, its low 64 bits then its high 64 bits, each
    little-endian (its `liveliness_utils.cpp`, `Entity`'s constructor)."""
    return xxhash.xxh3_128_intdigest(token.encode()).to_bytes(GID_SIZE, "little")


class AttachmentError(ValueError):
    """An attachment that is not rmw_zenoh's 33 bytes."""


@dataclass(frozen=True)
class Attachment:
    """A sample's attachment: the sender's sequence number, its source timestamp (ns since the
    epoch) and its GID."""

    sequence: int
    timestamp_ns: int
    gid: bytes

    def encode(self) -> bytes:
        """The 33 bytes (little-endian)."""
        return _ATTACHMENT.pack(self.sequence, self.timestamp_ns, GID_SIZE, self.gid)

    @classmethod
    def decode(cls, data: bytes | None) -> Attachment:
        """The attachment of a received sample.

        Raises:
            AttachmentError: none, or not 33 bytes with a GID length of 16.
        """
        if data is None:
            raise AttachmentError("no attachment (rmw_zenoh sends 33 bytes with every sample)")
        if len(data) != ATTACHMENT_SIZE:
            raise AttachmentError(f"an attachment of {len(data)} bytes, not {ATTACHMENT_SIZE}")
        sequence, stamp, size, gid = _ATTACHMENT.unpack(data)
        if size != GID_SIZE:
            raise AttachmentError(f"an attachment whose GID length is {size}, not {GID_SIZE}")
        return cls(sequence, stamp, gid)
