"""scripts/setup.sh installs the CPU build of torch (PyPI's torch==2.13.0 for Linux is the CUDA one, with triton)
from PyTorch's CPU index, and the plain pin, with a note, only where that build cannot be had. Run on a copy with
a stand-in .venv/bin/python that logs its pip calls (the GL packages reported installed)."""

import os
import shutil
import subprocess
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
FAKE_PYTHON = """#!/usr/bin/env bash
echo "$*" >> "$(dirname "$0")/calls.log"
case "$*" in *+cpu*) [ "$CPU_WHEEL" = 1 ] || exit 1 ;; esac
"""


def run_setup(tmp_path, cpu_wheel: bool) -> tuple[subprocess.CompletedProcess, list[str]]:
    for rel in ("scripts/setup.sh", "pyproject.toml", "setup.py", "datagen/plugin/relative_gravity.c"):
        os.makedirs(tmp_path / os.path.dirname(rel), exist_ok=True)
        shutil.copy(os.path.join(ROOT, rel), tmp_path / rel)
    (tmp_path / "datagen/plugin/_relative_gravity.so").write_bytes(b"")
    venv_bin = tmp_path / ".venv/bin"
    venv_bin.mkdir(parents=True)
    (venv_bin / "python").write_text(FAKE_PYTHON)
    (venv_bin / "python").chmod(0o755)
    fake_bin = tmp_path / "bin"
    fake_bin.mkdir()
    (fake_bin / "dpkg-query").write_text("#!/bin/sh\nprintf 'install ok installed'\n")
    (fake_bin / "dpkg-query").chmod(0o755)
    env = {**os.environ, "PATH": f"{fake_bin}{os.pathsep}{os.environ['PATH']}", "PYTHON": sys.executable,
           "CPU_WHEEL": "1" if cpu_wheel else "0", "WITH_VIEWER_CHECK": "0",
           "TORCH_CPU_INDEX": "https://cpu.invalid/whl"}
    p = subprocess.run(["bash", str(tmp_path / "scripts/setup.sh")], capture_output=True, text=True, env=env,
                       timeout=60)
    return p, (venv_bin / "calls.log").read_text().splitlines()


@pytest.mark.skipif(shutil.which("bash") is None, reason="no bash")
def test_torch_is_the_cpu_build_from_the_cpu_index(tmp_path):
    p, calls = run_setup(tmp_path, cpu_wheel=True)
    assert p.returncode == 0, p.stderr
    torch = [c for c in calls if "torch" in c]
    assert torch == ["-m pip install -q --retries 1 --extra-index-url https://cpu.invalid/whl torch==2.13.0+cpu"]
    assert "note" not in p.stderr


@pytest.mark.skipif(shutil.which("bash") is None, reason="no bash")
def test_without_the_cpu_build_the_plain_pin_with_a_note(tmp_path):
    p, calls = run_setup(tmp_path, cpu_wheel=False)
    assert p.returncode == 0, p.stderr
    assert [c for c in calls if "torch" in c][-1] == "-m pip install -q torch==2.13.0"
    assert "no torch==2.13.0+cpu (https://cpu.invalid/whl unreachable)" in p.stderr
