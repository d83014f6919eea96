"""The node's endpoints on a Zenoh session: a publisher that sends CDR with rmw_zenoh's
attachment and says when someone subscribes (or, transient local, keeps its last samples for
late joiners, as rmw_zenoh's advanced publisher does), and the counters of what arrived badly."""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter
from collections.abc import Callable
from typing import Any

import zenoh
import zenoh.ext

from archery.apps.ros2 import typestore
from archery.apps.ros2.wire import Attachment, Endpoint

__all__ = ["Counts", "RosPublisher"]

log = logging.getLogger("archery.ros2")


class Counts:
    """Thread-safe counters by name: samples sent per topic, drops and refusals by reason."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._counts: Counter[str] = Counter()

    def add(self, name: str, n: int = 1) -> None:
        """Count `n` more of `name`."""
        with self._lock:
            self._counts[name] += n

    def snapshot(self) -> dict[str, int]:
        """{name: count} now."""
        with self._lock:
            return dict(self._counts)


class RosPublisher:
    """One ROS 2 publisher: its token, its Zenoh publisher and its attachments.

    Args:
        session: the node's session.
        endpoint: what it publishes (an `MP` endpoint).
        ros_type: its message type, e.g. `sensor_msgs/msg/JointState`.
        counts: where it counts each sample sent (under the topic's name).
        on_match: called with True when the first subscriber matches, False after the last
            one left (a volatile publisher only; on Zenoh's thread: keep it short).
    """

    def __init__(
        self,
        session: zenoh.Session,
        endpoint: Endpoint,
        ros_type: str,
        counts: Counts,
        on_match: Callable[[bool], None] | None = None,
    ) -> None:
        self.endpoint = endpoint
        self.ros_type = ros_type
        self.topic = endpoint.name
        self._counts = counts
        self._gid = endpoint.gid()
        self._seq = 0
        self._lock = threading.Lock()
        self._listener: Any = None
        self._pub: Any
        if endpoint.qos.transient_local:
            cache = zenoh.ext.CacheConfig(endpoint.qos.depth)
            self._pub = zenoh.ext.declare_advanced_publisher(
                session,
                endpoint.key(),
                cache=cache,  # sequenced by number: the mesh's sessions keep no timestamps
                sample_miss_detection=zenoh.ext.MissDetectionConfig(
                    heartbeat=None, sporadic_heartbeat=None
                ),
                publisher_detection=True,
            )
        else:
            congestion = zenoh.CongestionControl.DROP
            self._pub = session.declare_publisher(endpoint.key(), congestion_control=congestion)
            if on_match is not None:
                self._listener = self._pub.declare_matching_listener(
                    lambda status: on_match(bool(status.matching))
                )
        self._token = session.liveliness().declare_token(endpoint.token())

    def publish(self, message: Any) -> None:
        """Send `message` (of this publisher's type) as CDR, with the attachment."""
        data = typestore.serialize(message, self.ros_type)
        with self._lock:
            self._seq += 1
            attachment = Attachment(self._seq, time.time_ns(), self._gid).encode()
            self._pub.put(data, attachment=attachment)
        self._counts.add(self.topic)

    def close(self) -> None:
        """Undeclare the token first (the graph sees it leave), then the publisher."""
        for part in (self._token, self._listener, self._pub):
            if part is not None:
                try:
                    part.undeclare()
                except Exception as exc:  # closing goes on whatever one part raises
                    log.debug("%s: %s not undeclared: %s", self.topic, type(part).__name__, exc)
