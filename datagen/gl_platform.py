"""The renderer's headless GL platform: MUJOCO_GL chosen before MuJoCo loads (osmesa unless the user set one; with
egl, EGL_PLATFORM surfaceless), and the GL context class of that platform. MuJoCo picks its GL platform when it is
imported: a module that renders with MuJoCo imports this one before it imports mujoco (datagen/render.py,
datagen/render_model.py)."""

from __future__ import annotations

import os

# MuJoCo picks its GL platform at import: choose a headless one unless the user did (platform-notes.md).
os.environ.setdefault("MUJOCO_GL", "osmesa")
if os.environ["MUJOCO_GL"].lower() == "egl":
    os.environ.setdefault("EGL_PLATFORM", "surfaceless")


def gl_context_class():
    """The GL context class of the platform named by MUJOCO_GL (osmesa or egl; default osmesa)."""
    backend = os.environ.get("MUJOCO_GL", "osmesa").lower()
    if backend == "egl":
        from mujoco.egl import GLContext
    elif backend == "osmesa":
        from mujoco.osmesa import GLContext
    else:
        raise RuntimeError(f"MUJOCO_GL={backend!r}: the image factory renders headless with 'osmesa' or 'egl'")
    return GLContext
