"""triton (brought by the CUDA build of torch, PyPI's torch==2.13.0) loads before Mesa's LLVM: loaded after it,
the first optimizer built segfaults the process (datagen/gl_check.py load_triton_before_mesa). gl_platform loads it
before MuJoCo, and the tests' conftest before pytest collects the modules that import mujoco under osmesa."""

import importlib.util
import os
import subprocess
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
HAS_TRITON = importlib.util.find_spec("triton") is not None


def python(code: str, extra_path: str | None = None) -> subprocess.CompletedProcess:
    paths = [p for p in (extra_path, ROOT, os.environ.get("PYTHONPATH")) if p]
    env = {**os.environ, "MUJOCO_GL": "osmesa", "PYTHONPATH": os.pathsep.join(paths)}
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)


def test_gl_platform_loads_an_installed_triton_before_mujoco(tmp_path):
    fake = tmp_path / "triton"
    fake.mkdir()
    (fake / "__init__.py").write_text("import sys\nAFTER_MUJOCO = 'mujoco' in sys.modules\n")
    p = python("import sys\nimport envisat_pose.datagen.gl_platform\nassert 'triton' in sys.modules, 'not loaded'\n"
               "import mujoco\nimport triton\nassert not triton.AFTER_MUJOCO\n", extra_path=str(tmp_path))
    assert p.returncode == 0, p.stderr


def test_not_after_mesas_llvm_where_mujoco_loaded_it_first(tmp_path):
    """A spawned worker imports mujoco (MUJOCO_GL=osmesa inherited) before gl_platform: triton is not imported
    then, which would crash the worker."""
    fake = tmp_path / "triton"
    fake.mkdir()
    (fake / "__init__.py").write_text("")
    p = python("import sys\nimport mujoco\nimport envisat_pose.datagen.gl_platform\n"
               "mesa = any('libLLVM' in line for line in open('/proc/self/maps'))\n"
               "assert not (mesa and 'triton' in sys.modules)\n", extra_path=str(tmp_path))
    assert p.returncode == 0, p.stderr


def test_the_test_session_loaded_an_installed_triton_first():
    assert not HAS_TRITON or "triton" in sys.modules


@pytest.mark.skipif(not HAS_TRITON, reason="the CPU build of torch: no triton")
def test_an_optimizer_after_mujoco_under_osmesa_does_not_crash():
    p = python("import envisat_pose.datagen.gl_platform\nimport mujoco\nimport torch\n"
               "torch.optim.AdamW([torch.zeros(1, requires_grad=True)])\n")
    assert p.returncode == 0, (p.returncode, p.stderr[-2000:])
