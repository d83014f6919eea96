"""Where the simulation loop's streams go: the `Sink` it calls, and `MeshSink`, its Zenoh
publishers (tests use a recording sink)."""

from __future__ import annotations

from typing import Protocol

import numpy as np

from archery.mesh.node import Node
from archery.protocol.messages import Array, JointState, WorldEvent, WorldState

__all__ = ["MeshSink", "Sink"]


class Sink(Protocol):
    """Where the loop's streams go (Zenoh publishers in the service; a list in tests)."""

    def joint_state(
        self,
        part: str,
        names: tuple[str, ...],
        position: list[float],
        velocity: list[float],
        motion_done: bool,
        sim_time: float,
    ) -> None:
        """One part's joint state: positions (rad), velocities (rad/s), sim time (s)."""

    def world_state(self, qpos: np.ndarray, phase: str, shot: int, sim_time: float) -> None:
        """The scene's generalized positions, the shot phase and number, sim time (s)."""

    def event(
        self,
        kind: str,
        shot: int,
        sim_time: float | None,
        impact_m: list[float] | None = None,
        reason: str = "",
    ) -> None:
        """A shot event (grasped, nocked, released, landed, missed, reset) or a watchdog hold
        (`reason` names the part); impact_m is ground truth; sim_time None: not known (a YARP
        robot's event, forwarded)."""


class MeshSink:
    """The loop's streams as Zenoh publishers (`ROBOT/{part}/state:o`, `ROBOT/world/state:o`,
    `ROBOT/world/events:o`, the last lossless; `world` False: the joint states alone, for a
    robot with no simulated world, whose `world_state` and `event` then publish nothing; but
    `events` True: the events too, a YARP robot's forwarded)."""

    def __init__(
        self, node: Node, parts: tuple[str, ...], world: bool = True, events: bool = False
    ) -> None:
        keys = node.keys
        self._states = {p: node.publisher(keys.state(p), JointState) for p in parts}
        self._world = node.publisher(keys.world_state(), WorldState) if world else None
        self._events = (
            node.publisher(keys.world_events(), WorldEvent, lossless=True)
            if world or events
            else None
        )

    def joint_state(
        self,
        part: str,
        names: tuple[str, ...],
        position: list[float],
        velocity: list[float],
        motion_done: bool,
        sim_time: float,
    ) -> None:
        self._states[part].put(
            JointState(
                part=part,
                names=list(names),
                position=position,
                velocity=velocity,
                motion_done=motion_done,
                sim_time=sim_time,
            )
        )

    def world_state(self, qpos: np.ndarray, phase: str, shot: int, sim_time: float) -> None:
        if self._world is None:
            return
        self._world.put(
            WorldState(qpos=Array.from_numpy(qpos), phase=phase, shot=shot, sim_time=sim_time)
        )

    def event(
        self,
        kind: str,
        shot: int,
        sim_time: float | None,
        impact_m: list[float] | None = None,
        reason: str = "",
    ) -> None:
        if self._events is None:
            return
        self._events.put(
            WorldEvent(
                kind=kind,  # type: ignore[arg-type]  # callers pass one of WorldEvent's kinds
                shot=shot,
                impact_m=impact_m,
                reason=reason,
                sim_time=sim_time,
            )
        )
