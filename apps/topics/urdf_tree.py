"""A URDF's kinematic tree and its forward kinematics: each joint's child link in its parent
link's frame, from the joint's origin (xyz, m; rpy, rad, fixed axes x then y then z), its axis
and its position (rad for a revolute or continuous joint, m for a prismatic one; a fixed joint
has none). What `/tf` and `/tf_static` publish, with the URDF's own frame names. Pure: no I/O.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass

import numpy as np

__all__ = ["MOVING", "UrdfJoint", "parse_joints", "rpy_matrix"]

MOVING = ("revolute", "continuous", "prismatic")  # the joint types that have a position
_KNOWN = (*MOVING, "fixed")


def rpy_matrix(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """URDF's rotation of `rpy` (rad): Rz(yaw) @ Ry(pitch) @ Rx(roll)."""
    cr, sr, cp, sp, cy, sy = (
        np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch), np.cos(yaw), np.sin(yaw)
    )  # fmt: skip
    return np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )


def _axis_angle(axis: np.ndarray, angle: float) -> np.ndarray:
    """The rotation of `angle` (rad) about the unit vector `axis` (Rodrigues)."""
    x, y, z = axis
    k = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    return np.eye(3) + np.sin(angle) * k + (1.0 - np.cos(angle)) * (k @ k)


@dataclass(frozen=True)
class UrdfJoint:
    """One joint of a URDF: its name, type, parent and child links, origin (translation, m;
    rotation matrix) and unit axis (in the child's frame)."""

    name: str
    kind: str
    parent: str
    child: str
    translation: np.ndarray
    rotation: np.ndarray
    axis: np.ndarray

    @property
    def moving(self) -> bool:
        """Whether the joint has a position (revolute, continuous, prismatic)."""
        return self.kind in MOVING

    def pose(self, position: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """The child's frame in the parent's at `position` (rad or m; a fixed joint ignores
        it): translation (3, m) and rotation (3×3)."""
        if self.kind in ("revolute", "continuous"):
            return self.translation, self.rotation @ _axis_angle(self.axis, position)
        if self.kind == "prismatic":
            return self.translation + self.rotation @ (self.axis * position), self.rotation
        return self.translation, self.rotation


def _floats(text: str | None, default: str, what: str) -> np.ndarray:
    try:
        values = np.array([float(v) for v in (text or default).split()])
    except ValueError:
        raise ValueError(f"{what}: not three numbers") from None
    if values.shape != (3,) or not np.all(np.isfinite(values)):
        raise ValueError(f"{what}: not three finite numbers")
    return values


def parse_joints(text: str) -> list[UrdfJoint]:
    """The joints of the URDF `text`, in the file's order.

    Raises:
        ValueError: not XML, a joint without a name, parent or child, of another type, or
            with an origin or axis that is not three finite numbers.
    """
    try:
        root = ET.fromstring(text)
    except ET.ParseError as exc:
        raise ValueError(f"not a URDF: {exc}") from None
    joints = []
    for element in root.findall("joint"):
        name = element.get("name") or ""
        kind = element.get("type") or ""
        parent, child = element.find("parent"), element.find("child")
        if not name or kind not in _KNOWN or parent is None or child is None:
            raise ValueError(f"joint {name!r}: needs a name, a type of {_KNOWN}, parent, child")
        origin = element.find("origin")
        xyz = _floats(None if origin is None else origin.get("xyz"), "0 0 0", f"{name} xyz")
        rpy = _floats(None if origin is None else origin.get("rpy"), "0 0 0", f"{name} rpy")
        axis_element = element.find("axis")
        axis = _floats(
            None if axis_element is None else axis_element.get("xyz"), "1 0 0", f"{name} axis"
        )
        norm = float(np.linalg.norm(axis))
        if kind in MOVING and norm == 0.0:
            raise ValueError(f"{name} axis: zero")
        joints.append(
            UrdfJoint(
                name,
                kind,
                parent.get("link") or "",
                child.get("link") or "",
                xyz,
                rpy_matrix(*rpy),
                axis / (norm or 1.0),
            )
        )
    return joints
