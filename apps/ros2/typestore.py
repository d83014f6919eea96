"""The ROS 2 message types the node speaks: rosbags' Jazzy typestore (CDR, RIHS01 type hashes)
and `std_srvs/srv/Trigger`, which rosbags does not ship, registered from its IDL.

A service's type hash covers its request, response and event messages; the event's
`service_msgs/msg/ServiceEventInfo` carries `client_gid` as `uint8[16]` in ROS 2's IDL, which
the services' own store declares so (rosbags' Jazzy store reads it as `char[16]`)."""

from __future__ import annotations

import functools
from typing import Any

from rosbags.typesys import Stores, get_types_from_idl, get_typestore
from rosbags.typesys.store import Typestore

__all__ = [
    "TRIGGER",
    "dds_type_name",
    "deserialize",
    "messages",
    "new",
    "serialize",
    "type_hash",
]

TRIGGER = "std_srvs/srv/Trigger"
_TIME = "builtin_interfaces/msg/Time"
_TRIGGER_IDL = """
module service_msgs { module msg {
  struct ServiceEventInfo {
    uint8 event_type; builtin_interfaces::msg::Time stamp; uint8 client_gid[16];
    int64 sequence_number;
  };
}; };
module std_srvs { module srv {
  struct Trigger_Request { uint8 structure_needs_at_least_one_member; };
  struct Trigger_Response { boolean success; string message; };
  struct Trigger_Event {
    service_msgs::msg::ServiceEventInfo info;
    sequence<std_srvs::srv::Trigger_Request, 1> request;
    sequence<std_srvs::srv::Trigger_Response, 1> response;
  };
  struct Trigger {
    std_srvs::srv::Trigger_Request request_message;
    std_srvs::srv::Trigger_Response response_message;
    std_srvs::srv::Trigger_Event event_message;
  };
}; };
"""


@functools.cache
def messages() -> Typestore:
    """rosbags' typestore of ROS 2 Jazzy's standard messages."""
    return get_typestore(Stores.ROS2_JAZZY)


@functools.cache
def _services() -> Typestore:
    store = get_typestore(Stores.EMPTY)
    store.register({_TIME: messages().fielddefs[_TIME]})
    store.register(get_types_from_idl(_TRIGGER_IDL))
    return store


def _store(ros_type: str) -> Typestore:
    return _services() if ros_type.startswith(TRIGGER) else messages()


def dds_type_name(ros_type: str) -> str:
    """The DDS-style name rmw_zenoh puts in keys, e.g. `sensor_msgs::msg::dds_::JointState_` for
    `sensor_msgs/msg/JointState`."""
    package, kind, name = ros_type.split("/")
    return f"{package}::{kind}::dds_::{name}_"


@functools.cache
def type_hash(ros_type: str) -> str:
    """The type's RIHS01 hash, as ROS 2 computes it (rosbags' `hash_rihs01`)."""
    return _store(ros_type).hash_rihs01(ros_type)


def new(ros_type: str, **fields: Any) -> Any:
    """A message of `ros_type` (rosbags' class) with `fields`."""
    return _store(ros_type).types[ros_type](**fields)


def serialize(message: Any, ros_type: str) -> bytes:
    """`message` as CDR (little-endian, with its encapsulation header)."""
    return bytes(_store(ros_type).serialize_cdr(message, ros_type))


def deserialize(data: bytes, ros_type: str) -> Any:
    """A CDR payload as a message of `ros_type`.

    Raises:
        Exception: whatever rosbags raises for bytes that are not such a message.
    """
    return _store(ros_type).deserialize_cdr(data, ros_type)
