"""zenoh-ros2-sdk's shared session opened on the mesh's own terms (tests and benchmarks)."""

from __future__ import annotations

import threading

from rosbags.typesys import Stores, get_typestore
from zenoh_ros2_sdk import ZenohSession

from mesh.netflags import NetConfig, open_session

__all__ = ["sdk_session"]


def sdk_session(net: NetConfig) -> ZenohSession:
    """The SDK's shared session, opened on the mesh's own terms (a client of the loopback router
    only) instead of its default peer configuration."""
    sdk = ZenohSession.__new__(ZenohSession)
    sdk.session = open_session(net)
    sdk.store = get_typestore(Stores.EMPTY)
    sdk._registered_types = {}
    sdk._node_counter = 0
    sdk._entity_counter = 0
    sdk._lock = threading.Lock()
    sdk.session_id = str(sdk.session.info.zid())
    sdk.liveliness = sdk.session.liveliness()
    ZenohSession._instance = sdk
    return sdk
