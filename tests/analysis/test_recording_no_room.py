"""A tracker recording (analysis/recording_stream.py, TrackRecorder) whose file the OS stops taking: Rerun's file
writer thread only logs the OS's reason, and its flush then waited forever (an `envisat run` or `track` that
filled its disk hung at its end) or raised a RuntimeError without the reason (a traceback, where a full disk is
one line). Now close() raises the OSError naming the file, and leaves no file."""

import json
import os
import subprocess
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
SCRIPT = r"""
import json, os, resource, sys
import numpy as np
from envisat_pose.analysis.recording import TrackRecorder
from envisat_pose.geometry import load_camera

out = sys.argv[1]
# `ulimit -f` (EFBIG) stands for a full disk (ENOSPC): Rerun's writer meets either the same way
resource.setrlimit(resource.RLIMIT_FSIZE, (400_000, resource.getrlimit(resource.RLIMIT_FSIZE)[1]))
K = 8
est = {"t_s": 0.0, "x_hat": np.r_[0.0, 50.0, 0.0, np.zeros(9)], "P": np.eye(12) * 0.01, "status": 1, "p_best": 1.0,
       "nis": 3.0, "nis_dof": 10, "corners_px": np.full((K, 2), np.nan), "visible": np.zeros(K, bool),
       "rejected": np.zeros(K, bool), "roi_px": np.full(3, np.nan)}
rec = TrackRecorder(f"save:{out}/track.rrd", load_camera(), with_truth=False)
rng = np.random.default_rng(0)
for k in range(4):  # noise frames: ~0.7 MB each as JPEG, past the limit
    rec.log_frame(k, dict(est, t_s=float(k)), rng.integers(0, 256, (1024, 1024), dtype=np.uint8))
try:
    rec.close()
    print(json.dumps({"raised": None}))
except Exception as e:
    print(json.dumps({"raised": type(e).__name__, "errno": getattr(e, "errno", None),
                      "filename": getattr(e, "filename", None)}))
sys.stdout.flush()
os._exit(0)  # Rerun's own exit waits on its dead writer thread where stdout and stderr are pipes (left as it is)
"""


def test_a_recording_the_os_stops_taking_is_one_oserror_naming_its_file_and_leaves_no_file(tmp_path):
    import errno

    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in (ROOT, os.environ.get("PYTHONPATH")) if p)}
    # the timeout only guards against the hang this test is about
    done = subprocess.run([sys.executable, "-c", SCRIPT, str(tmp_path)], capture_output=True, text=True,
                          timeout=120, env=env, cwd=tmp_path)
    assert done.returncode == 0, done.stderr[-2000:]
    got = json.loads(done.stdout.strip().splitlines()[-1])
    assert got["raised"] == "OSError" and got["errno"] == errno.EFBIG, got
    assert os.path.basename(got["filename"]).startswith(".tmp-") and got["filename"].endswith(".rrd"), got
    assert os.listdir(tmp_path) == []  # neither the broken recording (renamed as if whole) nor the probe
