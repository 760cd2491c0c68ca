"""The relative-orbit gravity plugin (C), loaded into MuJoCo through the `mujoco.plugins` entry point."""

import ctypes
import glob
import os

PLUGIN_NAME = "envisat.relative_gravity"
_HANDLES = []


def library_path() -> str:
    """Path of the compiled plugin library next to this file."""
    here = os.path.dirname(os.path.abspath(__file__))
    found = sorted(glob.glob(os.path.join(here, "_relative_gravity*.so")))
    if not found:
        raise FileNotFoundError(
            f"the relative-gravity plugin is not built in {here}: reinstall the package "
            "(pip install -e .), which compiles it against mujoco's headers"
        )
    return found[0]


def load() -> None:
    """Load the plugin library once; its constructor registers the plugin with MuJoCo.

    Called by `import mujoco` (entry point group `mujoco.plugins`), so it must not import mujoco itself.
    """
    if not _HANDLES:
        _HANDLES.append(ctypes.CDLL(library_path()))
