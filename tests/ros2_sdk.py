"""zenoh-ros2-sdk's shared session opened on the mesh's own terms, and the wait on a condition
(the ROS 2 tests and benchmarks)."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

from rosbags.typesys import Stores, get_typestore
from zenoh_ros2_sdk import ZenohSession

from archery.mesh.netflags import NetConfig, open_session

__all__ = ["sdk_session", "until"]


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


def until(condition: Callable[[], Any], what: str, timeout: float = 60.0) -> Any:
    """The first true value of `condition()`, asked every 50 ms.

    Raises:
        AssertionError: naming `what`, when none came within `timeout` (s).
    """
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = condition()
        if value:
            return value
        time.sleep(0.05)
    raise AssertionError(f"not within {timeout:g} s: {what}")
