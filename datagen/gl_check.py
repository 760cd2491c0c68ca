"""The renderer's GL platform checked without choosing one (datagen/gl_platform.py chooses, on import): a job that
renders calls check_gl_platform before any work, in the process that starts it, so a platform that cannot render
off-screen is one line (InputError) rather than a traceback from MuJoCo's import or from a renderer process. Also
triton loaded before Mesa's LLVM (load_triton_before_mesa), for gl_platform.py and the tests' conftest."""

from __future__ import annotations

import importlib
import importlib.util
import os
import sys

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


def load_triton_before_mesa() -> None:
    """Import triton now where it is installed (PyPI's torch==2.13.0 is the CUDA build and brings it; the CPU build
    does not), before Mesa's libLLVM loads (`import mujoco` under MUJOCO_GL=osmesa, or the first GL context): its own
    LLVM loaded after Mesa's segfaults the process (Debian 12's Mesa 22.3, LLVM 15; triton 3.7), and torch imports
    it when the first optimizer is built. Loaded first, both work. Where Mesa's is already loaded (mujoco imported
    under osmesa first) nothing is done: importing triton then would crash here. A broken triton is left to torch."""
    if "triton" in sys.modules or importlib.util.find_spec("triton") is None or _mesa_llvm_loaded():
        return
    try:
        importlib.import_module("triton")
    except Exception:
        pass


def _mesa_llvm_loaded() -> bool:
    """Whether a libLLVM is mapped into this process (Linux: /proc/self/maps; elsewhere: whether mujoco is)."""
    try:
        with open("/proc/self/maps") as maps:
            return any("libLLVM" in line for line in maps)
    except OSError:
        return "mujoco" in sys.modules
