"""Every entity a recording holds is named in the layout analysis/recording.py documents (the paths a user's
script or blueprint reads): the writers' (simulate, estimate) and a tracker's run, with and without a truth, read
back with Rerun's own reader. A tracker's corners_detected, roi, NEES, status... were written and named nowhere."""

import os
import re
import sys

import numpy as np

from envisat_pose.analysis import recording
from envisat_pose.analysis.recording import TrackRecorder, read_recording
from envisat_pose.geometry import load_camera

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))  # the folder's own helpers
from test_recording_blueprint import estimates  # noqa: E402


def documented_patterns() -> list[re.Pattern]:
    """The paths of the docstring's layout tables (lines indented four spaces: the first word, or several paths
    joined by ", "), {a,b} expanded, <name> one path component."""
    out = []
    for line in recording.__doc__.splitlines():
        if not line.startswith("    ") or line.startswith("     "):
            continue
        column = re.match(r"(?:[\w{}<>,/]+, )*[\w{}<>,/]+", line.strip()).group(0)
        for item in column.split(", "):
            paths = [item]
            while any("{" in p for p in paths):
                p = next(p for p in paths if "{" in p)
                head, alts, tail = re.match(r"(.*?)\{([^}]*)\}(.*)", p).groups()
                paths.remove(p)
                paths += [head + a + tail for a in alts.split(",")]
            out += [re.compile("/" + re.sub(r"<[a-z]+>", "[^/]+", re.escape(p).replace(r"\<", "<").replace(r"\>", ">"))
                               + "$") for p in paths]
    return out


def undocumented(path) -> list[str]:
    static, temporal = read_recording(str(path))
    patterns = documented_patterns()
    missing = []
    for entity in set(static) | set(temporal):
        if any(p.match(entity) for p in patterns):
            continue
        parts = entity.split("/")  # a child described in prose as ".../model/keypoints" under a documented path
        if any(any(p.match("/".join(parts[:i])) for p in patterns) and f".../{'/'.join(parts[i:])}" in recording.__doc__
               for i in range(2, len(parts))):
            continue
        missing.append(entity)
    return sorted(missing)


def tracked_run(path, with_truth: bool) -> None:
    cam = load_camera().scaled(64, 64)
    rec = TrackRecorder(f"save:{path}", cam, with_truth=with_truth, title="layout")
    x = np.zeros(12)
    x[:3] = cam.pos_C_m + cam.R_K_from_C.T @ np.array([0.0, 0.0, 60.0])
    for k, status in enumerate([0, 1, 1]):  # acquiring, then tracking: every series logged
        est = {"t_s": float(k), "x_hat": x, "P": np.eye(12) * 1e-4, "status": status, "p_best": 0.9, "nis": 2.0,
               "nis_dof": 4, "corners_px": np.full((8, 2), 30.0), "visible": np.ones(8, bool),
               "rejected": np.arange(8) == 3, "roi_px": np.array([10.0, 12.0, 40.0])}
        truth = {"x_true": x, "corners_true_px": np.full((8, 2), 31.0), "in_frame": np.ones(8, bool)} \
            if with_truth else {}
        rec.log_frame(k, est, np.full((64, 64), 50, np.uint8), **truth)
    rec.close()


def test_every_entity_of_every_recording_is_documented(tmp_path):
    for with_truth in (True, False):
        tracked_run(tmp_path / f"run{with_truth}.rrd", with_truth)
        assert undocumented(tmp_path / f"run{with_truth}.rrd") == []
    recording.write_estimates_recording(str(tmp_path / "est.rrd"), estimates())
    assert undocumented(tmp_path / "est.rrd") == []
