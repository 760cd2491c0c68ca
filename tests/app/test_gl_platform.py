"""MUJOCO_GL: osmesa and egl render; unset or blank is osmesa; any other value is one line naming it, before any
work, from every verb and library call that renders (not a traceback from MuJoCo's import, from the renderer or from
a renderer process)."""

import os
import subprocess
import sys

import pytest

from envisat_pose.app.cli import main
from envisat_pose.config import InputError


def cli(args: list[str], gl: str, cwd) -> subprocess.CompletedProcess:
    """The command line in a fresh process (MuJoCo reads MUJOCO_GL when it is first imported)."""
    env = {**os.environ, "MUJOCO_GL": gl}
    return subprocess.run([sys.executable, "-m", "envisat_pose.app.cli", *args], capture_output=True, text=True,
                          env=env, cwd=cwd, timeout=300)


def test_a_value_mujoco_refuses_at_import_is_one_line(tmp_path):
    p = cli(["simulate", "--duration-s", "2", "--out", "t.npz", "--quiet"], "bogus", tmp_path)
    assert p.returncode == 2, p.stderr
    assert p.stderr.startswith("envisat simulate: error: MUJOCO_GL='bogus': ") and p.stderr.count("\n") == 1
    assert "osmesa" in p.stderr and "egl" in p.stderr and not os.listdir(tmp_path)


def test_a_blank_value_renders_as_unset(tmp_path):
    p = cli(["generate", "--num-images", "1", "--shard-size", "1", "--resolution", "64", "--out", "d", "--quiet"],
            "", tmp_path)
    assert p.returncode == 0, p.stderr
    assert "manifest.json" in os.listdir(tmp_path / "d")


@pytest.mark.parametrize("verb", [
    ["generate", "--num-images", "2", "--shard-size", "2", "--resolution", "64", "--workers", "2"],
    ["run", "--duration-s", "5"],
    ["train", "--online", "--resolution", "64", "--steps", "1", "--batch-size", "2", "--render-workers", "1"],
])
def test_a_platform_that_cannot_render_off_screen_is_one_line_before_any_work(verb, tmp_path, monkeypatch,
                                                                              capsys):
    monkeypatch.setenv("MUJOCO_GL", "glfw")
    out = tmp_path / "out"
    assert main([*verb, "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"envisat {verb[0]}: error: MUJOCO_GL='glfw': ") and err.count("\n") == 1
    assert not out.exists()


def test_the_library_calls_that_render_refuse_it_too(tmp_path, monkeypatch):
    from envisat_pose import GenerateConfig, RunConfig, run_closed_loop, run_generate

    monkeypatch.setenv("MUJOCO_GL", "glfw")
    with pytest.raises(InputError, match="MUJOCO_GL='glfw'"):
        run_generate(GenerateConfig(num_images=1, shard_size=1, resolution_px=64), tmp_path / "d")
    with pytest.raises(InputError, match="MUJOCO_GL='glfw'"):
        run_closed_loop(RunConfig(duration_s=5.0), tmp_path / "r")
    assert not os.listdir(tmp_path)


def test_renderer_processes_take_a_blank_value_as_unset(monkeypatch):
    from envisat_pose.pipelines.detector.render_pool import gl_environment

    monkeypatch.setenv("MUJOCO_GL", " ")
    assert gl_environment("cuda", 1)["MUJOCO_GL"] == "egl"
    assert gl_environment("cpu", 1)["MUJOCO_GL"] == "osmesa"
