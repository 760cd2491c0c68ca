"""bench/target_estimation.py's speed check asserts that no run diverged: runs that end before the divergence
monitors are armed (filter.divergence_settle_steps, 60 steps of paper-all-0.02's 1 s) are never judged, so the
assert held whatever the filter did. Such a `--speed-duration-s` is refused in argparse's one line, before any work;
one long enough is taken."""

import importlib.util
import os
import subprocess
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
SCRIPT = os.path.join(ROOT, "bench", "target_estimation.py")


def test_a_speed_duration_too_short_to_be_judged_is_refused_before_any_work(tmp_path):
    out = tmp_path / "x.json"
    run = subprocess.run([sys.executable, SCRIPT, "--speed-duration-s", "30", "--speed-runs", "1", "--speed-repeats",
                          "1", "--runs", "1", "--duration-s", "5", "--settle-s", "1", "--out", str(out)],
                         capture_output=True, text=True, timeout=120, cwd=tmp_path)  # refused at once
    assert run.returncode == 2, run.stderr[-2000:]
    line = run.stderr.strip().splitlines()[-1]
    assert "--speed-duration-s: 30 s gives 31 steps" in line and "divergence_settle_steps" in line, line
    assert "expected at least 60 s" in line and not out.exists()


def test_the_shortest_judged_speed_duration_is_taken():
    spec = importlib.util.spec_from_file_location("bench_target_estimation", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    assert mod.speed_unjudged(60.0) is None and mod.speed_unjudged(600.0) is None
    assert "59.9 s gives 60 steps" in mod.speed_unjudged(59.9)
