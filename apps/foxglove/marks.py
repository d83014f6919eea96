"""What the bridge draws and writes for Foxglove from the mesh's messages: the detector's marks on
the camera's frame (`foxglove.ImageAnnotations`), a rollout as a JSON record a Plot panel reads,
and a world event as a `foxglove.Log` line. Pixels are image columns and rows; times ns since
the epoch."""

from __future__ import annotations

import math
from typing import Any

from foxglove_schemas_protobuf.ImageAnnotations_pb2 import ImageAnnotations
from foxglove_schemas_protobuf.Log_pb2 import Log

from archery.apps.topics.foxglove_records import stamp
from archery.protocol.journal_records import DoneRecord
from archery.protocol.messages import Detection, Rollout, WorldEvent

__all__ = ["ROLLOUT_SCHEMA", "event_log", "image_marks", "rollout_record"]

ELLIPSE_POINTS = 72  # points of the line loop that draws a ring's ellipse
_TARGET = (1.0, 1.0, 1.0, 1.0)  # white: the target's centre and its rings
_ARROW = (0.0, 1.0, 0.0, 1.0)  # green: the arrow's tip
_MARK_PX = 24.0  # diameter of a centre or tip mark (px)

#: The JSON schema of a rollout record (`rollout_record`): what Foxglove's Plot panel reads.
ROLLOUT_SCHEMA: dict[str, Any] = {
    "type": "object",
    "title": "archery.RolloutPoint",
    "properties": {
        "timestamp": {
            "type": "object",
            "title": "time",
            "properties": {"sec": {"type": "integer"}, "nsec": {"type": "integer"}},
        },
        "session": {"type": "string"},
        "rollout": {"type": "integer", "description": "done rollouts of the session, from 1"},
        "theta": {"type": "array", "items": {"type": "number"}, "description": "m"},
        "r": {"type": "array", "items": {"type": "number"}, "description": "m: right, up"},
        "distance": {"type": "number", "description": "m: ‖r‖"},
        "hit": {"type": "boolean"},
    },
}


def _colour(target: Any, rgba: tuple[float, float, float, float]) -> None:
    target.r, target.g, target.b, target.a = rgba


def _ellipse(ring: list[float]) -> list[tuple[float, float]]:
    """Points around an ellipse [centre column, centre row, full axes (px), angle (deg)]."""
    cx, cy, a, b, angle = ring
    cos, sin = math.cos(math.radians(angle)), math.sin(math.radians(angle))
    points = []
    for i in range(ELLIPSE_POINTS):
        t = 2 * math.pi * i / ELLIPSE_POINTS
        x, y = 0.5 * a * math.cos(t), 0.5 * b * math.sin(t)
        points.append((cx + x * cos - y * sin, cy + x * sin + y * cos))
    return points


def image_marks(detection: Detection) -> bytes:
    """The detection's marks, stamped with its frame's stamp (so the Image panel lays them on
    that frame): the fitted rings, the target's centre, the arrow's tip and the confidences."""
    message = ImageAnnotations()
    ns = round(detection.frame_stamp * 1e9)
    for ring in detection.rings or []:
        loop = message.points.add(type=2, thickness=2.0)  # LINE_LOOP
        stamp(loop.timestamp, ns)
        _colour(loop.outline_color, _TARGET)
        for x, y in _ellipse(ring):
            loop.points.add(x=x, y=y)
    text = [f"status {detection.status}"]
    for px, rgba, name, confidence in (
        (detection.target_px, _TARGET, "target", detection.target_confidence),
        (detection.arrow_px, _ARROW, "arrow", detection.arrow_confidence),
    ):
        if px is None:
            continue
        circle = message.circles.add(diameter=_MARK_PX, thickness=3.0)
        stamp(circle.timestamp, ns)
        circle.position.x, circle.position.y = px[0], px[1]
        _colour(circle.outline_color, rgba)
        text.append(f"{name} {confidence:.2f}")
    if detection.r_m is not None:
        text.append(f"r = ({detection.r_m[0]:+.3f}, {detection.r_m[1]:+.3f}) m")
    label = message.texts.add(text="  ".join(text), font_size=28.0)
    stamp(label.timestamp, ns)
    label.position.x, label.position.y = 20.0, 40.0
    _colour(label.text_color, _TARGET)
    _colour(label.background_color, (0.0, 0.0, 0.0, 0.6))
    return message.SerializeToString()


def rollout_record(rollout: Rollout) -> dict[str, Any] | None:
    """A done rollout as `ROLLOUT_SCHEMA`'s record, None for any other journal record."""
    record = rollout.record
    if not isinstance(record, DoneRecord):
        return None
    sec, nsec = divmod(round(rollout.stamp * 1e9), 1_000_000_000)
    return {
        "timestamp": {"sec": sec, "nsec": nsec},
        "session": record.session,
        "rollout": record.rollout,
        "theta": list(record.theta),
        "r": list(record.r_m),
        "distance": record.distance_m,
        "hit": record.hit,
    }


def event_log(event: WorldEvent, robot: str) -> bytes:
    """A world event (nocked, released, landed, …) as a `foxglove.Log` line at its stamp."""
    level = Log.Level.WARNING if event.kind == "watchdog" else Log.Level.INFO
    message = Log(level=level, name=f"{robot}/world")
    stamp(message.timestamp, round(event.stamp * 1e9))
    words = [f"{event.kind} (shot {event.shot})"]
    if event.impact_m is not None:
        words.append("impact (" + ", ".join(f"{v:+.3f}" for v in event.impact_m) + ") m")
    if event.reason:
        words.append(event.reason)
    message.message = ": ".join(words[:1]) + (" " + "; ".join(words[1:]) if words[1:] else "")
    return message.SerializeToString()
