"""What a camera sees of a qpos, as bytes: two qpos with the same key render the same image.

The lean renderer draws no shadows and no reflections, so a body outside the camera's view
frustum changes no pixel. The key of a qpos is the pose of every movable element that is drawn
and whose bounding sphere reaches into the frustum (`ViewKey.key`); everything else in the scene
is static. So the target camera's frames while the robot moves its arms behind it, or after a
reset, share one key and one render. The test is conservative (the near and far planes are
ignored, spheres are padded): an element that might be seen counts as seen, so equal keys
always mean equal images.
"""

from __future__ import annotations

import math

import mujoco
import numpy as np

__all__ = ["ViewKey"]

_PAD = 1.05  # bounding spheres padded by 5 % and 1 cm: rounding never hides a seen element
_PAD_M = 0.01


class ViewKey:
    """Keys of qpos for one camera of a model, as rendered with `option`.

    Args:
        model: the scene.
        camera: the camera's name.
        width, height: the image size (px): the frustum's aspect.
        option: the visualisation options the renderer uses (visible geom and site groups).
        lean: the renderer draws no shadows and no reflections (else the key is the qpos).
    """

    def __init__(
        self,
        model: mujoco.MjModel,
        camera: str,
        width: int,
        height: int,
        option: mujoco.MjvOption,
        *,
        lean: bool,
    ) -> None:
        self.model = model
        self.data = mujoco.MjData(model)
        self.cam = model.camera(camera).id
        tan_y = math.tan(0.5 * math.radians(float(model.cam_fovy[self.cam])))
        self._tans = (tan_y * width / height, tan_y)
        moving = model.body_weldid != 0  # a body welded to the world never moves
        self.exact = (
            not lean
            or bool(moving[model.cam_bodyid[self.cam]])
            or bool(np.any(moving[model.light_bodyid]))
            or model.nskin > 0
            or model.nflex > 0
        )
        geom_seen = np.asarray(option.geomgroup, bool)[np.clip(model.geom_group, 0, 5)]
        site_seen = np.asarray(option.sitegroup, bool)[np.clip(model.site_group, 0, 5)]
        self._geoms = np.flatnonzero(geom_seen & moving[model.geom_bodyid])
        self._sites = np.flatnonzero(site_seen & moving[model.site_bodyid])
        self._geom_r = model.geom_rbound[self._geoms] * _PAD + _PAD_M
        site_size = model.site_size[self._sites]
        self._site_r = np.linalg.norm(site_size, axis=1) * 2 * _PAD + _PAD_M
        self._tendons = self._drawn_tendons(option, moving)
        mujoco.mj_kinematics(model, self.data)
        mujoco.mj_camlight(model, self.data)  # a fixed camera: its pose, once
        self._cam_pos = self.data.cam_xpos[self.cam].copy()
        self._cam_rot = self.data.cam_xmat[self.cam].reshape(3, 3).copy()

    def _drawn_tendons(
        self, option: mujoco.MjvOption, moving: np.ndarray
    ) -> list[tuple[np.ndarray, np.ndarray, float]]:
        """The spatial tendons drawn that may move: (their sites, their wrap geoms, width m).
        A tendon's path lies within the sites' convex hull and its wrap geoms' spheres."""
        model = self.model
        if not option.flags[mujoco.mjtVisFlag.mjVIS_TENDON]:
            return []
        groups = np.asarray(option.tendongroup, bool)
        out = []
        for t in range(model.ntendon):
            if not groups[min(max(int(model.tendon_group[t]), 0), 5)]:
                continue
            wraps = range(model.tendon_adr[t], model.tendon_adr[t] + model.tendon_num[t])
            types = model.wrap_type[list(wraps)]
            ids = model.wrap_objid[list(wraps)]
            sites = ids[types == mujoco.mjtWrap.mjWRAP_SITE]
            geoms = ids[
                (types == mujoco.mjtWrap.mjWRAP_SPHERE) | (types == mujoco.mjtWrap.mjWRAP_CYLINDER)
            ]
            if sites.size == 0:
                continue  # a fixed tendon (joints only) is not drawn
            if moving[model.site_bodyid[sites]].any() or moving[model.geom_bodyid[geoms]].any():
                out.append((sites, geoms, float(model.tendon_width[t])))
        return out

    def _tendon_key(self) -> list[bytes]:
        """The poses of the points of each drawn tendon that may reach into the frustum."""
        data, parts = self.data, []
        for sites, geoms, width in self._tendons:
            points = np.concatenate([data.site_xpos[sites], data.geom_xpos[geoms]])
            reach = np.concatenate([np.zeros(sites.size), self.model.geom_rbound[geoms]])
            centre = points.mean(axis=0)
            radius = float(np.max(np.linalg.norm(points - centre, axis=1) + reach)) + width
            if self._in_view(centre[None, :], np.array([radius * _PAD + _PAD_M]))[0]:
                parts += [points.tobytes(), data.geom_xmat[geoms].tobytes()]
            parts.append(b"-")  # tendons in a fixed order: one separator each
        return parts

    def _in_view(self, centres: np.ndarray, radii: np.ndarray) -> np.ndarray:
        """Which spheres (world centres, radii m) may reach into the frustum."""
        # the camera frame's columns: right, up, backwards
        local = (centres - self._cam_pos) @ self._cam_rot
        depth = -local[:, 2]
        seen = depth > -radii  # not wholly behind the camera
        for axis, tan in zip((0, 1), self._tans, strict=True):
            # distance beyond the side planes |u| = depth · tan, measured along their normal
            beyond = (np.abs(local[:, axis]) - depth * tan) / math.hypot(1.0, tan)
            seen &= beyond < radii
        return seen

    def key(self, qpos: np.ndarray) -> bytes:
        """The key of `qpos` (the model's length): the pose of every movable element that is
        drawn (a geom or site of a visible group on a body that moves) and whose bounding sphere
        reaches into the frustum, with its index. A drawn spatial tendon (the bow's string)
        counts as seen when the sphere around its sites and wrap geoms reaches into the
        frustum. Where the test cannot be sure (a moving camera or light, skins or flexes,
        shadows or reflections on: `exact`), the key is the whole qpos."""
        if self.exact:
            return np.asarray(qpos, np.float64).tobytes()
        data = self.data
        data.qpos[:] = qpos
        mujoco.mj_kinematics(self.model, data)
        geoms = self._geoms[self._in_view(data.geom_xpos[self._geoms], self._geom_r)]
        sites = self._sites[self._in_view(data.site_xpos[self._sites], self._site_r)]
        return b"".join(
            (
                np.array([geoms.size, sites.size], np.int32).tobytes(),
                geoms.astype(np.int32).tobytes(),
                data.geom_xpos[geoms].tobytes(),
                data.geom_xmat[geoms].tobytes(),
                sites.astype(np.int32).tobytes(),
                data.site_xpos[sites].tobytes(),
                data.site_xmat[sites].tobytes(),
                *self._tendon_key(),
            )
        )
