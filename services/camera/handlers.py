"""The camera's RPC verbs on `ROBOT/cam/rpc:i` (`protocol.verbs.camera`): grab, calibration,
scene, status. Frames come from the capture thread's store; work on the source runs on that
thread; the scene view has its own thread (`services.camera.scene_view`)."""

from __future__ import annotations

import time

from archery.mesh.rates import RateLimit
from archery.mesh.rpc_server import caller_left, caller_or_anonymous
from archery.protocol.errors import BadRequest
from archery.protocol.messages import Image
from archery.protocol.robotspec import CALL_TIMEOUT
from archery.protocol.verbs import NoArgs, ServedVerbs
from archery.protocol.verbs import camera as cv
from archery.protocol.verbs.camera import (
    CAMERA_VERBS,
    GRAB_BURST,
    GRAB_RATE,
    CalibrationReply,
    CameraStatusReply,
    GrabArgs,
    SceneReply,
)
from archery.services.camera.capture import Capture
from archery.services.camera.config import CameraConfig
from archery.services.camera.frames import FrameStore, Freshness
from archery.services.camera.scene_view import SceneViews

__all__ = ["CALIBRATION_TIMEOUT", "CameraHandlers"]

CALIBRATION_TIMEOUT = 30.0  # wall s: a calibration frame is rendered on the capture thread


class CameraHandlers:
    """One method per camera verb."""

    def __init__(
        self, config: CameraConfig, capture: Capture, store: FrameStore, views: SceneViews
    ) -> None:
        self._config = config
        self._capture = capture
        self._store = store
        self._views = views
        self._rendered = config.source.kind == "mujoco"
        self.grabs = RateLimit("camera grab", GRAB_RATE, GRAB_BURST)  # per caller identity

    def verbs(self) -> ServedVerbs:
        """The verbs of `ROBOT/cam/rpc:i`."""
        return CAMERA_VERBS.bind(
            cv.GRAB.to(self.grab),
            cv.CALIBRATION.to(self.calibration),
            cv.SCENE.to(self.scene),
            cv.STATUS.to(self.status),
        )

    def grab(self, args: GrabArgs) -> Image:
        """The first frame newer than the stamps (sim s, wall s), within `timeout` s.

        With neither stamp, a frame captured after this request arrived: never the newest frame
        kept from before (nobody watching, it may show a shot of long ago). A device or folder
        frame has no sim time: there `after_sim_time` also means "captured after this request
        arrived". It never waits past its caller's own timeout (`RpcRequest.wait`; a request
        that does not say waits at most `CALL_TIMEOUT` s: a reply after its caller gave up would
        go to no one), and a stamp that no frame can reach within the timeout is refused at
        once. One caller identity makes at most `GRAB_RATE` grabs a second (bursts of
        `GRAB_BURST`); how many of its grabs wait at once the server bounds
        (`mesh.rpc_server.MAX_WAITING_PER_CALLER`).

        Raises:
            Busy: the caller is past its rate.
            BadRequest: `after_stamp` lies beyond the timeout (no frame can be captured then).
            RpcTimeout: no such frame within the timeout.
        """
        self.grabs.take(caller_or_anonymous())
        timeout = CALL_TIMEOUT if args.timeout is None else args.timeout
        left = caller_left()
        timeout = max(0.0, min(timeout, CALL_TIMEOUT if left is None else left))
        after_sim_time, after_stamp = args.after_sim_time, args.after_stamp
        now = time.time()
        if after_stamp is not None and after_stamp > now + timeout:
            raise BadRequest(
                f"grab: after_stamp is {after_stamp - now:.3g} s ahead of the camera's clock, "
                f"beyond the timeout of {timeout:g} s: no frame can be captured in time"
            )
        if after_sim_time is None and after_stamp is None:
            after_stamp = now
        elif not self._rendered and after_sim_time is not None:
            after_sim_time, after_stamp = None, max(after_stamp or 0.0, time.time())
        want = Freshness(after_sim_time=after_sim_time, after_stamp=after_stamp)
        return self._store.wait(want, timeout, on_wait=self._capture.jobs.notify)

    def calibration(self, args: NoArgs) -> CalibrationReply:
        """A frame with an arrow on the face and the pixels a user would mark (mujoco only)."""
        if not self._rendered:
            raise BadRequest(
                f"calibration marks come only from the mujoco source (this camera is "
                f"{self._config.source.kind}): mark pixels by hand and use `archery calibrate`, "
                f"or the detector's `calibrate` verb with pixels"
            )
        capture = self._capture

        def job() -> CalibrationReply:
            from archery.sim.render import calibration_frame

            latest = capture.world.latest() if capture.world else None
            qpos = latest.qpos.to_numpy() if latest else capture.renderer.model.qpos0
            capture.fit_scene(qpos)
            pixels, marks = calibration_frame(capture.renderer, qpos)
            image = Image.from_numpy(
                pixels, sim_time=latest.sim_time if latest else None, stamp=time.time()
            )
            return CalibrationReply(image=image, pixels=marks)

        return capture.jobs.call(job, timeout=CALIBRATION_TIMEOUT)

    def scene(self, args: NoArgs) -> SceneReply:
        """The newest view of the whole robot from the side camera (mujoco only); never waits:
        it asks the scene view's thread for the next one."""
        return self._views.reply()

    def status(self, args: NoArgs) -> CameraStatusReply:
        """Source, size, rate, encoding, frames, renders (and frames of an unchanged scene served
        without one), mean render time (ms), scene."""
        config, capture = self._config, self._capture
        latest = self._store.latest
        renders = capture.renders
        return CameraStatusReply(
            source=config.source.kind,
            width=config.width,
            height=config.height,
            rate=config.rate,
            encoding=config.encoding,
            frames=self._store.count,
            renders=renders,
            reuses=capture.reuses,
            render_ms=round(1e3 * capture.render_seconds / renders, 3) if renders else None,
            errors=capture.errors,
            latest_sim_time=latest.sim_time if latest else None,
            scene=capture.scene,
            scene_from=capture.scene_from,
            waiting=len(self._store.waiting()),
        )
