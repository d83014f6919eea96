"""Where the film's camera looks: the robot while it moves, the arrow while it flies.

`ShotCamera` gives each filmed state a free MuJoCo camera (`sim.scene_view.free_camera`): until
the release it frames the robot's upper body (hips to head, both arms, the bow) so that it
fills most of the frame's height; from the release it follows the arrow to the target and
comes to rest on the face, moving smoothly from one framing to the other. `framed` pairs a
film's frames with their cameras. Positions are metres in the root frame; the cameras' angles
are degrees, as MuJoCo's `mjvCamera` takes them (azimuth about +z from +x, −90 looking along
−y; a negative elevation looks down).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterable, Iterator

import mujoco
import numpy as np

from archery.apps.film.replay import FilmFrame
from archery.sim.render import ROBOT_GEOM_GROUP
from archery.sim.scene_config import ARROW_BODY, HOLDER_BODY, TARGET_CENTRE_SITE
from archery.sim.scene_view import free_camera

__all__ = [
    "CATCH_M",
    "FIT",
    "FLIGHT_AZIMUTH",
    "FLIGHT_ELEVATION",
    "FLIGHT_ZOOM",
    "LEAD",
    "REACH_M",
    "ROBOT_AZIMUTH",
    "ROBOT_ELEVATION",
    "ROBOT_FILL",
    "ShotCamera",
    "framed",
    "upper_body_geoms",
]

ROBOT_FILL = 0.8  # of the frame's height, the robot's hips to the top of its head
FIT = 0.9  # of the frame's half-width and half-height, the robot framing's box at most
ROBOT_AZIMUTH = -70.0  # degrees: from the robot's right (+y), 20° in front of it
ROBOT_ELEVATION = -8.0  # degrees
HIPS_M = 0.19  # m below the root, the bottom of the pelvis
REACH_M = 0.6  # m ahead of the root (−x), the bow held out and the whole shot's arrow holder
FLIGHT_AZIMUTH = -130.0  # degrees: behind the arrow's line, on the robot's right
FLIGHT_ELEVATION = -10.0  # degrees
FLIGHT_ZOOM = 1.25  # the camera's distance at the landing, times the robot framing's
CATCH_M = 0.9  # m of the arrow's travel over which the look-at point moves onto the arrow
LEAD = 0.4  # of the visible half-width, the look-at point ahead of the arrow


def _smoothstep(x: float) -> float:
    """0 below 0, 1 above 1, and 3x² − 2x³ between: continuous, with zero slope at both ends."""
    x = min(1.0, max(0.0, x))
    return x * x * (3.0 - 2.0 * x)


def upper_body_geoms(model: mujoco.MjModel) -> np.ndarray:
    """The robot's geoms that move with its joints: torso, chest, head and both arms (not the
    legs and the pelvis, which are welded to the world)."""
    moving = model.body_weldid[model.geom_bodyid] != 0
    return np.flatnonzero(moving & (model.geom_group == ROBOT_GEOM_GROUP))


def _axes(azimuth: float, elevation: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A free camera's forward, right and up unit vectors for `azimuth` and `elevation`
    (degrees), as MuJoCo orients it."""
    a, e = math.radians(azimuth), math.radians(elevation)
    forward = np.array([math.cos(a) * math.cos(e), math.sin(a) * math.cos(e), math.sin(e)])
    right = np.array([math.sin(a), -math.cos(a), 0.0])
    return forward, right, np.cross(right, forward)


def _aabb(model: mujoco.MjModel, data: mujoco.MjData, geoms: np.ndarray) -> np.ndarray:
    """The world-aligned box (2, 3: min, max, m) around `geoms`' bounding boxes."""
    corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
    points = []
    for g in geoms:
        centre, half = model.geom_aabb[g, :3], model.geom_aabb[g, 3:]
        rot = data.geom_xmat[g].reshape(3, 3)
        points.append(data.geom_xpos[g] + (centre + corners * half) @ rot.T)
    every = np.concatenate(points)
    return np.stack([every.min(axis=0), every.max(axis=0)])


class ShotCamera:
    """The film's camera for the scene `model` in frames `width` × `height` px: `aim` gives the
    camera of each filmed state, in the film's order (it remembers where the arrow was
    released).

    Until the release the framing is fixed for the film, from the robot's right and a little
    in front (`ROBOT_AZIMUTH`): it looks at the centre of `robot_box` from the distance at
    which the box's height, hips to the top of the head, fills `ROBOT_FILL` of the frame's
    height, or farther where that would leave some of what it must show out of view (`_fit`).
    Once the arrow flies, the look-at point moves from the robot onto a point ahead of the
    arrow over the arrow's first `CATCH_M` of travel, and stays on it until the landing: that
    point lies toward the target's centre, up to `LEAD` of the visible half-width ahead and
    less as the arrow nears the centre, never past it, so the camera comes to rest on the face
    with the landed arrow in view. Along the flight the camera turns from the robot's side to
    behind the arrow's line (`FLIGHT_AZIMUTH`), where the target's face is seen at an angle
    rather than edge-on, and draws back by `FLIGHT_ZOOM`. Every quantity is a smooth function
    of the arrow's position, equal to the robot framing's at the release, so the camera moves
    without a jump.
    """

    def __init__(self, model: mujoco.MjModel, width: int, height: int) -> None:
        self.model = model
        self.data = mujoco.MjData(model)
        self._arrow = model.body(ARROW_BODY).id
        self._target = model.site(TARGET_CENTRE_SITE).id
        self._tan_y = math.tan(0.5 * math.radians(float(model.vis.global_.fovy)))
        self._tan_x = self._tan_y * width / height
        box, points = self.robot_box()
        self.robot_lookat = box.mean(axis=0)
        self.robot_distance = self._fit(box, points)
        self._released_at: np.ndarray | None = None
        self._last_held: np.ndarray | None = None

    def robot_box(self) -> tuple[np.ndarray, np.ndarray]:
        """What the robot framing shows: the box (2, 3: min, max corners, m) from `HIPS_M`
        below the root to the top of the robot's head at the model's reference posture and
        from its back to `REACH_M` ahead of the root, in the root's plane (y = 0); and the
        points (N, 3, m) that must be in view, the box's corners and, in the whole shot, the
        corners of the arrow in its holder.

        Raises:
            ValueError: the model has no robot meshes (`sim.scene_view.SceneView`'s has).
        """
        model, data = self.model, self.data
        mujoco.mj_kinematics(model, data)
        geoms = upper_body_geoms(model)
        if geoms.size == 0:
            raise ValueError("the scene has no robot meshes to frame")
        body = _aabb(model, data, geoms)
        box = np.array([[min(body[0, 0], -REACH_M), 0.0, -HIPS_M], [body[1, 0], 0.0, body[1, 2]]])
        points = [np.array(corner) for corner in itertools.product(*box.T)]
        if mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, HOLDER_BODY) >= 0:
            held = _aabb(model, data, np.flatnonzero(model.geom_bodyid == self._arrow))
            points += [np.array(corner) for corner in itertools.product(*held.T)]
        return box, np.array(points)

    def _fit(self, box: np.ndarray, points: np.ndarray) -> float:
        """The robot framing's distance (m): the box's height fills `ROBOT_FILL` of the frame's
        height, unless one of the `points` would then fall outside the middle `FIT` of the
        frame (a narrow frame, the whole shot's holder): then as close as keeps them all in."""
        lookat = box.mean(axis=0)
        forward, right, up = _axes(ROBOT_AZIMUTH, ROBOT_ELEVATION)
        distance = float(box[1, 2] - box[0, 2]) / (2.0 * ROBOT_FILL * self._tan_y)
        for point in points:
            offset = point - lookat
            depth = float(offset @ forward)  # beyond the look-at point, seen from the camera
            for along, tan in ((right, self._tan_x), (up, self._tan_y)):
                # |offset · along| <= FIT · tan · (distance + depth)
                distance = max(distance, abs(float(offset @ along)) / (FIT * tan) - depth)
        return distance

    def _poses(self, qpos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(the arrow's centre, the target's centre) at `qpos` (m)."""
        self.data.qpos[:] = qpos
        mujoco.mj_kinematics(self.model, self.data)
        return self.data.xipos[self._arrow].copy(), self.data.site_xpos[self._target].copy()

    def aim(self, qpos: np.ndarray, released: bool) -> mujoco.MjvCamera:
        """The camera of the state `qpos`: the robot framing until the arrow is `released`,
        then following the arrow (see the module)."""
        arrow, target = self._poses(np.asarray(qpos, dtype=float))
        if not released:
            self._last_held, self._released_at = arrow, None
            return free_camera(
                self.robot_lookat, self.robot_distance, ROBOT_AZIMUTH, ROBOT_ELEVATION
            )
        if self._released_at is None:
            self._released_at = arrow if self._last_held is None else self._last_held
        start = self._released_at
        travel = float(np.linalg.norm(arrow - start))
        course = max(1e-6, float(start[0] - target[0]))  # m along −x, release to target
        turn = _smoothstep((start[0] - arrow[0]) / course)
        catch = _smoothstep(travel / CATCH_M)
        distance = self.robot_distance * (1.0 + (FLIGHT_ZOOM - 1.0) * turn)
        azimuth = ROBOT_AZIMUTH + (FLIGHT_AZIMUTH - ROBOT_AZIMUTH) * turn
        elevation = ROBOT_ELEVATION + (FLIGHT_ELEVATION - ROBOT_ELEVATION) * turn
        toward = target - arrow
        reach = LEAD * distance * self._tan_x
        # toward the target, at most `reach` ahead; the same as the target's centre at the end
        ahead = toward * reach / math.hypot(float(np.linalg.norm(toward)), reach)
        lookat = (1.0 - catch) * self.robot_lookat + catch * (arrow + ahead)
        return free_camera(lookat, distance, azimuth, elevation)


def framed(
    frames: Iterable[FilmFrame], model: mujoco.MjModel, width: int, height: int
) -> Iterator[tuple[FilmFrame, mujoco.MjvCamera]]:
    """Each of a film's `frames` (in order) with the camera that films it: one `ShotCamera` of
    the scene `model` for frames `width` × `height` px."""
    camera = ShotCamera(model, width, height)
    for frame in frames:
        yield frame, camera.aim(frame.qpos, frame.released)
