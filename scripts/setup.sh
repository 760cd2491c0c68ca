#!/usr/bin/env bash
# Set-up for envisat-pose on a fresh Debian/Ubuntu machine: the off-screen GL packages MuJoCo renders with,
# a Python 3.11 virtual environment in .venv, and the package (which compiles the MuJoCo gravity plugin).
# Safe to run again: it does only what is missing or out of date.
set -euo pipefail
cd "$(dirname "$0")/.."

PYTHON=${PYTHON:-python3.11}
TORCH_CPU_INDEX=${TORCH_CPU_INDEX:-https://download.pytorch.org/whl/cpu}
GL_PACKAGES=(libosmesa6 libegl1 libegl-mesa0 libgl1-mesa-dri)

# 1. Debian packages for off-screen rendering (OSMesa on the CPU, EGL where a GPU is).
if command -v dpkg-query >/dev/null 2>&1; then
  missing=()
  for pkg in "${GL_PACKAGES[@]}"; do
    dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed" || missing+=("$pkg")
  done
  if [ ${#missing[@]} -gt 0 ]; then
    if [ "$(id -u)" = "0" ]; then
      echo "setup: installing off-screen GL packages: ${missing[*]}"
      export DEBIAN_FRONTEND=noninteractive
      apt-get update -qq
      apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
    else
      echo "setup: error: missing Debian packages for off-screen rendering: ${missing[*]}" >&2
      echo "setup: install them as root: sudo apt-get install -y ${missing[*]}" >&2
      exit 1
    fi
  fi
elif ! ldconfig -p 2>/dev/null | grep -q libOSMesa; then
  echo "setup: warning: no dpkg here and libOSMesa was not found; install OSMesa (or EGL) for rendering" >&2
fi

# 1b. `make test-slow` and `make test-all` (WITH_VIEWER_CHECK=1) also want Chromium: a test opens a recording in the Rerun web viewer,
# headless with software GL. Optional: without it (and not root) that one test skips.
if [ "${WITH_VIEWER_CHECK:-0}" = "1" ] && command -v dpkg-query >/dev/null 2>&1 \
    && ! command -v chromium >/dev/null 2>&1; then
  if [ "$(id -u)" = "0" ]; then
    echo "setup: installing chromium (the web-viewer test)"
    export DEBIAN_FRONTEND=noninteractive
    apt-get update -qq && apt-get install -y -qq --no-install-recommends chromium >/dev/null \
      || echo "setup: warning: could not install chromium; the web-viewer test will skip" >&2
  else
    echo "setup: note: chromium is not installed; the web-viewer test will skip (sudo apt-get install chromium)" >&2
  fi
fi

# 1c. With them, Mesa's Vulkan drivers (lavapipe, on the CPU): two tests render foreign frames with MuJoCo's
# Filament renderer (tests/bench/test_foreign_frames.py), which needs a Vulkan driver. Optional: without it they skip.
if [ "${WITH_VIEWER_CHECK:-0}" = "1" ] && command -v dpkg-query >/dev/null 2>&1 \
    && ! dpkg-query -W -f='${Status}' mesa-vulkan-drivers 2>/dev/null | grep -q "install ok installed"; then
  if [ "$(id -u)" = "0" ]; then
    echo "setup: installing mesa-vulkan-drivers (the Filament tests)"
    export DEBIAN_FRONTEND=noninteractive
    apt-get update -qq && apt-get install -y -qq --no-install-recommends mesa-vulkan-drivers >/dev/null \
      || echo "setup: warning: could not install mesa-vulkan-drivers; the Filament tests will skip" >&2
  else
    echo "setup: note: mesa-vulkan-drivers is not installed; the Filament tests will skip" >&2
  fi
fi

# 2. The virtual environment.
if ! command -v "$PYTHON" >/dev/null 2>&1; then
  echo "setup: error: $PYTHON not found; envisat-pose needs Python 3.11 (set PYTHON=/path/to/python3.11)" >&2
  exit 1
fi
if [ ! -x .venv/bin/python ]; then
  echo "setup: creating .venv with $PYTHON"
  "$PYTHON" -m venv .venv
fi

# 3. The package and its pinned dependencies, again only when the build inputs changed.
stamp=$(cat pyproject.toml setup.py datagen/plugin/relative_gravity.c | sha256sum | cut -c1-16)
if [ "$(cat .venv/.setup-stamp 2>/dev/null)" != "$stamp" ] || ! ls datagen/plugin/_relative_gravity*.so >/dev/null 2>&1; then
  echo "setup: installing envisat-pose and its dependencies into .venv (first time: a few minutes)"
  .venv/bin/python -m pip install -q --upgrade pip
  # torch first, exactly the pinned CPU build: PyPI's torch==2.13.0 for Linux is the CUDA build (a few GB more, and
  # triton), so the +cpu one from PyTorch's CPU index (or a local wheel pip is pointed at). Where neither is
  # reachable, the pin from the usual index, with a note.
  if ! .venv/bin/python -m pip install -q --retries 1 --extra-index-url "$TORCH_CPU_INDEX" "torch==2.13.0+cpu" \
      2>/dev/null; then
    echo "setup: note: no torch==2.13.0+cpu ($TORCH_CPU_INDEX unreachable); installing torch==2.13.0 (CUDA build)" >&2
    .venv/bin/python -m pip install -q "torch==2.13.0"
  fi
  # dev: pytest and ruff; test and bench: what only the tests and the benchmarks import (filterpy, webdataset)
  .venv/bin/python -m pip install -q -e ".[dev,test,bench]"
  echo "$stamp" > .venv/.setup-stamp
fi
