"""The bench scripts' shared command line (bench/_common.py), read from their source: each one's --help describes it
in whole sentences (its docstring's first paragraph), each takes --out (default its bench/results/<name>.json, whatever
the working folder) and records its provenance (commit, UTC date, arguments with their seeds). Beside that, the
defects a user met: datagen_speed.py's --help ran the benchmark, memory.py's traced Tracker.step lacked a parameter,
target_tracking.py's stand-in handed the Tracker 4 x 4 frames."""

import argparse
import ast
import importlib.util
import inspect
import json
import os
import re
import subprocess
import sys

import numpy as np
import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
BENCH = os.path.join(ROOT, "bench")
SCRIPTS = sorted(f for f in os.listdir(BENCH) if f.endswith(".py") and not f.startswith("_"))
FOLDER_OUT = ("foreign_frames.py",)  # --out: the folder of frames it makes (meta.json records the provenance)


def load(name: str):
    spec = importlib.util.spec_from_file_location(f"bench_{name}", os.path.join(BENCH, f"{name}.py"))
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def calls(tree: ast.AST, name: str) -> list[ast.Call]:
    """The calls of a function or method called `name`."""
    return [n for n in ast.walk(tree) if isinstance(n, ast.Call)
            and (getattr(n.func, "id", None) == name or getattr(n.func, "attr", None) == name)]


def test_every_script_is_seen():
    assert len(SCRIPTS) >= 25 and "datagen_speed.py" in SCRIPTS


@pytest.mark.parametrize("script", SCRIPTS)
def test_each_script_describes_itself_takes_out_and_records_its_provenance(script):
    with open(os.path.join(BENCH, script), encoding="utf-8") as fh:
        tree = ast.parse(fh.read())
    desc = load("_common").description(ast.get_docstring(tree, clean=False))
    assert desc[-1] in ".?" and "\n\n" not in desc, f"{script}: --help's description {desc[-60:]!r}"
    parsers = calls(tree, "WholeFlagParser")  # bench/_common.py's: whole flags only
    assert len(parsers) == 1 and not calls(tree, "ArgumentParser")
    assert [ast.unparse(k.value) for k in parsers[0].keywords if k.arg == "description"] == ["description(__doc__)"]
    outs = [c for c in calls(tree, "add_argument") if c.args and getattr(c.args[0], "value", None) == "--out"]
    assert len(outs) == 1, f"{script}: no --out"
    if script not in FOLDER_OUT:
        default = [ast.unparse(k.value) for k in outs[0].keywords if k.arg == "default"]
        name = script[:-3]
        assert default and (f"'{name}.json'" in default[0] or f"results_path('{name}')" in default[0]), default
    assert calls(tree, "provenance"), f"{script}: its JSON records no provenance"


def test_a_bench_refuses_an_abbreviated_flag(tmp_path):
    """`--seed 0` was read as edge_truth.py's `--seeds 0` and `--dur` as online_speed.py's `--duration-s`: each is
    argparse's usage error now (exit 2, before any work)."""
    for script, typed in (("edge_truth.py", ["--seed", "0"]), ("online_speed.py", ["--dur", "1"])):
        out = subprocess.run([sys.executable, os.path.join(BENCH, script), *typed, "--out", str(tmp_path / "x.json")],
                             capture_output=True, text=True, timeout=120, cwd=tmp_path)
        assert out.returncode == 2 and f"unrecognized arguments: {' '.join(typed)}" in out.stderr, out.stderr[-2000:]


def test_provenance_names_the_commit_the_date_and_every_argument(monkeypatch):
    common = load("_common")
    monkeypatch.setattr(sys, "argv", ["bench/x.py", "--seed", "3"])
    monkeypatch.setattr(common, "git_hash", lambda: "0123abc+dirty")
    p = common.provenance(argparse.Namespace(seed=3, seeds=[0, 1], out=os.path.join("a", "x.json")))
    assert p["commit"] == "0123abc+dirty" and p["argv"] == ["--seed", "3"]
    assert p["args"] == {"seed": 3, "seeds": [0, 1], "out": os.path.join("a", "x.json")}
    assert re.fullmatch(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\dZ", p["date_utc"])
    assert json.loads(json.dumps(p)) == p
    monkeypatch.setattr(common, "git_hash", lambda: "unknown")  # no checkout, no ENVISAT_SOURCE_GIT
    assert common.provenance()["commit"] is None and common.provenance()["args"] is None


def test_results_path_is_the_repositorys_whatever_the_working_folder(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert load("_common").results_path("ukf_speed") == os.path.join(ROOT, "bench", "results", "ukf_speed.json")


def test_datagen_speed_help_prints_help_without_running(tmp_path):
    path = os.path.join(BENCH, "datagen_speed.py")
    out = subprocess.run([sys.executable, path, "--help"], capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert out.returncode == 0 and out.stdout.startswith("usage:") and "--out" in out.stdout, out.stderr[-2000:]
    assert "two-pass floor (" not in out.stdout  # the benchmark's first line
    bad = subprocess.run([sys.executable, path, "--baseline", "x"], capture_output=True, text=True, timeout=120,
                         cwd=tmp_path)
    assert bad.returncode == 2 and "--targets" in bad.stderr


def test_memorys_traced_step_takes_every_argument_of_the_trackers_step():
    from envisat_pose.pipelines.tracking.tracker import Tracker

    traced = next(n for n in ast.walk(ast.parse(load("memory").CHILD))
                  if isinstance(n, ast.FunctionDef) and n.name == "traced")
    passes_all = traced.args.vararg is not None and traced.args.kwarg is not None
    names = [a.arg for a in traced.args.args]
    assert passes_all or names == list(inspect.signature(Tracker.step).parameters)


def test_target_trackings_stand_in_tracks_on_frames_of_the_cameras_size():
    """The stand-in's frames carry their index for its detector and have the camera's size, which the Tracker
    checks (a 4 x 4 frame was refused); a short noisy-truth run goes through."""
    from envisat_pose.geometry import load_camera

    bench = load("target_tracking")
    camera = load_camera()
    img = bench.frame_image(300, camera)
    assert img.shape == (camera.height_px, camera.width_px) and img.dtype == np.uint8
    assert int(img[0, 0]) * 256 + int(img[0, 1]) == 300
    target = bench.ROOT / "models" / "upper_stage.xml"
    scores = bench.noisy_truth_run(str(target), "default", 0, 10.0, 1.0, 0.1)
    assert scores["second_half"]["frames"] > 0


def test_target_trackings_first_correct_median_is_over_the_runs_that_had_one():
    """pooled's median time to the first correct track: over the runs that had one, with their count (one run
    without a correct track made the scenario's median None, hiding seven that had one); None only when none did."""
    bench = load("target_tracking")

    def row(first_s):
        return {"time_to_first_correct_track_s": {"median": first_s}, "first_track_correct": first_s is not None,
                "false_lock_s": 0.0, "scored": {"frames": 0}, "real_time_factor": 9.0,
                "second_half": {"frames": 151, "claimed": 0, "sq_position_m2": 0.0, "sq_attitude_deg2": 0.0}}

    p = bench.pooled([row(t) for t in (104.0, None, 30.0, 60.0)])
    assert p["time_to_first_correct_track_s_median"] == 60.0 and p["time_to_first_correct_track_runs"] == 3
    assert p["first_track_correct"] == 3
    p = bench.pooled([row(t) for t in (20.0, 40.0)])
    assert p["time_to_first_correct_track_s_median"] == 30.0 and p["time_to_first_correct_track_runs"] == 2
    p = bench.pooled([row(None), row(None)])
    assert p["time_to_first_correct_track_s_median"] is None and p["time_to_first_correct_track_runs"] == 0
