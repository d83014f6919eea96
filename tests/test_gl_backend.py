"""The rendering backend as a user's shell meets it (`sim.gl_backend`): with MUJOCO_GL unset,
`egl` or `osmesa` a frame renders whatever was imported first; a backend that cannot start is
one line and exit status 2 before any session or service starts.

This is the one test module that names the rendering variables: it gives them to child
processes, as a user's shell would, and never sets them in its own process."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import pytest

from archery.mesh.router import free_tcp_endpoint
from tests.test_user_shell import bare_env

RENDER = """
import mujoco  # first, before anything of ours: MuJoCo reads MUJOCO_GL now
import numpy as np
from archery.sim.render import SceneRenderer
from archery.sim.scene_config import SceneConfig
from archery.sim.gl_backend import check
with SceneRenderer(SceneConfig(meshes=False), width=64, height=48) as renderer:
    frame = renderer.render(renderer.data.qpos.copy())
print(check(), frame.shape, int(np.asarray(frame).std() > 1))
"""


def _run(argv: list[str], home: Path, timeout: float = 120, **variables: str) -> tuple:
    """Run `argv` in a bare environment plus `variables`; (status, stdout, stderr, seconds)."""
    start = time.monotonic()
    proc = subprocess.run(
        argv,
        cwd=home,
        env=bare_env(home) | variables,
        stdin=subprocess.DEVNULL,
        capture_output=True,
        text=True,
        timeout=timeout,
    )
    return proc.returncode, proc.stdout, proc.stderr, time.monotonic() - start


@pytest.mark.parametrize("backend", [None, "egl", "osmesa"])
def test_a_frame_renders_whatever_was_imported_first(backend: str | None, tmp_path: Path) -> None:
    variables = {} if backend is None else {"MUJOCO_GL": backend}
    code, out, err, _ = _run([sys.executable, "-c", RENDER], tmp_path, **variables)
    assert code == 0, err[-3000:]
    picked, *_ = out.split()
    assert picked == (backend or "egl"), out  # unset: EGL first (Mesa's llvmpipe here)
    assert out.split()[-1] == "1", out  # not a blank frame


def _one_line_refusal(code: int, out: str, err: str, *names: str) -> None:
    assert code == 2, (code, out, err)
    assert out == "", out
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1, err
    assert "Traceback" not in err
    for name in names:
        assert name in lines[0], lines[0]


@pytest.mark.parametrize(
    "verb",
    [
        ["learn", "--wait", "60"],
        ["camera", "--log-level", "error"],
        ["film", "no-such-session"],
        ["demo"],
    ],
    ids=["learn", "camera", "film", "demo"],
)
def test_a_backend_that_cannot_start_is_one_line_before_anything(
    verb: list[str], tmp_path: Path
) -> None:
    """glfw with no display: refused at once, before a wait, a session or a service starts
    (learn against an endpoint where nothing listens would otherwise wait 60 s)."""
    argv = ["archery", *verb]
    if verb[0] in ("learn", "camera"):
        argv += ["--connect", free_tcp_endpoint()]
    code, out, err, took = _run(argv, tmp_path, MUJOCO_GL="glfw")
    _one_line_refusal(code, out, err, "MUJOCO_GL=glfw", "display", "egl", "osmesa")
    assert took < 30, took
    assert not (tmp_path / "runs").exists() or not any((tmp_path / "runs").iterdir())


def test_unknown_backend_and_disagreeing_variables(tmp_path: Path) -> None:
    code, out, err, _ = _run(["archery", "film", "x"], tmp_path, MUJOCO_GL="vulkan")
    _one_line_refusal(code, out, err, "MUJOCO_GL=vulkan", "egl, osmesa, glfw, glx")
    code, out, err, _ = _run(
        ["archery", "film", "x"], tmp_path, MUJOCO_GL="egl", PYOPENGL_PLATFORM="osmesa"
    )
    _one_line_refusal(code, out, err, "MUJOCO_GL=egl", "PYOPENGL_PLATFORM=osmesa")
    code, out, err, _ = _run(["archery", "film", "x"], tmp_path, MUJOCO_GL="disable")
    _one_line_refusal(code, out, err, "rendering is off", "MUJOCO_GL=disable")
