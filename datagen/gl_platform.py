"""The renderer's headless GL platform: MUJOCO_GL chosen before MuJoCo loads (osmesa unless the user set one; set
but blank counts as unset; with egl, EGL_PLATFORM surfaceless), and the GL context class of that platform. MuJoCo
picks its GL platform when it is imported: a module that renders with MuJoCo imports this one before it imports
mujoco (datagen/render.py, datagen/render_model.py). Any other platform is refused in one line (datagen/gl_check.py;
the jobs that render check it before any work)."""

from __future__ import annotations

import os

from envisat_pose.datagen.gl_check import check_gl_platform, load_triton_before_mesa

load_triton_before_mesa()  # before MuJoCo loads Mesa's LLVM (gl_check.py says why)
# MuJoCo picks its GL platform at import: choose a headless one unless the user did (platform-notes.md).
if not os.environ.get("MUJOCO_GL", "").strip():
    os.environ["MUJOCO_GL"] = "osmesa"
if os.environ["MUJOCO_GL"].strip().lower() == "egl":
    os.environ.setdefault("EGL_PLATFORM", "surfaceless")


def gl_context_class():
    """The GL context class of the platform named by MUJOCO_GL (osmesa or egl; default osmesa); any other: the
    InputError of check_gl_platform."""
    if check_gl_platform() == "egl":
        from mujoco.egl import GLContext
    else:
        from mujoco.osmesa import GLContext
    return GLContext
