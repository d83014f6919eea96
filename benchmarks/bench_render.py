"""Benchmark of the camera: render time of a 1280×720 target-camera frame with the default and
the lean settings, what each lean setting saves, and the frame rate the camera service sustains.

Run `MUJOCO_GL=egl python -m benchmarks.bench_render [--frames N] [--seconds S]`. The render
timings run pinned to one CPU core; the service part runs a real `archery router` process and
the camera service on a thread of this process, fed world states at 200 Hz of changing arrow
positions, and counts the frames a subscriber receives (`--rate 120`, the camera's maximum).

`--smoke`: every variant on 2 frames and 0.5 s of the camera service (seconds; its figures are
noise, and the render goal does not set its exit status: 0 once every part ran).
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import platform
import statistics
import threading
import time
from collections.abc import Callable

os.environ.setdefault("MUJOCO_GL", "egl")

import mujoco
import numpy as np

from archery.mesh.netflags import NetConfig
from archery.mesh.node import Node
from archery.mesh.router import free_tcp_endpoint, spawn_router
from archery.protocol.messages import Array, Image, WorldState
from archery.services.camera.config import CameraConfig
from archery.services.camera.service import run
from archery.sim.arrow import arrow_quat
from archery.sim.model_build import build_scene
from archery.sim.render import LEAN_FLAGS, ROBOT_GEOM_GROUP, SceneRenderer
from archery.sim.scene import ScenePhysics
from archery.sim.scene_config import TARGET_CAMERA, TARGET_CENTRE_SITE, SceneConfig
from benchmarks.machine import cpu_model
from tests.rpc import rpc_call

__all__ = ["main"]

WIDTH, HEIGHT = 1280, 720
RENDER_GOAL_MS = 40.0


def _states(model: mujoco.MjModel, count: int) -> list[np.ndarray]:
    """qpos of the model's initial state with the arrow stuck at `count` places on the face."""
    physics = ScenePhysics(model)
    physics.reset()
    physics.forward()
    centre = physics.site_position(TARGET_CENTRE_SITE)
    rng = np.random.default_rng(0)
    out = []
    for _ in range(count):
        offset = rng.uniform(-0.2, 0.2, 2)
        physics.set_arrow_pose(
            centre + np.array([0.0, offset[0], offset[1]]), arrow_quat(np.array([-1, 0, -0.05]))
        )
        out.append(physics.qpos())
    return out


def _time_renderer(render: Callable[[np.ndarray], object], states: list[np.ndarray]) -> list[float]:
    render(states[0])  # warm up
    out = []
    for qpos in states:
        start = time.perf_counter()
        render(qpos)
        out.append((time.perf_counter() - start) * 1e3)
    return out


def _variant(
    model: mujoco.MjModel, *, robot: bool, shadows: bool, samples: int, states: list[np.ndarray]
) -> list[float]:
    """Render times (ms) of a plain mujoco.Renderer with the given settings."""
    model.vis.quality.offsamples = samples
    data = mujoco.MjData(model)
    option = mujoco.MjvOption()
    option.geomgroup[ROBOT_GEOM_GROUP] = int(robot)
    renderer = mujoco.Renderer(model, height=HEIGHT, width=WIDTH)

    def render(qpos: np.ndarray) -> np.ndarray:
        data.qpos[:] = qpos
        mujoco.mj_fwdPosition(model, data)
        renderer.update_scene(data, camera=TARGET_CAMERA, scene_option=option)
        if not shadows:
            for flag in LEAN_FLAGS:
                renderer.scene.flags[flag] = 0
        return renderer.render()

    try:
        return _time_renderer(render, states)
    finally:
        renderer.close()


def _camera_rate(seconds: float) -> dict[str, float]:
    """Frames per second the camera service publishes and a subscriber receives, and the
    latency of a grab for a new world state (ms)."""
    endpoint = free_tcp_endpoint()
    router = spawn_router(endpoint)
    stop = threading.Event()
    net = NetConfig(connect=(endpoint,), robot="benchcam")
    config = CameraConfig(net=net, rate=120.0, robot_timeout=0.2)
    camera = threading.Thread(target=run, args=(config, stop), daemon=True)
    try:
        camera.start()
        with Node(None, net) as node:
            keys = node.keys
            node.wait_alive(["camera"], timeout=30)
            received = []
            node.subscribe(keys.cam_frames(), Image, callback=lambda m: received.append(m.frame))
            world = node.publisher(keys.world_state(), WorldState)
            world.wait_matched(5)
            states = _states(build_scene(SceneConfig(meshes=False)), 200)
            sim_time = 0.0
            start = time.perf_counter()
            count0 = len(received)
            while time.perf_counter() - start < seconds:
                sim_time += 0.005
                world.put(
                    WorldState(
                        qpos=Array.from_numpy(states[int(sim_time * 200) % len(states)]),
                        sim_time=sim_time,
                    )
                )
                time.sleep(0.005)
            elapsed = time.perf_counter() - start
            fps = (len(received) - count0) / elapsed
            status = rpc_call(node, keys.cam_rpc(), "status", timeout=5)
            latencies = []
            for i in range(20):
                sim_time += 1.0
                t0 = time.perf_counter()
                world.put(WorldState(qpos=Array.from_numpy(states[i]), sim_time=sim_time))
                rpc_call(node, keys.cam_rpc(), "grab", {"after_sim_time": sim_time}, timeout=10)
                latencies.append((time.perf_counter() - t0) * 1e3)
                time.sleep(0.05)
        return {
            "fps": fps,
            "published": float(status["frames"]),
            "render_ms": float(status["render_ms"]),
            "grab_ms": statistics.median(latencies),
        }
    finally:
        stop.set()
        camera.join(timeout=15)
        router.terminate()
        router.wait(timeout=10)


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark and print its figures (exit 1 if the render goal is missed)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=40, help="frames timed per variant")
    parser.add_argument("--seconds", type=float, default=5.0, help="camera service run (s)")
    parser.add_argument(
        "--smoke",
        action="store_true",
        help="2 frames per variant, 0.5 s of the camera service: every part, no figures (exit 0)",
    )
    args = parser.parse_args(argv)
    if args.smoke:
        args.frames, args.seconds = 2, 0.5
    affinity = os.sched_getaffinity(0)
    core = min(affinity)
    os.sched_setaffinity(0, {core})
    print(f"machine: {os.cpu_count()} CPUs, {cpu_model()}; renders pinned to core {core}")
    gl = os.environ["MUJOCO_GL"]
    print(f"python {platform.python_version()}, mujoco {mujoco.__version__}, MUJOCO_GL={gl}")

    full = build_scene(SceneConfig())  # the robot's model, meshes and all
    states = _states(full, args.frames)
    rows = []
    for label, kwargs in (
        (
            "default (robot meshes, shadows, reflections, skybox, 4× MSAA)",
            {"robot": True, "shadows": True, "samples": 4},
        ),
        ("  robot geoms hidden", {"robot": False, "shadows": True, "samples": 4}),
        ("  + no shadows, reflections, skybox", {"robot": False, "shadows": False, "samples": 4}),
        ("  + no multisampling", {"robot": False, "shadows": False, "samples": 0}),
    ):
        model = build_scene(SceneConfig())
        rows.append((label, _variant(model, **kwargs, states=states)))
    with SceneRenderer(dataclasses.replace(SceneConfig(), meshes=True)) as lean:
        rows.append(
            (
                "lean SceneRenderer (also no robot meshes in the model)",
                _time_renderer(lean.render, states),
            )
        )
    print(f"render time of a {WIDTH}x{HEIGHT} target-camera frame, {args.frames} arrow positions:")
    for label, times in rows:
        median, p90 = statistics.median(times), float(np.quantile(times, 0.9))
        print(f"  {label:62s} median {median:7.1f} ms, p90 {p90:7.1f} ms")
    default_ms, lean_ms = statistics.median(rows[0][1]), statistics.median(rows[-1][1])
    print(
        f"lean / default: {lean_ms:.1f} / {default_ms:.1f} ms = {default_ms / lean_ms:.1f}x faster"
    )

    os.sched_setaffinity(0, affinity)
    rate = _camera_rate(args.seconds)
    print(
        f"camera service (rgb8 {WIDTH}x{HEIGHT}, --rate 120, world states at 200 Hz, "
        f"not pinned): {rate['fps']:.1f} frames/s received, mean render "
        f"{rate['render_ms']:.1f} ms, grab of a new world state {rate['grab_ms']:.1f} ms "
        f"(median of 20)"
    )
    met = lean_ms <= RENDER_GOAL_MS
    print(f"goal (lean render ≤ {RENDER_GOAL_MS:g} ms): {'met' if met else 'MISSED'}")
    return 0 if met or args.smoke else 1


if __name__ == "__main__":
    raise SystemExit(main())
