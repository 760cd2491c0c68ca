"""The renderer's GL platform checked without choosing one (datagen/gl_platform.py chooses, on import): a job that
renders calls check_gl_platform before any work, in the process that starts it, so a platform that cannot render
off-screen is one line (InputError) rather than a traceback from MuJoCo's import or from a renderer process."""

from __future__ import annotations

import os

from envisat_pose.config import InputError

HEADLESS = ("osmesa", "egl")  # what renders off-screen on a machine without a display


def check_gl_platform() -> str | None:
    """The headless platform MUJOCO_GL names ('osmesa' or 'egl'), None where it is unset or blank (the job's
    default then: osmesa, or egl for a CUDA device's renderer processes); any other value is one InputError line
    naming it and the two that render."""
    value = os.environ.get("MUJOCO_GL", "")
    if not value.strip():
        return None
    if value.strip().lower() not in HEADLESS:
        raise InputError(f"MUJOCO_GL={value!r}: MuJoCo renders headless here with MUJOCO_GL=osmesa (on the CPU; the "
                         "default where it is unset) or MUJOCO_GL=egl (EGL_PLATFORM=surfaceless without a GPU)")
    return value.strip().lower()
