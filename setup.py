"""Builds the relative-gravity MuJoCo plugin at install time.

Everything else about the package is in pyproject.toml. The plugin is an ordinary shared library (MuJoCo
loads it with ctypes through the `mujoco.plugins` entry point), compiled against the headers and the
libmujoco of the mujoco wheel in the build environment.
"""

import os

import mujoco
from setuptools import Extension, setup

_MUJOCO_DIR = os.path.dirname(mujoco.__file__)
_LIBMUJOCO = f"libmujoco.so.{mujoco.__version__}"

gravity_plugin = Extension(
    "envisat_pose.datagen.plugin._relative_gravity",
    sources=["datagen/plugin/relative_gravity.c"],
    include_dirs=[os.path.dirname(mujoco.HEADERS_DIR)],
    extra_compile_args=["-O2", "-std=c11", "-D_GNU_SOURCE", "-Wall"],
    # Linked by soname, as MuJoCo's bundled plugins are: at run time `import mujoco` has already loaded
    # that library, so the loader reuses it whatever the rpath says.
    extra_link_args=[f"-L{_MUJOCO_DIR}", f"-l:{_LIBMUJOCO}", "-Wl,-rpath,$ORIGIN/../../mujoco", "-lm"],
)

setup(ext_modules=[gravity_plugin])
