"""Simulation: the MuJoCo iCub scene, arrow physics and the paper's analytic ballistic world.

Importing the package picks the rendering backend (`sim.gl_backend.select`) before any of its
modules imports `mujoco`, which reads `MUJOCO_GL` only then.
"""

from archery.sim.gl_backend import select as _select_rendering_backend

_select_rendering_backend()
