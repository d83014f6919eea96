"""Where the rendering backend is picked: MuJoCo's `MUJOCO_GL`, PyOpenGL's
`PYOPENGL_PLATFORM`.

MuJoCo reads `MUJOCO_GL` once, when `mujoco` is first imported, and PyOpenGL reads
`PYOPENGL_PLATFORM` when `OpenGL` is first imported; a process that imports either before the
variables are set renders through GLFW, which needs a display (`mujoco.FatalError: an OpenGL
platform library has not been loaded into this process`). So `select()` runs when the `sim`
package is imported, `renderer_ready()` before every MuJoCo renderer is made, and `check()` is
the preflight of every verb that renders; each one's docstring says what it does.
"""

from __future__ import annotations

import ctypes
import os
import sys
from typing import Any

from archery.protocol.errors import ConfigError

__all__ = ["HEADLESS", "RenderBackendError", "check", "renderer_ready", "select"]

# backend -> the shared libraries it loads (any one name of each tuple), as Debian names them
_LIBRARIES: dict[str, tuple[tuple[str, ...], ...]] = {
    "egl": (("libEGL.so.1", "libEGL.so"), ("libOpenGL.so.0", "libOpenGL.so", "libGL.so.1")),
    "osmesa": (("libOSMesa.so.8", "libOSMesa.so.6", "libOSMesa.so"),),
}
# what provides them, on Debian/Ubuntu
_PACKAGES = {
    "egl": "libegl1 libegl-mesa0 libgl1-mesa-dri libopengl0",
    "osmesa": "libosmesa6",
}
HEADLESS = ("egl", "osmesa")  # tried in this order when MUJOCO_GL is unset
_ALL = ("egl", "osmesa", "glfw", "glx")
_OFF = ("disable", "disabled", "off", "false", "0")
_state: dict[str, Any] = {"checked": None}


class RenderBackendError(ConfigError):
    """No rendering backend starts in this process (exit status 2: bad configuration)."""


def _loads(backend: str) -> bool:
    """Whether every library `backend` needs loads in this process."""
    for names in _LIBRARIES.get(backend, ()):
        for name in names:
            try:
                ctypes.CDLL(name)
                break
            except OSError:
                continue
        else:
            return False
    return True


def _install_hint() -> str:
    return "; ".join(f"MUJOCO_GL={b} needs {_PACKAGES[b]} (apt install)" for b in HEADLESS)


def select() -> str | None:
    """The backend this process renders with; sets `MUJOCO_GL` (and `PYOPENGL_PLATFORM` for
    EGL and OSMesa) in `os.environ` when they are unset. None: rendering is off
    (`MUJOCO_GL=disable`), or `MUJOCO_GL` is unset and no headless backend's libraries load
    (physics still runs; `check()` says what to install).

    It runs when the `sim` package is imported, before any of its modules imports `mujoco`:
    with `MUJOCO_GL` unset it picks the first headless backend whose libraries load, EGL (GPU
    or Mesa's llvmpipe) then OSMesa, and sets both variables for this process and its children.
    A `MUJOCO_GL` the user set is kept (`egl`, `osmesa`, `glfw`, `glx`; `disable` turns
    rendering off).
    """
    given = os.environ.get("MUJOCO_GL", "").strip().lower()
    if given in _OFF:
        return None
    if not given:
        given = next((b for b in HEADLESS if _loads(b)), "")
        if not given:
            return None
        os.environ["MUJOCO_GL"] = given
    if given in HEADLESS and not os.environ.get("PYOPENGL_PLATFORM"):
        os.environ["PYOPENGL_PLATFORM"] = given
    return given


def _context_class(backend: str) -> Any:
    """MuJoCo's GL context class for `backend` (imports PyOpenGL for EGL and OSMesa).

    Raises:
        RenderBackendError: `PYOPENGL_PLATFORM` names another platform.
    """
    platform = os.environ.get("PYOPENGL_PLATFORM", "").lower()
    if backend in HEADLESS and platform and platform != backend:
        raise RenderBackendError(
            f"MUJOCO_GL={backend} but PYOPENGL_PLATFORM={platform}: set both to the same "
            f"backend, or unset both to let archery pick one"
        )
    if backend == "egl":
        from mujoco.egl import GLContext
    elif backend == "osmesa":
        from mujoco.osmesa import GLContext
    else:
        from mujoco.glfw import GLContext
    return GLContext


def renderer_ready() -> None:
    """Make sure MuJoCo's renderer opens its context with the selected backend, whatever was
    imported first.

    It runs before every MuJoCo renderer is made (`sim.render.SceneRenderer`): should `mujoco`
    have been imported before `sim` (a user's script, a test importing `mujoco` first), it
    points MuJoCo's renderer at the selected backend's context class, so the import order does
    not matter.

    Raises:
        RenderBackendError: rendering is off or has no backend (`check` explains), or the
            variables disagree.
    """
    backend = select()
    if backend is None:
        check()  # raises with the reason
        return
    from mujoco.rendering.classic import gl_context

    wanted = _context_class(backend)
    if getattr(gl_context, "GLContext", None) is not wanted:
        gl_context.GLContext = wanted  # mujoco was imported before `sim`: MUJOCO_GL unread


def _failure(backend: str, picked: bool, exc: BaseException) -> RenderBackendError:
    origin = "picked because MUJOCO_GL is unset" if picked else "from MUJOCO_GL"
    why = " ".join(f"{type(exc).__name__}: {exc}".split())[:200]
    return RenderBackendError(
        f"the rendering backend does not start: tried MUJOCO_GL={backend} ({origin}): {why}. "
        f"Set MUJOCO_GL to a backend this machine has, or install one: {_install_hint()}"
    )


def check() -> str:
    """Open and free a 16×16 context with the selected backend (once per process); the
    backend's name.

    The preflight of every verb that renders (camera, film, demo, learn's film, record's scene
    view, selfcheck): it raises `RenderBackendError` (one line: the variable, what was tried,
    what to install) before any session starts, instead of a traceback after it.

    Raises:
        RenderBackendError: rendering is off, no backend's libraries load, or the backend does
            not start; the message names `MUJOCO_GL`, what was tried and what to install.
    """
    if _state["checked"] is not None:
        return str(_state["checked"])
    given = os.environ.get("MUJOCO_GL", "").strip().lower()
    if given in _OFF and given:
        raise RenderBackendError(
            f"rendering is off (MUJOCO_GL={given}): unset MUJOCO_GL to let archery pick a "
            f"backend, or set it to one of {', '.join(_ALL)}"
        )
    if given and given not in _ALL:
        raise RenderBackendError(
            f"MUJOCO_GL={given} is not a rendering backend: use one of {', '.join(_ALL)}, or "
            f"unset it to let archery pick one"
        )
    backend = select()
    if backend is None:
        tried = ", ".join(f"{b} ({' + '.join(n[0] for n in _LIBRARIES[b])})" for b in HEADLESS)
        raise RenderBackendError(
            f"no rendering backend: MUJOCO_GL is unset and none of {tried} loads. "
            f"Install one: {_install_hint()}"
        )
    if backend == "glfw" and sys.platform.startswith("linux") and not _has_display():
        raise RenderBackendError(
            f"MUJOCO_GL=glfw needs a display and DISPLAY/WAYLAND_DISPLAY is unset: unset "
            f"MUJOCO_GL to let archery pick a headless backend, or set it to egl or osmesa "
            f"({_install_hint()})"
        )
    if backend in HEADLESS and not _loads(backend):
        names = " + ".join(n[0] for n in _LIBRARIES[backend])
        raise RenderBackendError(
            f"MUJOCO_GL={backend} needs {names}, which do not load here: install "
            f"{_PACKAGES[backend]} (apt install), or unset MUJOCO_GL to let archery pick a "
            f"backend this machine has"
        )
    try:
        context = _context_class(backend)(16, 16)
        try:
            context.make_current()
        finally:
            context.free()
    except RenderBackendError:
        raise
    except Exception as exc:  # each backend fails its own way (ImportError, FatalError, …)
        raise _failure(backend, not given, exc) from exc
    _state["checked"] = backend
    return backend


def _has_display() -> bool:
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))
