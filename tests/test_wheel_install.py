"""The package as a user gets it: a wheel, installed with pip (not editable) into a fresh venv, runs
`envisat simulate` from an unrelated folder, finds the MJCF as package data and loads the gravity plugin."""

import os
import shutil
import subprocess
import sys
import sysconfig

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def run(cmd, **kw):
    proc = subprocess.run(cmd, capture_output=True, text=True, **kw)
    assert proc.returncode == 0, f"{cmd} failed:\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}"
    return proc


def test_wheel_installs_and_simulates_from_another_folder(tmp_path):
    # the tracked sources only (no in-place build products), as a fresh clone has them
    src = tmp_path / "src"
    files = run(["git", "ls-files", "-z"], cwd=ROOT).stdout.split("\0")
    for rel in filter(None, files):
        os.makedirs(src / os.path.dirname(rel), exist_ok=True)
        shutil.copy2(os.path.join(ROOT, rel), src / rel, follow_symlinks=False)  # envisat_pose/<layer> links
    wheels = tmp_path / "wheels"
    run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(wheels), str(src)])
    (wheel,) = list(wheels.glob("envisat_pose-*.whl"))

    venv = tmp_path / "venv"
    run([sys.executable, "-m", "venv", str(venv)])
    py = venv / "bin" / "python"
    # the dependencies (torch, mujoco, ...) come from this environment's site-packages through a .pth line;
    # a path line adds the folder only: this environment's editable-install hook is not run there
    site = run([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"]).stdout.strip()
    with open(os.path.join(site, "deps.pth"), "w") as fh:
        fh.write(sysconfig.get_paths()["purelib"] + "\n")
    run([str(py), "-m", "pip", "install", "--no-deps", "--no-index", "-q", str(wheel)])

    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "ENVISAT_MODEL")}
    where = run([str(py), "-c", "import envisat_pose.datagen.plugin as p, envisat_pose.geometry as g; "
                 "print(p.__file__); print(g.model_path())"], cwd=elsewhere, env=env).stdout.split()
    assert all(path.startswith(site) for path in where), where  # the installed copy, not the repository
    models = os.path.dirname(where[1])  # the installed models folder (envisat.xml in it)
    for name in ("envisat.xml", "detector.safetensors", "upper_stage.xml", "upper_stage_detector.safetensors"):
        assert os.path.isfile(os.path.join(models, name)), name  # a shipped target's own detector ships with it
    run([str(venv / "bin" / "envisat"), "simulate", "--duration-s", "20", "--dt-s", "2", "--out", "run.npz",
         "--quiet"], cwd=elsewhere, env=env)
    with np.load(elsewhere / "run.npz", allow_pickle=False) as z:
        assert z["x"].shape == (11, 12)
        assert abs(np.linalg.norm(z["x"][0, 0:3]) - 50.0) < 1e-9  # the default 50 m V-bar hold
