"""Benchmark of the simulated robot's physics: real-time factor, posture changes and whole shots.

Run `python -m benchmarks.bench_physics` (add `--render DIR` to also time and save 1280×720
frames from the target and side cameras; needs MUJOCO_GL=egl or osmesa). The process is pinned
to one CPU core. Figures:

* real-time factor of the archery scene (simulated seconds per wall second), for raw `mj_step`
  and through `ArcheryWorld.step` (setpoint ramps and the held arrow included), against the iCub
  URDF loaded into MuJoCo unmodified (floating legs, self-collision, no actuators);
* wall time to move between two archery postures and release (the learner's loop);
* wall time of one complete shot from a fresh reset: settle into the posture, release, land.

`--smoke` runs every part once at its smallest budget: 0.2 simulated s per speed run and 1
repeat of each timed shot (seconds; its figures are noise, and the real-time goal does not set
its exit status: 0 once every part ran). Without `--render`, as the default run.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time
from collections.abc import Callable
from pathlib import Path

import mujoco
import numpy as np

from archery.sim.geometry import BOW_HAND, START_THETA
from archery.sim.model_build import build_scene
from archery.sim.scene_config import SIDE_CAMERA, TARGET_CAMERA, SceneConfig
from archery.sim.urdf import load_urdf_model
from archery.sim.world import ArcheryWorld, WorldConfig
from benchmarks.machine import cpu_model, pin_one_core
from tests.postures import archery_posture
from tests.world_steps import move_until_done

__all__ = ["main"]

REALTIME_GOAL = 20.0  # × real time on one core
THETA_B = START_THETA + np.array([0.02, 0.01, -0.01])  # m, a second archery posture


def _realtime_factor(model: mujoco.MjModel, data: mujoco.MjData, seconds: float) -> float:
    steps = round(seconds / model.opt.timestep)
    start = time.perf_counter()
    for _ in range(steps):
        mujoco.mj_step(model, data)
    return steps * model.opt.timestep / (time.perf_counter() - start)


def _baseline(seconds: float) -> tuple[float, int]:
    """Real-time factor of the unmodified URDF model, and how often MuJoCo had to reset it.

    The raw model is unstable: MuJoCo detects NaN/Inf accelerations and resets its state (the
    count comes from a second, untimed pass, so that counting costs the timing nothing).
    """
    previous = mujoco.get_mju_user_warning()
    mujoco.set_mju_user_warning(lambda _message: None)  # no MUJOCO_LOG.TXT in the cwd
    try:
        model = load_urdf_model()
        data = mujoco.MjData(model)
        factor = _realtime_factor(model, data, seconds)
        mujoco.mj_resetData(model, data)
        resets = 0
        for _ in range(round(seconds / model.opt.timestep)):
            before = data.time
            mujoco.mj_step(model, data)
            resets += data.time < before
    finally:
        mujoco.set_mju_user_warning(previous)
    return factor, resets


def _timed(repeats: int, setup: Callable[[], None], run: Callable[[], object]) -> list[float]:
    out = []
    for _ in range(repeats):
        setup()
        start = time.perf_counter()
        run()
        out.append((time.perf_counter() - start) * 1e3)
    return out


def _go(world: ArcheryWorld, posture: dict[str, np.ndarray]) -> None:
    for part, values in posture.items():
        world.set_joint_targets(part, values)
    if not move_until_done(world, timeout=15.0):
        raise RuntimeError("the posture was not reached within 15 simulated seconds")


def _render(world: ArcheryWorld, out_dir: Path) -> float:
    """Save target- and side-camera frames; return the mean wall ms per 1280×720 frame."""
    import PIL.Image

    out_dir.mkdir(parents=True, exist_ok=True)
    model = world.model
    data = mujoco.MjData(model)
    data.qpos[:] = world.qpos()
    mujoco.mj_forward(model, data)
    renderer = mujoco.Renderer(model, 720, 1280)
    try:
        for camera in (TARGET_CAMERA, SIDE_CAMERA):
            renderer.update_scene(data, camera=camera)
            PIL.Image.fromarray(renderer.render()).save(out_dir / f"{camera}.png")
        start = time.perf_counter()
        for _ in range(10):
            renderer.update_scene(data, camera=TARGET_CAMERA)
            renderer.render()
        return (time.perf_counter() - start) / 10 * 1e3
    finally:
        renderer.close()


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark and print a report; returns 0 if the real-time goal is met, else 1."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=20.0, help="simulated s per speed run")
    parser.add_argument("--repeats", type=int, default=20, help="repeats of the timed shots")
    parser.add_argument(
        "--render", type=Path, default=None, help="save and time camera frames here"
    )
    parser.add_argument(
        "--smoke",
        action="store_true",
        help="0.2 simulated s per speed run, 1 repeat: runs every part, no figures (exit 0)",
    )
    args = parser.parse_args(argv)
    if args.smoke:
        args.seconds, args.repeats = 0.2, 1
    pinning = pin_one_core()

    print(f"machine: {os.cpu_count()} CPUs ({pinning}), {cpu_model()}")
    print(f"python {platform.python_version()}, mujoco {mujoco.__version__}")

    start = time.perf_counter()
    model = build_scene(SceneConfig(meshes=args.render is not None))
    build_ms = (time.perf_counter() - start) * 1e3
    world = ArcheryWorld(
        WorldConfig(scene=SceneConfig(meshes=args.render is not None)), model=model
    )
    posture_a = archery_posture(model, BOW_HAND, BOW_HAND + START_THETA, tolerance=5e-3)
    posture_b = archery_posture(model, BOW_HAND, BOW_HAND + THETA_B, tolerance=5e-3)

    # Real-time factor: holding posture A with the arrow nocked.
    world.reset(seed=0)
    _go(world, posture_a)
    world.nock()
    raw = _realtime_factor(model, world.physics.data, args.seconds)
    steps = round(args.seconds / world.timestep)
    began = time.perf_counter()
    for _ in range(steps // 10):
        world.step(10 * world.timestep)
    stepped = (steps // 10) * 10 * world.timestep / (time.perf_counter() - began)
    baseline, resets = _baseline(args.seconds)

    # Move A → B and release; one complete shot from reset.
    def at_a() -> None:
        world.reset(seed=1)
        _go(world, posture_a)
        world.nock()

    def move_and_release() -> None:
        _go(world, posture_b)
        world.release()

    move_ms = _timed(args.repeats, at_a, move_and_release)
    at_a()
    move_sim = world.sim_time
    move_and_release()
    move_sim = world.sim_time - move_sim

    def fresh() -> None:
        world.reset(seed=2)
        for part, values in posture_a.items():
            world.set_joint_targets(part, values)
        world.nock()

    def shot() -> None:
        move_until_done(world, timeout=15.0)
        world.release()

    shot_ms = _timed(args.repeats, fresh, shot)
    fresh()
    shot()
    shot_sim = world.sim_time
    landing = world.landing
    assert landing is not None

    print(f"scene build ({'with' if args.render else 'without'} meshes): {build_ms:.0f} ms")
    print(f"timestep {world.timestep * 1e3:.1f} ms; nq {model.nq}, nv {model.nv}, nu {model.nu}")
    print(f"real-time factor, archery scene, raw mj_step:     {raw:8.1f} x")
    print(f"real-time factor, archery scene, ArcheryWorld:    {stepped:8.1f} x")
    print(f"real-time factor, unmodified iCub URDF (baseline): {baseline:7.1f} x")
    print(f"  baseline NaN resets by MuJoCo in {args.seconds:g} simulated s: {resets}")
    print(
        f"speed-up over baseline: {raw / baseline:.1f} x (raw), {stepped / baseline:.1f} x (world)"
    )
    print(f"goal >= {REALTIME_GOAL:.0f} x: {'met' if stepped >= REALTIME_GOAL else 'NOT met'}")
    print(
        f"move A->B + release: median {statistics.median(move_ms):.1f} ms wall "
        f"(min {min(move_ms):.1f}, max {max(move_ms):.1f}; {move_sim:.2f} s simulated)"
    )
    print(
        f"complete shot (settle from home, release, land): median "
        f"{statistics.median(shot_ms):.1f} ms wall (min {min(shot_ms):.1f}, "
        f"max {max(shot_ms):.1f}; {shot_sim:.2f} s simulated; flight "
        f"{landing.flight_time * 1e3:.0f} ms, {landing.outcome.value})"
    )
    if args.render is not None:
        per_frame = _render(world, args.render)
        backend = os.environ.get("MUJOCO_GL", "default GL")
        print(f"render 1280x720 ({backend}): {per_frame:.0f} ms/frame")
        print(f"frames saved in {args.render}")
    return 0 if stepped >= REALTIME_GOAL or args.smoke else 1


if __name__ == "__main__":
    raise SystemExit(main())
